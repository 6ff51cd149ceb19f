"""Helpers for fullperc's multi-process tests (imported by tests and by the root conftest).

Pure Python: starting installed executables in their own process groups, making sure they are
gone afterwards, polling with a liveness bound, and a DDS domain id no other test on this machine holds.
"""

from __future__ import annotations

import fcntl
import itertools
import os
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO

import pytest


def workspace_root() -> Path:
    """The workspace root: $FULLPERC_ROOT (set by scripts/env.sh) or the current directory."""
    return Path(os.environ.get("FULLPERC_ROOT", os.getcwd()))


DOMAIN_IDS = range(1, 201)   # Fast DDS: 7400 + 250 d + participant ports stay below 65535 for these
_claims = itertools.count()


class DomainLease:
    """A ROS_DOMAIN_ID held by this process until :meth:`release` (or the process ends).

    Why a lock file and not a number derived from the pid: two test runs on one machine (two terminals, a helper
    beside CI, the benches while the tests run) that picked the same id see each other's topics (with two suites
    at once, test_two_local_sources.py saw a fused mean error of 419 mm against its 0.69 mm bound, most likely
    another test's tool poses). Each id is an exclusive
    ``flock`` on ``<tmp>/fullperc-ros-domains/<id>.lock``: the kernel drops it when the holder exits, even on
    SIGKILL, so a crashed run never leaves an id taken. The file descriptor is not inherited by child processes
    (PEP 446), so a node started under the id does not keep it after the test.
    """

    def __init__(self, domain: int, lock: IO[str]) -> None:
        self.domain = domain
        self._lock: IO[str] | None = lock

    def release(self) -> None:
        if self._lock is not None:
            self._lock.close()     # closing the only descriptor drops the flock
            self._lock = None

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def claim_domain(ids: range = DOMAIN_IDS, lock_dir: Path | None = None) -> DomainLease:
    """The first free id of ``ids``, searched from a per-process and per-claim offset (successive tests of one run
    take different ids, so a peer that outlives its test by a moment cannot meet the next test). Raises
    RuntimeError when every id is held."""
    d = lock_dir or Path(tempfile.gettempdir()) / "fullperc-ros-domains"
    d.mkdir(parents=True, exist_ok=True)
    start = os.getpid() * 7 + next(_claims)
    for k in range(len(ids)):
        dom = ids[(start + k) % len(ids)]
        f = open(d / f"{dom}.lock", "a")   # noqa: SIM115 (held open: the lock lives as long as the descriptor)
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.close()
            continue
        return DomainLease(dom, f)
    raise RuntimeError(f"every ROS domain id in {ids} is held by another test process (lock files in {d})")


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

    def start_split(self, args: list[str], name: str, **kw) -> subprocess.Popen:
        """Like :meth:`start`, with stdout and stderr in separate files (read with :meth:`out` / :meth:`err`)."""
        out = open(self.tmp / f"{name}.out", "wb")  # noqa: SIM115 - closed with the process
        err = open(self.tmp / f"{name}.err", "wb")  # noqa: SIM115
        p = self.start(args, name=name, stdout=out, stderr=err, **kw)
        p.out_path, p.err_path = self.tmp / f"{name}.out", self.tmp / f"{name}.err"  # type: ignore[attr-defined]
        return p

    @staticmethod
    def out(p: subprocess.Popen) -> str:
        return Path(p.out_path).read_text(errors="replace")  # type: ignore[attr-defined]

    @staticmethod
    def err(p: subprocess.Popen) -> str:
        return Path(p.err_path).read_text(errors="replace")  # type: ignore[attr-defined]

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


def wait_for(pred, timeout: float = 20.0, interval: float = 0.05, what: str = "condition",
             detail: Callable[[], object] | None = None):
    """Poll ``pred`` until truthy (returned) or fail the test after ``timeout`` seconds.

    This is a liveness bound for multi-process tests (a hung peer must not hang CI), not a
    performance assertion. ``detail``: called on timeout only, its result appended to the failure
    message (what the peers had done by then), so a failure says why.
    """
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(interval)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}" + (f": {detail()}" if detail else ""))


def poll_until(pred, timeout: float, interval: float = 0.05):
    """Like :func:`wait_for` but returns None on timeout instead of failing (for scripts outside pytest)."""
    end = time.monotonic() + timeout
    while True:
        v = pred()
        if v or time.monotonic() >= end:
            return v or None
        time.sleep(interval)


class SpunNode:
    """A node of this process spun by its own executor in a background thread: the listeners of tests and soaks.

    A subclass calls ``super().__init__(context, name)``, creates its subscriptions on ``self.node`` (guarding shared
    state with ``self.lock``), then calls :meth:`start`; :meth:`close` stops the thread and destroys the node.
    """

    def __init__(self, context, name: str) -> None:
        import threading

        from rclpy.node import Node

        self.node = Node(name, context=context)
        self.lock = threading.Lock()
        self._context = context
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        import threading

        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=self._context)
        self.ex.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True, name=self.node.get_name())
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
            self.ex.shutdown()
        self.node.destroy_node()


class TopicCounter(SpunNode):
    """Counts messages on topics in this process (own node, spun in a background thread).

    Subscribes best effort, which matches reliable and best-effort publishers alike: for tests that only
    need to know that data flows (and how much), not every message.
    """

    def __init__(self, context, topics: dict[str, type], node_name: str = "fullperc_topic_counter") -> None:
        from rclpy.qos import qos_profile_sensor_data

        super().__init__(context, node_name)
        self.counts = dict.fromkeys(topics, 0)
        for topic, msg_type in topics.items():
            self.node.create_subscription(msg_type, topic, lambda _m, t=topic: self._count(t), qos_profile_sensor_data)
        self.start()

    def _count(self, topic: str) -> None:
        with self.lock:
            self.counts[topic] += 1

    def count(self, topic: str) -> int:
        with self.lock:
            return self.counts[topic]

    def call(self, srv_type, name: str, request, timeout: float = 20.0):
        """Call a service from this node; the response, or None when it did not answer within ``timeout``."""
        cli = self.node.create_client(srv_type, name)
        try:
            if not poll_until(cli.service_is_ready, timeout):
                return None
            fut = cli.call_async(request)
            return fut.result() if poll_until(fut.done, timeout) else None
        finally:
            self.node.destroy_client(cli)
