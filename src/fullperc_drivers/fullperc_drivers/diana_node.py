"""``diana_state``: Diana 7 joint state -> ``/diana/joint_states``, ``/diana/flange_pose`` (+ ``/diana/tool_pose``).

Backends: ``stream`` (the simulator's UDP joint-state stream; device timestamps mapped to the host clock)
and ``diana_api`` (the vendor library through ctypes, polled at ``rate_hz`` from the SDK's local cache;
stamped at the read). Poses come from :class:`~fullperc_drivers.diana_kinematics.DianaKinematics`, with
the DH table from ``dh_source``: ``nominal`` (reference table), ``parameters`` (``dh_a/alpha/d/theta``,
e.g. a real robot's ``getDH`` output copied into the yaml) or ``controller`` (``getDH`` read at connect,
``diana_api`` only). Joint names ``joint1..joint7``; poses in frame ``diana_base``.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import JointState

from fullperc_common.diagnostics import Diagnostics
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare
from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_common.transforms import T_to_pq

from .clock_sync import ClockSync
from .diana import JointSample
from .diana.api import DianaApiBackend, DianaApiError
from .diana.stream import DianaStreamBackend, DianaStreamPipeline, RawJointState
from .diana_kinematics import DIANA7_MDH, JOINT_NAMES, DianaKinematics
from .handoff import Handoff
from .omc_node import ERROR, OK, WARN, make_qos


class DianaStateNode(Node):
    def __init__(self) -> None:
        super().__init__("diana_state")
        backend = declare(self, "backend", "stream", lambda v: v in ("stream", "diana_api"),
                          "one of stream, diana_api")
        robot_ip = declare(self, "robot_ip", "192.168.10.75", lambda v: bool(v), "non-empty")
        library = declare(self, "api_library", "", description="path of libDianaApi.so")
        host = declare(self, "stream_host", "127.0.0.1")
        port = declare(self, "stream_port", 3884, lambda v: 0 < v < 65536, "UDP port 1..65535")
        rate = declare(self, "rate_hz", 100.0, lambda v: 0 < v <= 1000, "0 < rate <= 1000")
        self.frame_id = declare(self, "frame_id", "diana_base", lambda v: bool(v), "non-empty")
        self.publish_tool = declare(self, "publish_tool", False)
        tool = declare(self, "tool_offset", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                       lambda v: len(v) == 7 and np.linalg.norm(v[3:]) > 0.5, "x y z qx qy qz qw (unit quaternion)")
        self.dh_source = declare(self, "dh_source", "nominal", lambda v: v in ("nominal", "parameters", "controller"),
                                 "nominal, parameters or controller")
        dh = [declare(self, f"dh_{k}", DIANA7_MDH[:, i].tolist(), lambda v: len(v) == 7, "7 values")
              for k, i in (("a", 1), ("alpha", 0), ("d", 2), ("theta", 3))]
        qos = declare(self, "qos", "reliable", lambda v: v in ("reliable", "sensor"), "reliable or sensor")
        depth = declare(self, "qos_depth", 10, lambda v: v > 0, "> 0")
        window = declare(self, "sync_window_s", 5.0, lambda v: v > 0, "> 0")
        age = declare(self, "age_compensation_s", 0.0, lambda v: 0 <= v < 1, "0..1 s")
        self.stale_s = declare(self, "stale_timeout_s", 1.0, lambda v: v > 0, "> 0")
        diag_period = declare(self, "diagnostics_period_s", 1.0, lambda v: v > 0, "> 0")
        if self.dh_source == "controller" and backend != "diana_api":
            raise ParameterError("parameter 'dh_source' = 'controller' needs backend 'diana_api'")

        self.tool_offset = np.array(tool, dtype=float)
        try:
            if self.dh_source == "parameters":
                self.kin = DianaKinematics.from_getdh(*dh, tool_offset=self.tool_offset)
            else:
                self.kin = DianaKinematics(tool_offset=self.tool_offset)
        except ValueError as e:
            raise ParameterError(f"DH table / tool offset parameters: {e}") from e
        self._dh_loaded = self.dh_source != "controller"

        q = make_qos(qos, depth)
        self.pub_js = self.create_publisher(JointState, "/diana/joint_states", q)
        self.pub_flange = self.create_publisher(PoseStamped, "/diana/flange_pose", q)
        self.pub_tool = self.create_publisher(PoseStamped, "/diana/tool_pose", q) if self.publish_tool else None
        self.diag = Diagnostics(self, hardware_id=f"diana7:{backend}", period_s=diag_period)
        self.backend_name = backend
        self.samples = 0
        self.publish_errors = 0
        self.stalls = 0
        self._stalled = False
        self._last_mono: float | None = None
        self._rate_count = 0
        self._rate_t0 = time.monotonic()
        self._rate_hz = 0.0
        self._vendor_dev_mm: float | None = None
        if backend == "stream":
            self.pipeline = DianaStreamPipeline(ClockSync(window_s=window))
            self._gc = self.create_guard_condition(self._drain)
            self.handoff: Handoff[RawJointState] = Handoff(maxlen=256, notify=self._gc.trigger)
            self.backend = DianaStreamBackend(host, port, self.handoff.put)
            self.get_logger().info(f"Diana stream backend listening on UDP {self.backend.address}")
        else:
            self.pipeline = None
            self.backend = DianaApiBackend(library, robot_ip, age_compensation_s=age)
            self._poll = self.create_timer(1.0 / rate, self._poll_api)
            self.get_logger().info(f"DianaApi from {library}, robot {robot_ip}, polling at {rate} Hz")
        self._diag_timer = self.create_timer(diag_period, self._update_diagnostics)
        self._update_diagnostics()

    def _drain(self) -> None:
        for raw in self.handoff.drain():
            s = self.pipeline.process(raw)
            if s is not None:
                self._publish(s)

    def _poll_api(self) -> None:
        if not self._dh_loaded and self.backend.connected:
            dh = self.backend.read_dh()
            if dh is not None:
                try:
                    self.kin = DianaKinematics.from_getdh(*dh, tool_offset=self.tool_offset)
                    self._dh_loaded = True
                    self.get_logger().info(f"using the controller's DH table (getDH): {[a.tolist() for a in dh]}")
                except ValueError as e:
                    self.backend.last_error = f"controller DH table rejected: {e}"
            if not self._dh_loaded:
                return  # never publish poses from a table we were told not to use
        s = self.backend.read()
        if s is not None:
            self._publish(s)

    def _publish(self, s: JointSample) -> None:
        self._last_mono = time.monotonic()
        self._rate_count += 1
        self.samples += 1
        js = JointState()
        js.header.stamp = ns_to_stamp(s.stamp_ns)
        js.header.frame_id = self.frame_id
        js.name = list(JOINT_NAMES)
        js.position = [float(v) for v in s.q]
        js.velocity = [float(v) for v in s.dq] if s.dq is not None else []
        self.pub_js.publish(js)
        try:
            T = self.kin.fk(s.q)
            p, q = T_to_pq(T)
            self.pub_flange.publish(pose_stamped(s.stamp_ns, self.frame_id, p, q))
            if self.pub_tool is not None:
                p, q = T_to_pq(T @ self.kin.tool_offset)
                self.pub_tool.publish(pose_stamped(s.stamp_ns, self.frame_id, p, q))
            if s.vendor_tcp is not None:
                # Cross-check against the controller's own FK (its default TCP = flange unless reconfigured).
                dp = np.linalg.norm(s.vendor_tcp[:3] - T[:3, 3]) * 1e3
                R = Rotation.from_rotvec(s.vendor_tcp[3:]).as_matrix()
                dr = np.linalg.norm(R - T[:3, :3]) * 100.0  # ~mm at 0.1 m lever
                self._vendor_dev_mm = float(max(dp, dr))
        except ValueError as e:
            self.publish_errors += 1
            self.get_logger().warn(f"pose not published: {e}", throttle_duration_sec=5.0)

    def _update_diagnostics(self) -> None:
        now = time.monotonic()
        dt = now - self._rate_t0
        if dt > 0:
            self._rate_hz = self._rate_count / dt
        self._rate_count, self._rate_t0 = 0, now
        be = self.backend
        stale = self._last_mono is None or now - self._last_mono > self.stale_s
        if stale and self._last_mono is not None and not self._stalled:
            self.stalls += 1
        self._stalled = stale and self._last_mono is not None
        values = {"backend": self.backend_name, "connected": be.connected, "rate_hz": f"{self._rate_hz:.1f}",
                  "samples": self.samples, "stalls": self.stalls, "publish_errors": self.publish_errors,
                  "dh_source": self.dh_source, "dh_loaded": self._dh_loaded, "last_error": be.last_error}
        errors = False
        if self.pipeline is not None:
            c = self.pipeline.counters
            off = self.pipeline.sync.offset_ns
            values.update(decode_errors=be.decode_errors, dropped=c.dropped, duplicates=c.duplicates,
                          invalid=c.invalid, restarts=c.restarts, stamp_not_increasing=c.stamp_not_increasing,
                          queue_overflow=self.handoff.overflow, clock_resets=self.pipeline.sync.stats.resets,
                          clock_offset_ms="n/a" if off is None else f"{off / 1e6:.3f}")
            errors = bool(be.decode_errors or c.invalid or self.handoff.overflow)
        else:
            values.update(read_failures=be.read_failures, invalid=be.invalid, connect_attempts=be.connect_attempts,
                          vendor_tcp_vs_fk_mm="n/a" if self._vendor_dev_mm is None else f"{self._vendor_dev_mm:.3f}")
            errors = bool(be.read_failures or be.invalid)
            if self._vendor_dev_mm is not None and self._vendor_dev_mm > 1.0:
                errors = True
                values["warning"] = "controller TCP differs from our flange FK (other DH table or active TCP set)"
        if not be.connected:
            level, msg = ERROR, f"not connected: {be.last_error}"
        elif self._last_mono is None:
            level, msg = WARN, "connected, no joint state yet"
        elif stale:
            level, msg = ERROR, f"no joint state for {now - self._last_mono:.1f} s (stream stopped)"
        elif errors:
            level, msg = WARN, "receiving, with errors (see values)"
        else:
            level, msg = OK, f"receiving at {self._rate_hz:.1f} Hz"
        self.diag.set("diana", level, msg, values)

    def close(self) -> None:
        self.backend.close()


def main(args=None) -> int:
    return run_node(DianaStateNode, "diana_state", (ParameterError, DianaApiError, OSError), args)


if __name__ == "__main__":
    sys.exit(main())
