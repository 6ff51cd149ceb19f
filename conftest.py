"""Fixtures shared by every test in the repository (pytest loads this rootdir conftest first).

DDS isolation: every test that talks DDS gets its own ROS_DOMAIN_ID (an id no other test process on
this machine holds: fullperc_common.testing.claim_domain) and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
so nothing leaves this machine and parallel pytest runs do not cross-talk.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from fullperc_common.testing import Procs, claim_domain, installed_exe, wait_for  # noqa: F401 (re-exported)

ROOT = Path(__file__).resolve().parent


@pytest.fixture
def ros_env(monkeypatch) -> Iterator[dict[str, str]]:
    """Environment (also applied to this process) with a ROS_DOMAIN_ID no other test on this machine holds
    (fullperc_common.testing.claim_domain), released after the test's processes are gone."""
    with claim_domain() as lease:
        monkeypatch.setenv("ROS_DOMAIN_ID", str(lease.domain))
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        monkeypatch.setenv("PYTHONUNBUFFERED", "1")
        yield dict(os.environ)


@pytest.fixture
def load_script():
    """Loader of ``scripts/<name>.py`` as a module (the scripts are run from a checkout, not installed): the tests
    of a script call its functions and its ``main`` in this process."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    return load


@pytest.fixture
def procs(ros_env, tmp_path):
    """Process launcher for multi-process tests; kills leftovers even when the test fails."""
    ps = Procs(ros_env, tmp_path)
    yield ps
    ps.stop_all()


@pytest.fixture
def rclpy_context(ros_env):
    """An initialised rclpy context for in-test nodes, shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    if ctx.ok():
        rclpy.shutdown(context=ctx)


@pytest.fixture
def python_exe() -> str:
    return sys.executable

