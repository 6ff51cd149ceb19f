"""claim_domain: a ROS_DOMAIN_ID held by one test process is never handed to another on this machine."""

from __future__ import annotations

import subprocess
import sys

import pytest

from fullperc_common.testing import claim_domain

_CHILD = """
import sys
from pathlib import Path
from fullperc_common.testing import claim_domain
lease = claim_domain(range(1, 4), Path(sys.argv[1]))
print(lease.domain)
"""


def _claim_in_another_process(lock_dir) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _CHILD, str(lock_dir)], capture_output=True, text=True, timeout=60)


def test_held_ids_are_not_handed_out_again_in_this_or_another_process(tmp_path):
    a = claim_domain(range(1, 4), tmp_path)
    b = claim_domain(range(1, 4), tmp_path)
    assert a.domain != b.domain
    child = _claim_in_another_process(tmp_path)
    assert child.returncode == 0, child.stderr
    assert int(child.stdout) not in (a.domain, b.domain)   # the one id left
    # the child exited: the kernel dropped its lock, so its id is free again; with a and b held it is the only one
    with claim_domain(range(1, 4), tmp_path) as c:
        assert c.domain == int(child.stdout)
        with pytest.raises(RuntimeError, match="every ROS domain id"):
            claim_domain(range(1, 4), tmp_path)
        a.release()
        a.release()   # idempotent
        child = _claim_in_another_process(tmp_path)
        assert int(child.stdout) == a.domain      # released: the only free id
    b.release()


def test_a_child_process_does_not_inherit_the_lock(tmp_path):
    """A node started under the id must not keep it after the test (the descriptor is not inheritable)."""
    lease = claim_domain(range(1, 2), tmp_path)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lease.release()
        with claim_domain(range(1, 2), tmp_path) as again:   # would fail if the sleeper held the lock
            assert again.domain == 1
    finally:
        sleeper.kill()
        sleeper.wait()


def test_ros_env_fixture_holds_its_id(ros_env, tmp_path):
    """The fixture's id is held for the test: a claim over the default ids in another process never gets it."""
    from fullperc_common.testing import DOMAIN_IDS

    assert int(ros_env["ROS_DOMAIN_ID"]) in DOMAIN_IDS
    code = ("from fullperc_common.testing import claim_domain\nls = []\n"
            "while True:\n    try:\n        ls.append(claim_domain())\n    except RuntimeError:\n        break\n"
            "print(' '.join(str(x.domain) for x in ls))")   # every id still free (others may run tests too)
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert got.returncode == 0, got.stderr
    held = got.stdout.split()
    assert len(held) >= 100 and ros_env["ROS_DOMAIN_ID"] not in held
