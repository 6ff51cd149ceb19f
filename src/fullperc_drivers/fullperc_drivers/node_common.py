"""What the three driver nodes share above their cores: QoS, topic tokens, the health parameters, console throttle,
the frame-in-one-message record of the two trackers.

Every driver node has the same shape: a ROS-free core/backend whose thread only puts items into a
:class:`~fullperc_drivers.handoff.Handoff`; the executor drains it, publishes, and feeds one
:class:`fullperc_common.health.Health`, whose verdict a timer publishes through
:class:`fullperc_common.diagnostics.Diagnostics`; ``main`` is :func:`fullperc_common.node_main.run_node`, and
``close()`` stops the core's threads before the node is destroyed, so nothing calls into rclpy after shutdown.

ROS conventions the three share (docs/nodes.md "Namespaces and parameters"): topic names are relative
(``omc/<body>/pose``, ``ots/<tool>/pose``, ``diana/joint_states``), so ``-r __ns:=/or1`` moves every topic of
the node to ``/or1/...`` and the default namespace gives the familiar ``/omc/...``; ``/tf`` and ``/diagnostics``
stay global (tf2 and diagnostic_aggregator listen there). Every parameter is declared read-only
(:func:`fullperc_common.params.declare_fixed`): a driver reads its parameters once, to open the device and
build its pipeline, so a run-time ``set_parameters`` is refused with the reason instead of reporting a success
that changes nothing.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable

from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from fullperc_common.health import OK, Health, HealthConfig, Verdict
from fullperc_common.params import declare_fixed

HEALTH_PERIOD_S = 0.25  # how often the nodes evaluate their health ladder


def topic_name(name: str) -> str:
    """A device body/tool name as a ROS topic token: other characters become ``_``, no leading digit."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", name.strip())
    return s if s and not s[0].isdigit() else f"b_{s}"


def tracked_body(q, pose):
    """The TrackedBody of one body of a device frame (``<prefix>/bodies``): its TrackingQuality ``q``'s fields, as
    published, and ``pose`` (geometry_msgs/Pose: the published pose, all zeros when none was)."""
    from fullperc_msgs.msg import TrackedBody

    return TrackedBody(name=q.body, visible=q.visible, pose=pose, fit_error=q.fit_error, frame_number=q.frame_number,
                       markers_used=q.markers_used, port_status=q.port_status)


def make_qos(kind: str, depth: int) -> QoSProfile:
    if kind == "sensor":
        return qos_profile_sensor_data
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def declare_health(node, frames_stale_after_s: float | None = None) -> HealthConfig:
    """Declare ``health.stale_after_s``, ``health.reconnect_window_s`` and ``health.max_reconnects``."""
    cfg = HealthConfig(
        stale_after_s=declare_fixed(node, "health.stale_after_s", 2.0, lambda v: v > 0, "> 0 s",
                                    "an item without a good output for this long leaves OK [s]"),
        frames_stale_after_s=frames_stale_after_s,
        reconnect_window_s=declare_fixed(node, "health.reconnect_window_s", 10.0, lambda v: v > 0, "> 0 s",
                                         "window over which reconnects are counted [s]"),
        max_reconnects=declare_fixed(node, "health.max_reconnects", 3, lambda v: v >= 1, ">= 1",
                                     "reconnects within the window that make the level WARN while outputs flow"),
    )
    return cfg


class ConsoleThrottle:
    """Log one line per key at once, then at most every ``period_s`` with the latest text and a repeat count.

    A device that cannot be reached fails every couple of seconds, a garbled link many times a second: the
    operator needs the reason on the console, not a flood of it.
    """

    def __init__(self, logger: Callable[[], object], period_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._logger = logger
        self.period_s = period_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def __call__(self, key: str, text: str, level: str = "warning") -> bool:
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        n = self._suppressed.pop(key, 0)
        if n:
            text += f" ({n} more time{'s' if n != 1 else ''} in the last {now - last:.0f} s)"
        log = self._logger()
        # rclpy binds a severity to each call site ("Logger severity cannot be changed between calls"): one each
        if level == "info":
            log.info(text)
        elif level == "error":
            log.error(text)
        else:
            log.warning(text)
        self._last[key] = now
        return True


_LEVEL_WORD = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


class HealthReport:
    """Publishes a :class:`Health` verdict as one ``/diagnostics`` status and logs its level changes (throttled)."""

    def __init__(self, diag, name: str, health: Health, console: ConsoleThrottle) -> None:
        self.diag, self.name, self.health, self.console = diag, name, health, console
        self.level: int | None = None

    def publish(self, values: dict | None = None, conditions=()) -> Verdict:
        v = self.health.verdict(conditions)
        self.diag.set_verdict(self.name, v, values)
        if self.level is not None and v.level != self.level:  # the first verdict (start-up) is not news
            if v.level == OK:
                self.console(f"health:{self.name}:0", f"{self.name}: OK again ({v.message})", level="info")
            else:  # one throttle per level: an ERROR is never hidden behind a WARN line
                self.console(f"health:{self.name}:{v.level}",
                             f"{self.name}: {_LEVEL_WORD.get(v.level, v.level)}: {v.message}")
        self.level = v.level
        return v
