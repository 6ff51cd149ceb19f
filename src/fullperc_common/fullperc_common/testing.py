"""Helpers for fullperc's multi-process tests (imported by tests and by the root conftest).

Pure Python: starting installed executables in their own process groups, making sure they are
gone afterwards, and polling with a liveness bound.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest


def workspace_root() -> Path:
    """The workspace root: $FULLPERC_ROOT (set by scripts/env.sh) or the current directory."""
    return Path(os.environ.get("FULLPERC_ROOT", os.getcwd()))


def installed_exe(pkg: str, exe: str) -> str:
    """Path of an executable as `ros2 run pkg exe` would exec it (install/<pkg>/lib/<pkg>/<exe>)."""
    path = workspace_root() / "install" / pkg / "lib" / pkg / exe
    if not path.exists():
        pytest.fail(f"{path} is not built; run `make build`")
    return str(path)


class Procs:
    """Starts processes in their own process groups and guarantees they are gone after the test."""

    def __init__(self, env: dict[str, str], tmp: Path) -> None:
        self.env = env
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []

    def start(self, args: list[str], name: str | None = None, **kw) -> subprocess.Popen:
        name = name or Path(args[0]).name
        log = open(self.tmp / f"{name}.log", "wb")  # noqa: SIM115 - closed with the process
        p = subprocess.Popen(args, env=kw.pop("env", self.env), stdout=kw.pop("stdout", log),
                             stderr=kw.pop("stderr", subprocess.STDOUT), start_new_session=True, **kw)
        p.log_path = self.tmp / f"{name}.log"  # type: ignore[attr-defined]
        self.procs.append(p)
        return p

    def stop(self, p: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 10.0) -> int:
        if p.poll() is None:
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                pass
            try:
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        return p.returncode

    def stop_all(self) -> None:
        for p in reversed(self.procs):
            self.stop(p)

    @staticmethod
    def log(p: subprocess.Popen) -> str:
        return Path(p.log_path).read_text(errors="replace")  # type: ignore[attr-defined]


def wait_for(pred, timeout: float = 20.0, interval: float = 0.05, what: str = "condition"):
    """Poll ``pred`` until truthy (returned) or fail the test after ``timeout`` seconds.

    This is a liveness bound for multi-process tests (a hung peer must not hang CI), not a
    performance assertion.
    """
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(interval)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
