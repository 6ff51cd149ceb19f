"""Fixtures shared by every test in the repository (pytest loads this rootdir conftest first).

DDS isolation: every test that talks DDS gets its own ROS_DOMAIN_ID (unique per process and
test, see DEVELOPERS notes) and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so nothing leaves this
machine and parallel pytest runs do not cross-talk.
"""

from __future__ import annotations

import itertools
import os
import sys
from pathlib import Path

import pytest

from fullperc_common.testing import Procs, installed_exe, wait_for  # noqa: F401 (re-exported)

ROOT = Path(__file__).resolve().parent
_counter = itertools.count()
# Domain ids 1..100 are safe for Fast DDS port arithmetic; spread by pid to keep parallel runs apart.
_base = (os.getpid() * 7) % 100


def _next_domain() -> int:
    return 1 + (_base + next(_counter)) % 100


@pytest.fixture
def ros_env(monkeypatch) -> dict[str, str]:
    """Environment (also applied to this process) with a test-unique ROS_DOMAIN_ID."""
    dom = str(_next_domain())
    monkeypatch.setenv("ROS_DOMAIN_ID", dom)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("PYTHONUNBUFFERED", "1")
    return dict(os.environ)


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

