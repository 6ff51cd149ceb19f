"""``diana_state``: Diana 7 joint state -> ``/diana/joint_states``, ``/diana/flange_pose`` (+ ``/diana/tool_pose``).

Backends: ``stream`` (the simulator's UDP joint-state stream; device timestamps mapped to the host clock; the
receiver thread only puts items into a :class:`~fullperc_drivers.handoff.Handoff`, the executor drains it) and
``diana_api`` (the vendor library through ctypes, polled at ``rate_hz`` from the SDK's local cache on the
executor; stamped at the read). Poses come from :class:`~fullperc_drivers.diana_kinematics.DianaKinematics`, with
the DH table from ``dh_source``: ``nominal`` (reference table), ``parameters`` (``dh_a/alpha/d/theta``,
e.g. a real robot's ``getDH`` output copied into the yaml) or ``controller`` (``getDH`` read at connect,
``diana_api`` only). Joint names ``joint1..joint7``; poses in frame ``diana_base``.

TF (``tf`` true by default): every joint state also goes to ``/tf`` (tf2_msgs/TFMessage, stamp = the joint
state's stamp) as the arm's tree from FK: ``<frame_id>`` -> ``diana_link1`` -> ... -> ``diana_link7`` ->
``diana_flange`` (-> ``diana_tool`` with ``publish_tool``). Where the arm stands in ``base`` (``base`` ->
``diana_base``) is fusion_node's ``tf.diana_base``.

Health (``/diagnostics``, status ``diana_state: diana``; the rule is in :mod:`fullperc_common.health`, one item
``arm``): ERROR when no new joint state arrived for ``stale_timeout_s`` (not connected / sequence frozen / stream
stopped) or when no good joint state was published for ``health.stale_after_s`` because every sample was
refused (non-finite, wrong joint count, pose not computable); WARN for recent refusals, decode errors, read
failures, queue overflow, a controller TCP that differs from our FK, and repeated reconnects.
"""

from __future__ import annotations

import sys

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from fullperc_common.diagnostics import Diagnostics
from fullperc_common.health import ERROR, WARN, Health
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare_fixed
from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_common.subscribers import SubscriberLog
from fullperc_common.tf import Broadcaster, transform_stamped
from fullperc_common.transforms import T_to_pq

from .clock_sync import ClockSync
from .diana import JointSample
from .diana.api import DianaApiBackend, DianaApiError
from .diana.stream import DianaStreamBackend, DianaStreamPipeline, RawJointState
from .diana_kinematics import DIANA7_MDH, JOINT_NAMES, DianaKinematics
from .handoff import ExecutorWake, Handoff
from .node_common import HEALTH_PERIOD_S, ConsoleThrottle, HealthReport, declare_health, make_qos


def _rotvec_to_R(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (the controller's TCP orientation, ``diana_api`` only). scipy is imported
    here: the stream backend's processes (simulator, demo, tests) never need it, and scipy.spatial's imports cost
    ~0.5 s of CPU at every start (test/test_startup_imports.py)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix()


class DianaStateNode(Node):
    def __init__(self) -> None:
        super().__init__("diana_state")
        backend = declare_fixed(self, "backend", "stream", lambda v: v in ("stream", "diana_api"),
                                "one of stream, diana_api")
        robot_ip = declare_fixed(self, "robot_ip", "192.168.10.75", lambda v: bool(v), "non-empty")
        library = declare_fixed(self, "api_library", "", description="path of libDianaApi.so")
        host = declare_fixed(self, "stream_host", "127.0.0.1")
        port = declare_fixed(self, "stream_port", 3884, lambda v: 0 < v < 65536, "UDP port 1..65535")
        rate = declare_fixed(self, "rate_hz", 100.0, lambda v: 0 < v <= 1000, "0 < rate <= 1000")
        self.frame_id = declare_fixed(self, "frame_id", "diana_base", lambda v: bool(v), "non-empty")
        self.publish_tool = declare_fixed(self, "publish_tool", False)
        publish_tf = declare_fixed(self, "tf", True, description="the arm's links from FK on /tf")
        tool = declare_fixed(self, "tool_offset", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                             lambda v: len(v) == 7 and np.linalg.norm(v[3:]) > 0.5,
                             "x y z qx qy qz qw (unit quaternion)")
        self.dh_source = declare_fixed(self, "dh_source", "nominal",
                                       lambda v: v in ("nominal", "parameters", "controller"),
                                       "nominal, parameters or controller")
        dh = [declare_fixed(self, f"dh_{k}", DIANA7_MDH[:, i].tolist(), lambda v: len(v) == 7, "7 values")
              for k, i in (("a", 1), ("alpha", 0), ("d", 2), ("theta", 3))]
        qos = declare_fixed(self, "qos", "reliable", lambda v: v in ("reliable", "sensor"), "reliable or sensor")
        depth = declare_fixed(self, "qos_depth", 1000, lambda v: v > 0, "> 0")   # config/diana.yaml: why
        window = declare_fixed(self, "sync_window_s", 5.0, lambda v: v > 0, "> 0")
        age = declare_fixed(self, "age_compensation_s", 0.0, lambda v: 0 <= v < 1, "0..1 s")
        self.stale_s = declare_fixed(self, "stale_timeout_s", 1.0, lambda v: v > 0, "> 0")
        diag_period = declare_fixed(self, "diagnostics_period_s", 1.0, lambda v: v > 0, "> 0")
        health_cfg = declare_health(self, frames_stale_after_s=self.stale_s)
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
        self.pub_js = self.create_publisher(JointState, "diana/joint_states", q)
        self.pub_flange = self.create_publisher(PoseStamped, "diana/flange_pose", q)
        self.pub_tool = self.create_publisher(PoseStamped, "diana/tool_pose", q) if self.publish_tool else None
        # "subscribers on /diana/joint_states: 1": the ground truth is recorded from the task's first sample only if the
        # recorder is matched before it starts (supervisor demo waits for this line)
        self.subscribers = SubscriberLog(self, lambda: {"js": self.pub_js, "flange": self.pub_flange})
        self.tf = Broadcaster(self) if publish_tf else None
        self.diag = Diagnostics(self, hardware_id=f"diana7:{backend}", period_s=diag_period)
        self.health = Health(["arm"], health_cfg, item_kind="arm", output="joint state", frame="joint state",
                             unseen_level=ERROR)
        self.console = ConsoleThrottle(self.get_logger, period_s=5.0)
        self.report = HealthReport(self.diag, "diana", self.health, self.console)
        self.backend_name = backend
        self.samples = 0
        self.publish_errors = 0
        self._vendor_dev_mm: float | None = None
        self._seen = {"decode": 0, "invalid": 0, "read": 0, "overflow": 0}
        self._connected: bool | None = None
        self.handoff = None
        if backend == "stream":
            self.pipeline = DianaStreamPipeline(ClockSync(window_s=window))
            self._wake = ExecutorWake(self, self._drain)
            self.handoff: Handoff[RawJointState] = Handoff(maxlen=256, notify=self._wake)
            self.backend = DianaStreamBackend(host, port, self.handoff.put)
            self.get_logger().info(f"Diana stream backend listening on UDP {self.backend.address}")
        else:
            self.pipeline = None
            self.backend = DianaApiBackend(library, robot_ip, age_compensation_s=age)
            _rotvec_to_R(np.zeros(3))   # scipy's import now, not in the first poll (see _rotvec_to_R)
            self._poll = self.create_timer(1.0 / rate, self._poll_api)
            self.get_logger().info(f"DianaApi from {library}, robot {robot_ip}, polling at {rate} Hz")
        self._diag_timer = self.create_timer(min(diag_period, HEALTH_PERIOD_S), self._update_diagnostics)
        self._update_diagnostics()

    def _drain(self) -> None:
        for raw in self.handoff.drain():
            self.health.frame(raw.sequence)
            invalid = self.pipeline.counters.invalid
            s = self.pipeline.process(raw)
            if s is not None:
                self._publish(s)
            elif self.pipeline.counters.invalid > invalid:
                self.health.refused("arm", self.pipeline.last_reason)

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
        invalid = self.backend.invalid
        s = self.backend.read()
        if s is not None:
            self.health.frame()
            self._publish(s)
        elif self.backend.invalid > invalid:
            self.health.frame()
            self.health.refused("arm", self.backend.last_error)

    def _publish(self, s: JointSample) -> None:
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
            if self.tf is not None and self.tf.wanted():   # the links only while /tf has a reader (volatile: unseen)
                self.tf.send([transform_stamped(s.stamp_ns, a, b, T_ab) for a, b, T_ab
                              in self.kin.link_transforms(s.q, self.frame_id, tool=self.publish_tool)])
            if s.vendor_tcp is not None:
                # Cross-check against the controller's own FK (its default TCP = flange unless reconfigured).
                dp = np.linalg.norm(s.vendor_tcp[:3] - T[:3, 3]) * 1e3
                R = _rotvec_to_R(s.vendor_tcp[3:])
                dr = np.linalg.norm(R - T[:3, :3]) * 100.0  # ~mm at 0.1 m lever
                self._vendor_dev_mm = float(max(dp, dr))
        except ValueError as e:
            self.publish_errors += 1
            self.health.refused("arm", f"pose not computable: {e}")
            self.console("pose", f"pose not published: {e}")
        else:
            self.health.good("arm")

    def _update_diagnostics(self) -> None:
        if self.handoff is not None:
            self._wake.catch_up()   # what came before the node was spinning (ExecutorWake)
        be = self.backend
        if be.connected != self._connected:
            if be.connected:
                self.health.link_up()
            else:
                self.health.link_down(be.last_error or "not connected")
            self._connected = be.connected
        values = {"backend": self.backend_name, "connected": be.connected, "samples": self.samples,
                  "publish_errors": self.publish_errors, "dh_source": self.dh_source, "dh_loaded": self._dh_loaded,
                  "last_error": be.last_error}
        conditions: list[tuple[int, str]] = []
        if self.pipeline is not None:
            c = self.pipeline.counters
            off = self.pipeline.sync.offset_ns
            values.update(decode_errors=be.decode_errors, dropped=c.dropped, duplicates=c.duplicates,
                          invalid=c.invalid, restarts=c.restarts, stamp_not_increasing=c.stamp_not_increasing,
                          queue_overflow=self.handoff.overflow, clock_resets=self.pipeline.sync.stats.resets,
                          clock_offset_ms="n/a" if off is None else f"{off / 1e6:.3f}")
            problems = (("decode", be.decode_errors, "decode errors", be.last_error),
                        ("overflow", self.handoff.overflow, "queue overflows", ""))
        else:
            values.update(read_failures=be.read_failures, invalid=be.invalid, connect_attempts=be.connect_attempts,
                          vendor_tcp_vs_fk_mm="n/a" if self._vendor_dev_mm is None else f"{self._vendor_dev_mm:.3f}")
            problems = (("read", be.read_failures, "read failures", be.last_error),)
            if not self._dh_loaded and be.connected:
                conditions.append((WARN, f"waiting for the controller's DH table (getDH): {be.last_error or ''}"))
            if self._vendor_dev_mm is not None and self._vendor_dev_mm > 1.0:
                values["warning"] = "controller TCP differs from our flange FK (other DH table or active TCP set)"
                conditions.append((WARN, f"controller TCP {self._vendor_dev_mm:.1f} mm from our flange FK "
                                         "(other DH table or active TCP set)"))
        for key, n, what, detail in problems:
            if n > self._seen[key]:
                self.health.problem(what, n - self._seen[key], detail)
            self._seen[key] = n
        values["rate_hz"] = f"{self.health.rate_hz():.1f}"
        self.report.publish(values, conditions)

    def close(self) -> None:
        """Stop the backend's threads (stream receiver / API worker) before the node is destroyed."""
        if self.handoff is not None:
            self.handoff.notify = None
        self._diag_timer.cancel()
        self.backend.close()


def main(args=None) -> int:
    return run_node(DianaStateNode, "diana_state", (ParameterError, DianaApiError, OSError), args,
                    params_file=("fullperc_drivers", "diana.yaml"))


if __name__ == "__main__":
    sys.exit(main())
