"""``omc_driver``: NOKOV rigid bodies -> ``/omc/<body>/pose`` (PoseStamped, frame ``omc``) + ``/omc/<body>/quality``.

Thin ROS layer around the ROS-free core (:mod:`fullperc_drivers.nokov`): a backend thread (SDK callback or
UDP reader) puts :class:`RawFrame` into a :class:`~fullperc_drivers.handoff.Handoff` and triggers a guard
condition; the executor drains it, runs :class:`FramePipeline` (dedupe, gaps, mm -> m, capture stamp on the
host clock) and publishes. Untracked bodies get a quality message with ``visible: false`` and no pose.
``/diagnostics`` reports connection, frame rate, dropped frames (frame-number gaps), decode errors, clock
offset and stalls (no frame for ``stale_timeout_s``).
"""

from __future__ import annotations

import re
import sys
import time

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from fullperc_common.diagnostics import ERROR as _ERROR
from fullperc_common.diagnostics import OK as _OK
from fullperc_common.diagnostics import WARN as _WARN
from fullperc_common.diagnostics import Diagnostics
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare
from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_common.subscribers import SubscriberLog
from fullperc_msgs.msg import TrackingQuality

from .clock_sync import ClockSync
from .handoff import Handoff
from .nokov.frames import FramePipeline, MocapFrame, RawFrame
from .nokov.sdk import NokovSdkBackend, NokovSdkError
from .nokov.stream import OmcStreamBackend


def as_level(v) -> int:
    """DiagnosticStatus level constants are bytes in the Jazzy wheels; ``Diagnostics.set`` takes an int."""
    return v[0] if isinstance(v, bytes) else int(v)


OK, WARN, ERROR = as_level(_OK), as_level(_WARN), as_level(_ERROR)


def topic_name(body: str) -> str:
    """A device body name as a ROS topic token (names.md names pass through unchanged)."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", body.strip())
    return s if s and not s[0].isdigit() else f"b_{s}"


def make_qos(kind: str, depth: int) -> QoSProfile:
    if kind == "sensor":
        return qos_profile_sensor_data
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


class OmcDriverNode(Node):
    def __init__(self) -> None:
        super().__init__("omc_driver")
        p = {}
        p["backend"] = declare(self, "backend", "stream", lambda v: v in ("stream", "nokov_sdk"),
                               "one of stream, nokov_sdk")
        p["server"] = declare(self, "server", "10.1.1.198", lambda v: bool(v), "XINGYING server IP")
        p["sdk_library"] = declare(self, "sdk_library", "", description="path of libnokov_sdk.so")
        p["stream_host"] = declare(self, "stream_host", "127.0.0.1")
        p["stream_port"] = declare(self, "stream_port", 3883, lambda v: 0 < v < 65536, "UDP port 1..65535")
        bodies = declare(self, "bodies", ["all"], description="body names to publish, or ['all']")
        self.frame_id = declare(self, "frame_id", "omc", lambda v: bool(v), "non-empty")
        qos = declare(self, "qos", "reliable", lambda v: v in ("reliable", "sensor"), "reliable or sensor")
        depth = declare(self, "qos_depth", 10, lambda v: v > 0, "> 0")
        lat = declare(self, "latency_compensation", True)
        dev_stamp = declare(self, "device_stamp", "capture", lambda v: v in ("capture", "send"), "capture or send")
        stamp_src = declare(self, "stamp_source", "device", lambda v: v in ("device", "receive"),
                            "device or receive")
        window = declare(self, "sync_window_s", 5.0, lambda v: v > 0, "> 0")
        transport = declare(self, "transport_delay_s", 0.0, lambda v: 0 <= v < 1, "0..1 s")
        ts_unit = declare(self, "sdk_timestamp_unit_ns", 1_000_000, lambda v: v > 0, "> 0")
        lat_unit = declare(self, "sdk_latency_unit_s", 1.0, lambda v: v > 0, "> 0")
        mask = declare(self, "sdk_valid_flag_mask", 0, lambda v: 0 <= v < 65536, "0..65535")
        self.stale_s = declare(self, "stale_timeout_s", 1.0, lambda v: v > 0, "> 0")
        self.reconnect_s = declare(self, "reconnect_after_s", 5.0, lambda v: v > 0, "> 0")
        diag_period = declare(self, "diagnostics_period_s", 1.0, lambda v: v > 0, "> 0")

        self.bodies = None if (not bodies or "all" in bodies) else set(bodies)
        self.qos = make_qos(qos, depth)
        self.pipeline = FramePipeline(ClockSync(window_s=window, transport_delay_ns=int(transport * 1e9)),
                                      device_stamp=dev_stamp, stamp_source=stamp_src, latency_compensation=lat)
        self.diag = Diagnostics(self, hardware_id=f"nokov:{p['backend']}", period_s=diag_period)
        self._gc = self.create_guard_condition(self._drain)
        self.handoff: Handoff[RawFrame] = Handoff(maxlen=256, notify=self._gc.trigger)
        self._pose_pubs: dict[str, object] = {}
        self._quality_pubs: dict[str, object] = {}
        self.unnamed = 0
        self.publish_errors = 0
        self.stalls = 0
        self._stalled = False
        self._last_frame_mono: float | None = None
        self._rate_count = 0
        self._rate_t0 = time.monotonic()
        self._rate_hz = 0.0
        self._reconnect_requested = False
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
        self._diag_timer = self.create_timer(diag_period, self._update_diagnostics)
        self.subscribers = SubscriberLog(self, lambda: self._pose_pubs)
        self._update_diagnostics()

    # ---- executor side ----------------------------------------------------------------------------
    def _pubs_for(self, name: str):
        if name not in self._pose_pubs:
            tok = topic_name(name)
            self._pose_pubs[name] = self.create_publisher(PoseStamped, f"/omc/{tok}/pose", self.qos)
            self._quality_pubs[name] = self.create_publisher(TrackingQuality, f"/omc/{tok}/quality", self.qos)
        return self._pose_pubs[name], self._quality_pubs[name]

    def _drain(self) -> None:
        for raw in self.handoff.drain():
            if self.backend_name == "nokov_sdk":
                for b in raw.bodies:
                    b.name = b.name or self.backend.name_of(b.id)
            frame = self.pipeline.process(raw)
            if frame is not None:
                self._publish(frame)

    def _publish(self, frame: MocapFrame) -> None:
        self._last_frame_mono = time.monotonic()
        self._rate_count += 1
        latency = max(0.0, (frame.recv_ns - frame.stamp_ns) * 1e-9)
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
            if b.tracked:
                try:
                    pose_pub.publish(pose_stamped(frame.stamp_ns, self.frame_id, b.position_m, b.quat_xyzw))
                except ValueError as e:  # refused non-finite pose: report, publish as not visible
                    self.publish_errors += 1
                    q.visible = False
                    self.get_logger().warn(f"body {b.name}: {e}", throttle_duration_sec=5.0)
            q_pub.publish(q)

    def _update_diagnostics(self) -> None:
        now = time.monotonic()
        dt = now - self._rate_t0
        if dt > 0:
            self._rate_hz = self._rate_count / dt
        self._rate_count, self._rate_t0 = 0, now
        c = self.pipeline.counters
        be = self.backend
        stale = self._last_frame_mono is None or now - self._last_frame_mono > self.stale_s
        if stale and self._last_frame_mono is not None and not self._stalled:
            self.stalls += 1
        self._stalled = stale and self._last_frame_mono is not None
        if (self.backend_name == "nokov_sdk" and stale and be.connected and self._last_frame_mono is not None
                and now - self._last_frame_mono > self.reconnect_s and not self._reconnect_requested):
            self._reconnect_requested = True
            be.request_reconnect()
        if not stale:
            self._reconnect_requested = False
        off = self.pipeline.sync.offset_ns
        values = {
            "backend": self.backend_name, "connected": be.connected, "frame_rate_hz": f"{self._rate_hz:.1f}",
            "frames": c.frames, "dropped_frames": c.dropped, "duplicate_frames": c.duplicates,
            "frame_restarts": c.restarts, "stalls": self.stalls,
            "decode_errors": getattr(be, "decode_errors", 0), "callback_errors": getattr(be, "callback_errors", 0),
            "queue_overflow": self.handoff.overflow, "bad_latency": c.bad_latency,
            "no_device_time": c.no_device_time, "stamp_not_increasing": c.stamp_not_increasing,
            "clock_offset_ms": "n/a" if off is None else f"{off / 1e6:.3f}",
            "clock_resets": self.pipeline.sync.stats.resets, "unnamed_bodies": self.unnamed,
            "publish_errors": self.publish_errors, "last_error": be.last_error,
        }
        if self.backend_name == "nokov_sdk":
            values.update(sdk_version=be.version, names=len(be.names), name_refreshes=be.name_refreshes,
                          connect_attempts=be.connect_attempts)
        if not be.connected:
            level, msg = ERROR, f"not connected: {be.last_error}"
        elif self._last_frame_mono is None:
            level, msg = WARN, "connected, no frame received yet"
        elif stale:
            level, msg = ERROR, f"no frames for {now - self._last_frame_mono:.1f} s (stream stopped)"
        elif getattr(be, "decode_errors", 0) or c.bad_latency or self.handoff.overflow:
            level, msg = WARN, "receiving, with errors (see values)"
        else:
            level, msg = OK, f"receiving at {self._rate_hz:.1f} Hz"
        self.diag.set("omc", level, msg, values)

    def close(self) -> None:
        self.backend.close()


def main(args=None) -> int:
    return run_node(OmcDriverNode, "omc_driver", (ParameterError, NokovSdkError, OSError), args)


if __name__ == "__main__":
    sys.exit(main())
