"""Hand items from a device thread (SDK callback, socket reader) to the ROS executor without busy-waiting.

Why: vendor SDKs call us on their own thread, and a blocking ``recv`` needs a thread too, but publishing
and all node state belong to the executor thread. :class:`Handoff` is a bounded queue plus a wake-up
callable (in the nodes: :class:`ExecutorWake`, which schedules the drain callback on the executor that spins the
node). The producer side never raises: it is called from C through ctypes, where an exception would be lost or
abort the process.

:class:`UdpReceiver` is the socket-reader thread used by the stream backends: it blocks in ``recvfrom``
(with a short timeout only so that ``close`` is prompt) and stamps each datagram with the host receive
time: the kernel's receive timestamp (``SO_TIMESTAMPNS``, CLOCK_REALTIME = the ``time.time_ns`` domain)
where available, so the thread's wake-up delay does not enter the clock-offset samples; otherwise
``time.time_ns()`` right after ``recvmsg`` returns.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux value; not exported by every Python build
_TIMESPEC = struct.Struct("@qq")


class Handoff(Generic[T]):
    """Bounded thread-safe queue; ``put`` never blocks or raises, overflow drops the oldest item."""

    def __init__(self, maxlen: int = 256, notify: Callable[[], None] | None = None) -> None:
        self._q: deque[T] = deque()
        self._maxlen = maxlen
        self._lock = threading.Lock()
        self.notify = notify
        self.overflow = 0
        self.notify_errors = 0

    def put(self, item: T) -> None:
        try:
            with self._lock:
                self._q.append(item)
                if len(self._q) > self._maxlen:
                    self._q.popleft()
                    self.overflow += 1
            if self.notify is not None:
                self.notify()
        except Exception:  # noqa: BLE001 - must never propagate into a C callback thread
            self.notify_errors += 1

    def drain(self) -> list[T]:
        with self._lock:
            items = list(self._q)
            self._q.clear()
        return items

    def __len__(self) -> int:
        with self._lock:
            return len(self._q)


class ExecutorWake:
    """``Handoff.notify`` of a node: ``drain`` runs on the executor that spins ``node``, called from any thread.

    Why not a guard condition (rclpy's usual hand-off): rclpy 7.1's EventsExecutor runs none, so a node with one
    spins on the SingleThreadedExecutor, which rebuilds its wait set in Python on every wake-up -- a third of
    diana_state's py-spy samples in the demo graph, where it wakes per device frame. ``Executor.create_task`` is
    thread-safe on both executors (it queues the call and wakes the executor; checked in test_executor_wake.py).
    At most one drain is scheduled at a time: an item handed over while one waits is taken by it. Before the node
    is spinning (no ``node.executor``) nothing is scheduled: the node's periodic timer drains what came meanwhile
    (call :meth:`catch_up` there)."""

    def __init__(self, node, drain: Callable[[], None]) -> None:
        self._node = node
        self._drain = drain
        self._lock = threading.Lock()
        self._scheduled = False

    def __call__(self) -> None:
        with self._lock:
            if self._scheduled:
                return
            ex = self._node.executor
            if ex is None:
                return
            self._scheduled = True
        ex.create_task(self._run)

    def _run(self) -> None:
        with self._lock:
            self._scheduled = False
        self._drain()

    def catch_up(self) -> None:
        """On the executor: drain now if no drain is scheduled (what came before the node was spinning)."""
        if not self._scheduled:
            self._drain()


class UdpReceiver:
    """Thread that receives datagrams on ``host:port`` and calls ``on_datagram(data, recv_ns)``."""

    def __init__(self, host: str, port: int, on_datagram: Callable[[bytes, int], None],
                 bufsize: int = 65536, name: str = "udp-rx") -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._sock.bind((host, int(port)))
        except OSError as e:
            self._sock.close()
            raise OSError(f"cannot bind UDP {host}:{port}: {e}") from e
        self._sock.settimeout(0.2)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            self.kernel_timestamps = True
        except OSError:
            self.kernel_timestamps = False
        self.address = self._sock.getsockname()
        self._on = on_datagram
        self._bufsize = bufsize
        self._stop = threading.Event()
        self.errors = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, anc, _, _ = self._sock.recvmsg(self._bufsize, 64)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                self.errors += 1
                time.sleep(0.05)
                continue
            recv_ns = time.time_ns()
            for level, kind, payload in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(payload)
                    recv_ns = min(recv_ns, sec * 1_000_000_000 + nsec)
            try:
                self._on(data, recv_ns)
            except Exception:  # noqa: BLE001 - a bad datagram handler must not kill the reader
                self.errors += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()
