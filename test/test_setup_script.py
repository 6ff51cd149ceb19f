"""scripts/setup.sh: a failing pin stops setup with a message naming the package, and re-runs are no-ops.

These run the real script against a throw-away venv and requirement files; pip really fails to find
the bogus distribution on the index.
"""

import os
import subprocess
import sys
from pathlib import Path

from fullperc_common.testing import workspace_root

SETUP = str(workspace_root() / "scripts" / "setup.sh")


def _run(tmp_path: Path, python_lines: list[str]) -> subprocess.CompletedProcess:
    req = tmp_path / "req"
    req.mkdir(exist_ok=True)
    (req / "ros-jazzy.txt").write_text("# nothing from ROS in this test\n")
    (req / "python.txt").write_text("\n".join(python_lines) + "\n")
    env = dict(os.environ, PYTHON=sys.executable, VENV=str(tmp_path / "venv"), FULLPERC_USE_SYSTEM_ROS="0",
               FULLPERC_REQUIREMENTS=str(req), PIP_NO_INDEX="0")
    return subprocess.run(["bash", SETUP], env=env, capture_output=True, text=True, timeout=600)


def test_broken_pin_names_the_package(tmp_path):
    r = _run(tmp_path, ["fullperc-no-such-distribution==9.9.9"])
    assert r.returncode != 0
    assert "could not install 'fullperc-no-such-distribution==9.9.9'" in r.stderr
    assert "CMake" not in r.stderr


def test_missing_interpreter_is_named(tmp_path):
    env = dict(os.environ, PYTHON="python-does-not-exist", VENV=str(tmp_path / "v"))
    r = subprocess.run(["bash", SETUP], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "python-does-not-exist" in r.stderr


def test_second_setup_installs_nothing():
    """`make test` ran setup already; running it again must find everything up to date."""
    env = dict(os.environ)
    env.pop("FULLPERC_REQUIREMENTS", None)
    r = subprocess.run(["bash", SETUP], env=env, capture_output=True, text=True, timeout=120,
                       cwd=str(workspace_root()))
    assert r.returncode == 0, r.stderr
    assert "up to date" in r.stdout and "installing" not in r.stdout.lower()
