"""``omc_driver``: NOKOV rigid bodies -> ``/omc/<body>/pose`` (PoseStamped, frame ``omc``) + ``/omc/<body>/quality``.

Also ``/omc/bodies`` (fullperc_msgs/TrackedBodies): every body of one device frame in one message -- the stamp, pose
and quality fields of that frame's per-body messages, in the same order; sent for every frame with at least one
published body.

Thin ROS layer around the ROS-free core (:mod:`fullperc_drivers.nokov`): a backend thread (SDK callback or
UDP reader) puts :class:`RawFrame` into a :class:`~fullperc_drivers.handoff.Handoff`, which schedules a drain on
the node's executor (:class:`~fullperc_drivers.handoff.ExecutorWake`); the executor drains it, runs
:class:`FramePipeline` (dedupe, gaps, mm -> m, capture stamp on the host clock) and publishes. Untracked bodies
get a quality message with ``visible: false`` and no pose.

Health (``/diagnostics``, status ``omc_driver: omc``; the rule is in :mod:`fullperc_common.health`): ERROR when
no new frame arrived for ``stale_timeout_s`` (not connected / frame number frozen / stream stopped, counted as a
stall) or when every body's pose was refused (non-finite, non-unit quaternion) for ``health.stale_after_s``;
WARN per body not seen or refused for that long, for recent decode errors / implausible latencies / queue
overflow, and for repeated SDK reconnects; OK only while every body's poses flow. Values: frame rate, dropped
frames (frame-number gaps), decode errors, clock offset, stalls.
"""

from __future__ import annotations

import sys
import time

from geometry_msgs.msg import Pose, PoseStamped
from rclpy.node import Node

from fullperc_common.diagnostics import Diagnostics
from fullperc_common.health import Health
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare_fixed
from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_common.subscribers import SubscriberLog
from fullperc_msgs.msg import TrackedBodies, TrackingQuality

from .clock_sync import ClockSync
from .handoff import ExecutorWake, Handoff
from .node_common import (
    HEALTH_PERIOD_S,
    ConsoleThrottle,
    HealthReport,
    declare_health,
    make_qos,
    topic_name,
    tracked_body,
)
from .nokov.frames import REFUSED_REASONS, FramePipeline, MocapFrame, RawFrame
from .nokov.sdk import NokovSdkBackend, NokovSdkError
from .nokov.stream import OmcStreamBackend

__all__ = ["OmcDriverNode", "main", "make_qos", "topic_name"]


class OmcDriverNode(Node):
    def __init__(self) -> None:
        super().__init__("omc_driver")
        p = {}
        p["backend"] = declare_fixed(self, "backend", "stream", lambda v: v in ("stream", "nokov_sdk"),
                                     "one of stream, nokov_sdk")
        p["server"] = declare_fixed(self, "server", "10.1.1.198", lambda v: bool(v), "XINGYING server IP")
        p["sdk_library"] = declare_fixed(self, "sdk_library", "", description="path of libnokov_sdk.so")
        p["stream_host"] = declare_fixed(self, "stream_host", "127.0.0.1")
        p["stream_port"] = declare_fixed(self, "stream_port", 3883, lambda v: 0 < v < 65536, "UDP port 1..65535")
        bodies = declare_fixed(self, "bodies", ["all"], description="body names to publish, or ['all']")
        self.frame_id = declare_fixed(self, "frame_id", "omc", lambda v: bool(v), "non-empty")
        qos = declare_fixed(self, "qos", "reliable", lambda v: v in ("reliable", "sensor"), "reliable or sensor")
        depth = declare_fixed(self, "qos_depth", 1000, lambda v: v > 0, "> 0")   # config/omc.yaml: why
        lat = declare_fixed(self, "latency_compensation", True)
        dev_stamp = declare_fixed(self, "device_stamp", "capture", lambda v: v in ("capture", "send"),
                                  "capture or send")
        stamp_src = declare_fixed(self, "stamp_source", "device", lambda v: v in ("device", "receive"),
                                  "device or receive")
        window = declare_fixed(self, "sync_window_s", 5.0, lambda v: v > 0, "> 0")
        transport = declare_fixed(self, "transport_delay_s", 0.0, lambda v: 0 <= v < 1, "0..1 s")
        ts_unit = declare_fixed(self, "sdk_timestamp_unit_ns", 1_000_000, lambda v: v > 0, "> 0")
        lat_unit = declare_fixed(self, "sdk_latency_unit_s", 1.0, lambda v: v > 0, "> 0")
        mask = declare_fixed(self, "sdk_valid_flag_mask", 0, lambda v: 0 <= v < 65536, "0..65535")
        self.stale_s = declare_fixed(self, "stale_timeout_s", 1.0, lambda v: v > 0, "> 0")
        self.reconnect_s = declare_fixed(self, "reconnect_after_s", 5.0, lambda v: v > 0, "> 0")
        diag_period = declare_fixed(self, "diagnostics_period_s", 1.0, lambda v: v > 0, "> 0")
        health_cfg = declare_health(self, frames_stale_after_s=self.stale_s)

        self.bodies = None if (not bodies or "all" in bodies) else set(bodies)
        self.qos = make_qos(qos, depth)
        self.pipeline = FramePipeline(ClockSync(window_s=window, transport_delay_ns=int(transport * 1e9)),
                                      device_stamp=dev_stamp, stamp_source=stamp_src, latency_compensation=lat)
        self.diag = Diagnostics(self, hardware_id=f"nokov:{p['backend']}", period_s=diag_period)
        self.health = Health(sorted(self.bodies or ()), health_cfg, item_kind="body", output="pose", frame="frame")
        self.console = ConsoleThrottle(self.get_logger, period_s=5.0)
        self.report = HealthReport(self.diag, "omc", self.health, self.console)
        self._wake = ExecutorWake(self, self._drain)
        self.handoff: Handoff[RawFrame] = Handoff(maxlen=256, notify=self._wake)
        self._pose_pubs: dict[str, object] = {}
        self._quality_pubs: dict[str, object] = {}
        self._bodies_pub = self.create_publisher(TrackedBodies, "omc/bodies", self.qos)
        self.unnamed = 0
        self.publish_errors = 0
        self.refused = 0
        self._last_frame_mono: float | None = None
        self._reconnect_requested = False
        self._seen = {"decode": 0, "latency": 0, "overflow": 0}
        self._connected: bool | None = None
        self.backend_name = p["backend"]
        if p["backend"] == "stream":
            self.backend = OmcStreamBackend(p["stream_host"], p["stream_port"], self.handoff.put)
            self.get_logger().info(f"OMC stream backend listening on UDP {self.backend.address}")
        else:
            self.backend = NokovSdkBackend(p["sdk_library"], p["server"], self.handoff.put, ts_unit, lat_unit, mask)
            self.get_logger().info(f"NOKOV SDK {self.backend.version or '?'} from {p['sdk_library']}, "
                                   f"server {p['server']}")
        for name in sorted(self.bodies or ()):
            self._pubs_for(name)  # explicit bodies: topics exist before the first frame
        self._diag_timer = self.create_timer(min(diag_period, HEALTH_PERIOD_S), self._update_diagnostics)
        self.subscribers = SubscriberLog(self, lambda: {**self._pose_pubs, "": self._bodies_pub})   # bodies too
        self._update_diagnostics()

    # ---- executor side ----------------------------------------------------------------------------
    def _pubs_for(self, name: str):
        if name not in self._pose_pubs:
            tok = topic_name(name)
            self._pose_pubs[name] = self.create_publisher(PoseStamped, f"omc/{tok}/pose", self.qos)
            self._quality_pubs[name] = self.create_publisher(TrackingQuality, f"omc/{tok}/quality", self.qos)
        return self._pose_pubs[name], self._quality_pubs[name]

    def _drain(self) -> None:
        for raw in self.handoff.drain():
            if self.backend_name == "nokov_sdk":
                for b in raw.bodies:
                    b.name = b.name or self.backend.name_of(b.id)
            self.health.frame(raw.frame_number)
            frame = self.pipeline.process(raw)
            if frame is not None:
                self._publish(frame)

    def _publish(self, frame: MocapFrame) -> None:
        self._last_frame_mono = time.monotonic()
        latency = max(0.0, (frame.recv_ns - frame.stamp_ns) * 1e-9)
        out = TrackedBodies()  # the frame in one message: each body as its quality (and pose) message says
        out.header.stamp = ns_to_stamp(frame.stamp_ns)
        out.header.frame_id = self.frame_id
        out.latency = float(latency)
        for b in frame.bodies:
            if not b.name:
                self.unnamed += 1
                continue
            if self.bodies is not None and b.name not in self.bodies:
                continue
            pose_pub, q_pub = self._pubs_for(b.name)
            q = TrackingQuality()
            q.header.stamp = ns_to_stamp(frame.stamp_ns)
            q.header.frame_id = self.frame_id
            q.body = b.name
            q.visible = b.tracked
            q.fit_error = float(b.mean_error_m) if b.mean_error_m == b.mean_error_m else -1.0
            q.frame_number = int(frame.frame_number) & 0xFFFFFFFF
            q.markers_used = max(0, min(int(b.markers), 65535))
            q.latency = float(latency)
            pose = Pose()  # all zeros unless visible
            if b.tracked:
                try:
                    msg = pose_stamped(frame.stamp_ns, self.frame_id, b.position_m, b.quat_xyzw)
                except ValueError as e:  # refused non-finite pose: report, publish as not visible
                    self.publish_errors += 1
                    q.visible = False
                    self.health.refused(b.name, str(e))
                    self.console(f"refused:{b.name}", f"body {b.name}: {e}")
                else:
                    pose_pub.publish(msg)
                    pose = msg.pose
                    self.health.good(b.name)
            elif b.reason in REFUSED_REASONS:
                self.refused += 1
                self.health.refused(b.name, b.reason)
            q_pub.publish(q)
            out.bodies.append(tracked_body(q, pose))
        if out.bodies:
            self._bodies_pub.publish(out)

    def _update_diagnostics(self) -> None:
        self._wake.catch_up()   # what came before the node was spinning (ExecutorWake)
        now = time.monotonic()
        c = self.pipeline.counters
        be = self.backend
        if be.connected != self._connected:
            if be.connected:
                self.health.link_up()
            else:
                self.health.link_down(be.last_error or "not connected")
            self._connected = be.connected
        stale = self._last_frame_mono is None or now - self._last_frame_mono > self.stale_s
        if (self.backend_name == "nokov_sdk" and stale and be.connected and self._last_frame_mono is not None
                and now - self._last_frame_mono > self.reconnect_s and not self._reconnect_requested):
            self._reconnect_requested = True
            be.request_reconnect()
            self.console("reconnect", f"no frames from the NOKOV SDK for {now - self._last_frame_mono:.1f} s: "
                                      "re-initialising it")
        if not stale:
            self._reconnect_requested = False
        for key, n, what in (("decode", getattr(be, "decode_errors", 0), "decode errors"),
                             ("latency", c.bad_latency, "implausible latencies"),
                             ("overflow", self.handoff.overflow, "queue overflows")):
            if n > self._seen[key]:
                self.health.problem(what, n - self._seen[key], be.last_error if key == "decode" else "")
            self._seen[key] = n
        off = self.pipeline.sync.offset_ns
        values = {
            "backend": self.backend_name, "connected": be.connected,
            "frames": c.frames, "dropped_frames": c.dropped, "duplicate_frames": c.duplicates,
            "frame_restarts": c.restarts,
            "decode_errors": getattr(be, "decode_errors", 0), "callback_errors": getattr(be, "callback_errors", 0),
            "queue_overflow": self.handoff.overflow, "bad_latency": c.bad_latency,
            "no_device_time": c.no_device_time, "stamp_not_increasing": c.stamp_not_increasing,
            "clock_offset_ms": "n/a" if off is None else f"{off / 1e6:.3f}",
            "clock_resets": self.pipeline.sync.stats.resets, "unnamed_bodies": self.unnamed,
            "publish_errors": self.publish_errors, "refused_bodies": self.refused, "last_error": be.last_error,
        }
        values["frame_rate_hz"] = f"{self.health.rate_hz():.1f}"
        if self.backend_name == "nokov_sdk":
            values.update(sdk_version=be.version, names=len(be.names), name_refreshes=be.name_refreshes,
                          connect_attempts=be.connect_attempts)
        self.report.publish(values)

    def close(self) -> None:
        """Stop the backend's threads (receiver / SDK callbacks and worker) before the node is destroyed."""
        self.handoff.notify = None
        self._diag_timer.cancel()
        self.backend.close()


def main(args=None) -> int:
    return run_node(OmcDriverNode, "omc_driver", (ParameterError, NokovSdkError, OSError), args,
                    params_file=("fullperc_drivers", "omc.yaml"))


if __name__ == "__main__":
    sys.exit(main())
