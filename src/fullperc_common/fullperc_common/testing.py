"""Helpers for fullperc's multi-process tests (imported by tests and by the root conftest).

Pure Python: starting installed executables in their own process groups, making sure they are
gone afterwards, polling with a liveness bound, and a DDS domain id no other test on this machine holds.
"""

from __future__ import annotations

import fcntl
import itertools
import os
import signal
import socket
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


def load_by_path(path: Path, name: str):
    """The Python module at ``path``, imported under ``name``: a sibling test module or script whose helpers a test
    reuses (the suite runs with --import-mode=importlib, so test modules are not importable by name)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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


class RosSession:
    """A DDS domain of its own, its environment, a :class:`Procs` and (on first use) an rclpy context.

    The module-scoped counterpart of the root conftest's ``ros_env`` / ``procs`` / ``rclpy_context`` fixtures: a
    module that starts one node (or one scenario) and checks it in several tests builds a session in a
    ``scope="module"`` fixture, and scenarios that must not see each other run side by side in sessions of their own.
    The context is initialised with the session's domain id (``rclpy.init(domain_id=...)``), so this process's
    environment is left alone; :meth:`close` stops the processes, shuts the context down and releases the id.
    """

    def __init__(self, tmp: Path, lease: DomainLease | None = None) -> None:
        self.lease = lease or claim_domain()
        self.domain = self.lease.domain
        self.tmp = tmp
        self.env = {**os.environ, "ROS_DOMAIN_ID": str(self.domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                    "PYTHONUNBUFFERED": "1"}
        self.procs = Procs(self.env, tmp)
        self._context = None

    @property
    def context(self):
        if self._context is None:
            import rclpy
            from rclpy.context import Context

            # the range is read from the environment when the participant is made: the repository's (env.sh) one
            os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
            ctx = Context()
            rclpy.init(context=ctx, domain_id=self.domain)
            self._context = ctx
        return self._context

    def close(self) -> None:
        try:
            self.procs.stop_all()
        finally:
            if self._context is not None and self._context.ok():
                import rclpy

                rclpy.shutdown(context=self._context)
            self.lease.release()

    def __enter__(self) -> RosSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SideBySide:
    """Scenarios that wait on other processes most of the time (a node starting, data sent in real time), run at
    once, each in a thread of its own: their waits overlap instead of adding up.

    ``jobs`` maps a name to a callable; :meth:`start` starts the named ones (all by default; a job starts once),
    :meth:`result` starts its job if need be, waits for it and returns its result or raises its exception (a
    ``pytest.fail`` of a ``wait_for`` included) -- in the test that asked for it. Give each job a
    :class:`RosSession` of its own, so the scenarios share nothing but this process.
    """

    def __init__(self, jobs: dict[str, Callable[[], object]]) -> None:
        self.jobs = dict(jobs)
        self._threads: dict[str, object] = {}
        self._results: dict[str, object] = {}
        self._errors: dict[str, BaseException] = {}

    def start(self, names=None) -> SideBySide:
        import threading

        for name in self.jobs if names is None else names:
            if name in self._threads:
                continue
            t = threading.Thread(target=self._run, args=(name,), daemon=True, name=f"side-by-side {name}")
            self._threads[name] = t
            t.start()
        return self

    def _run(self, name: str) -> None:
        try:
            self._results[name] = self.jobs[name]()
        except BaseException as e:  # noqa: BLE001 - raised in the test that asks for the result
            self._errors[name] = e

    def result(self, name: str):
        self.start([name])
        self._threads[name].join()  # type: ignore[attr-defined]
        if name in self._errors:
            raise self._errors[name]
        return self._results[name]

    def join(self) -> None:
        """Wait for every started job (a module fixture's teardown: no scenario outlives its module)."""
        for t in self._threads.values():
            t.join()  # type: ignore[attr-defined]


def selected_cases(request, names) -> list[str]:
    """Of ``names`` (test names as pytest shows them, ``test_x[param]``), those of the selected tests of the requesting
    module, in order: a module fixture starts only these scenarios (a test picked with ``-k`` runs its own scenario,
    not the whole module's); each test then asks for ``request.node.name``."""
    picked = []
    for item in request.session.items:
        if getattr(item, "module", None) is request.module and item.name in names and item.name not in picked:
            picked.append(item.name)
    return picked


def call_in_session(fn: Callable, session: RosSession, **kwargs):
    """Call ``fn``, a test body written against the root conftest's fixtures, with the session's counterparts of the
    ones it names (``procs``, ``ros_env``, ``rclpy_context``, ``tmp_path``, ``python_exe``) and ``kwargs``."""
    import inspect
    import sys

    supply = {"procs": lambda: session.procs, "ros_env": lambda: session.env, "rclpy_context": lambda: session.context,
              "tmp_path": lambda: session.tmp, "python_exe": lambda: sys.executable}
    args = {n: supply[n]() for n in inspect.signature(fn).parameters if n in supply and n not in kwargs}
    return fn(**args, **kwargs)


def side_by_side_fixture(*bodies: Callable, **named: Callable | tuple[Callable, dict]):
    """A module-scoped fixture ``scenarios``: a :class:`SideBySide` of test bodies, each run by
    :func:`call_in_session` in a :class:`RosSession` and a directory of its own, started at once for the module's
    selected tests. ``bodies`` are functions named ``_<x>``, the body of the test ``test_<x>``; ``named`` maps a test
    name as pytest shows it (``test_y[param]``: pass it with ``**{...}``) to a body or ``(body, kwargs)``. Each test
    then calls ``scenarios.result(request.node.name)``, which returns its body's result or raises what it raised.

    Usage (module level): ``scenarios = side_by_side_fixture(_a, _b, **{"test_c[x]": (_c, {"x": 1})})``.
    """
    import re

    jobs = {f"test{fn.__name__}": fn for fn in bodies} | named

    def run(fn, kwargs, tmp):
        with RosSession(tmp) as s:
            return call_in_session(fn, s, **kwargs)

    @pytest.fixture(scope="module", name="scenarios")
    def scenarios(request, tmp_path_factory):
        prepared = {}
        for name, job in jobs.items():
            fn, kwargs = job if isinstance(job, tuple) else (job, {})
            tmp = tmp_path_factory.mktemp(re.sub(r"\W", "_", name)[:40])   # here, not in the jobs: not thread-safe
            prepared[name] = (lambda fn=fn, kwargs=kwargs, tmp=tmp: run(fn, kwargs, tmp))
        sbs = SideBySide(prepared).start(selected_cases(request, prepared))
        yield sbs
        sbs.join()
    return scenarios


def udp_socket_off_dds_ports(host: str = "127.0.0.1") -> socket.socket:
    """A UDP socket bound to an ephemeral port of ``host`` that no Fast DDS participant of a test domain sends to.

    The RTPS default port mapping puts domain d's ports at 7400 + 250 d + offset (multicast 0 and 1, unicast
    10 + 2 i and 11 + 2 i for participant i), and with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` every participant
    sends discovery to its peers' unicast ports. A test socket that the OS happened to give such a port received
    another test's RTPS packets (a CI run: "bad Diana magic b'RTPS'"); ports at offsets below 60 (participants
    0-24) are not used.
    """
    while True:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind((host, 0))
        port = s.getsockname()[1]
        if port < 7400 or (port - 7400) % 250 >= 60:
            return s
        s.close()


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


def wait_for_first_line(procs: Procs, p: subprocess.Popen, timeout: float = 60.0) -> str:
    """Wait until ``p`` (started by ``procs``) has written a line or exited; its output so far.

    Make a test's subscriptions to a node after this: a node writes its first line once its DDS participant is up,
    and a reader made after a new participant appeared is matched with that participant's writers at once, while a
    reader that existed before often waits for Fast DDS's next periodic announcement (up to ~3 s; 0.5-3.6 s from a
    node's start to the first message on an old subscription, 0.2-0.4 s on a new one). A liveness bound only.
    """
    wait_for(lambda: p.poll() is not None or procs.log(p).strip(), timeout, what=f"{Path(p.args[0]).name}'s output")
    return procs.log(p)


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
