"""``echo /topic | head -n 2``: when the reader of the pipe exits, the installed ``echo`` stops quietly.

Python ignores SIGPIPE, so a write into a closed pipe raises BrokenPipeError; ``echo`` must end like a coreutils
program killed by SIGPIPE does (status 141, nothing on stderr), not with a traceback.
"""

from __future__ import annotations

import subprocess

from fullperc_common.testing import installed_exe


def test_echo_into_head_exits_quietly(procs, ros_env):
    procs.start([installed_exe("fullperc_eval", "pub"), "/test/pipe", "std_msgs/msg/String", '{"data": "tick"}',
                 "--rate", "50"], name="pub")
    script = 'set -o pipefail; "$0" /test/pipe --type std_msgs/msg/String --timeout 120 | head -n 2; ' \
             'echo "status=${PIPESTATUS[0]}"'
    p = subprocess.run(["bash", "-c", script, installed_exe("fullperc_eval", "echo")], capture_output=True,
                       text=True, timeout=300, env=ros_env)
    lines = p.stdout.splitlines()
    assert lines[:2] == ['{"data": "tick"}'] * 2, p.stdout + p.stderr
    assert lines[2] == "status=141", p.stdout + p.stderr  # as `yes | head -n 2`: SIGPIPE's status, not a crash
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr
    assert p.stderr.strip() == "", p.stderr
