"""A small /diagnostics publisher: one DiagnosticStatus per component, published at a fixed rate.

ROS's ``diagnostic_updater`` is not available as a wheel; this is the part of it we need.
Components call :meth:`Diagnostics.set` whenever their state changes; a timer publishes the
latest state of every component so late subscribers see it within one period.
"""

from __future__ import annotations

import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR
STALE = DiagnosticStatus.STALE


def as_level(v: bytes | int) -> int:
    """A diagnostic level as an int: Jazzy's message constants (OK, WARN, ...) are one-byte ``bytes``."""
    return v[0] if isinstance(v, bytes) else int(v)


class Diagnostics:
    def __init__(self, node, hardware_id: str = "", period_s: float = 1.0) -> None:
        self._node = node
        self._hw = hardware_id
        self._lock = threading.Lock()
        self._status: dict[str, DiagnosticStatus] = {}
        self.published = 0   # DiagnosticArrays sent so far: a component with per-period figures knows when a
        #                      period's values went out (fusion_node's input load)
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.period_s = period_s
        self._last_publish = time.monotonic()
        self._timer = node.create_timer(period_s, self.publish)

    def set(self, name: str, level: int, message: str, values: dict | None = None,
            publish_on_change: bool = False) -> None:
        """Store ``name``'s status; with ``publish_on_change`` a changed level is published at once.

        Publishing a level change immediately (not at the next period) keeps a health verdict's latency to
        its own evaluation period; messages and values alone never trigger a publish (no flooding).
        """
        # DiagnosticStatus.level is a byte; accept the message constants (bytes) and plain ints alike
        lvl = bytes([as_level(level)])
        st = DiagnosticStatus(
            level=lvl,
            name=f"{self._node.get_name()}: {name}",
            message=message,
            hardware_id=self._hw,
            values=[KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()],
        )
        with self._lock:
            prev = self._status.get(name)
            self._status[name] = st
        if publish_on_change and (prev is None or prev.level != st.level):
            self.publish()

    def set_verdict(self, name: str, verdict, values: dict | None = None) -> None:
        """Publish a :class:`fullperc_common.health.Verdict`: its level and message, ``values`` then its values."""
        self.set(name, verdict.level, verdict.message, {**(values or {}), **verdict.values}, publish_on_change=True)

    def publish(self) -> None:
        with self._lock:
            statuses = list(self._status.values())
        if not statuses:
            return
        arr = DiagnosticArray(status=statuses)
        arr.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(arr)
        self.published += 1
        self._last_publish = time.monotonic()

    def publish_if_overdue(self) -> bool:
        """Publish when the period's timer is a whole period late (nothing sent for two periods); True if it did.

        For a node whose own callbacks may keep its executor from running timers: fusion_node on rclpy's
        EventsExecutor, busy in input callbacks for a whole task on an overloaded machine, published no
        /diagnostics for 22 s -- its overload and lost-sample WARNs included. It calls this from its input path."""
        if time.monotonic() - self._last_publish < 2.0 * self.period_s:
            return False
        self.publish()
        return True
