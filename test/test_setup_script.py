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


def test_the_venv_is_a_proper_ament_prefix_for_colcon(tmp_path):
    """env.sh puts the wheel venv on AMENT_PREFIX_PATH; colcon must accept it without the warning that the path
    "doesn't contain any 'local_setup.*' files" (printed on every build before), and the setup files colcon
    generates (which chain that prefix's local_setup.<shell>) must still source cleanly."""
    root = workspace_root()
    empty = tmp_path / "no_packages"
    empty.mkdir()
    build = subprocess.run(
        ["bash", "-c", 'source scripts/env.sh && colcon --log-base "$1/log" build --base-paths "$1/no_packages" '
                       '--build-base "$1/build" --install-base "$1/install"', "build", str(tmp_path)],
        cwd=str(root), capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr
    assert "local_setup" not in build.stdout + build.stderr, build.stdout + build.stderr
    for shell in ("bash", "sh"):
        script = tmp_path / "install" / f"setup.{shell}"
        src = subprocess.run([shell, "-c", '. "$1" && echo sourced', shell, str(script)], capture_output=True,
                             text=True, timeout=60)
        assert src.returncode == 0 and "sourced" in src.stdout, (shell, src.stdout, src.stderr)
        assert "not found" not in src.stderr, (shell, src.stderr)  # every chained local_setup.<shell> exists
