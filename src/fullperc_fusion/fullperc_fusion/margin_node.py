"""margin_node: labels every target BVV / GVV / PVV (paper Algorithm 1, eq. 17) and publishes the margin map.

Subscribes ``pose_topic`` (default ``/fullperc/<target>/pose``) for each name in ``targets`` and publishes
``/fullperc/<target>/region`` (fullperc_msgs/Region) for every pose received, with the header (stamp = acquisition
time of the labelled pose, frame_id) and the position of that pose. ``/fullperc/margin_map``
(visualization_msgs/MarkerArray, reliable + transient local, so late RViz instances get it) is published at start
and again whenever a parameter changes. ``/fullperc/<target>/region_marker`` (visualization_msgs/Marker, a sphere at
the labelled position in the pose's frame, coloured by the published label: BVV green, GVV blue, PVV red, UNKNOWN
grey; the colours of the margin map) goes out with every Region while a subscriber is matched, for RViz
(docs/nodes.md "TF and RViz2").
``/diagnostics`` reports the layout and, per target, the last label.

Frames. The layout (cameras, OTS volume) is in ``omc``; fused poses are in ``base`` (``base_frame``: fusion_node's
``frames.base``, renamed per OR when two share one /tf). A pose whose frame_id is the
layout frame is labelled directly; a pose in ``base`` needs T_omc_base, which we take (decision) from the
``/omc/base/pose`` stream (``base_pose_topic``; the base marker is fixed on the table, so the latest sample is
enough for a region label) or, if ``T_omc_base`` is given as a parameter [x y z qx qy qz qw], from that (then the
topic is not subscribed). Until T_omc_base is known, poses in ``base`` are answered with label UNKNOWN and the
diagnostics say why. Any other frame_id gives UNKNOWN and an ERROR diagnostic.

Hysteresis (:mod:`fullperc_fusion.margin.hysteresis`): ``hysteresis.margin_band_deg`` [deg] (default 1.0; a GVV
label is kept while margin >= threshold - band, a PVV label becomes GVV at margin >= threshold + band) and
``hysteresis.min_dwell`` [s] (default 0.2; after a change the label is held for at least this much of pose
stamps), both 0 = off, changeable at run time. The published label changes once per real crossing (delayed by at
most min_dwell) instead of flickering with the estimate's noise. Every Region stays consistent: ``threshold_deg``
is the threshold in force (threshold -/+ band), and while a change is held back by the dwell ``margin_deg``,
``valid_pairs``, ``cameras_seeing`` and ``in_local_volume`` are those of the newest pose that had the held label
(header and position are the current pose's). A layout change starts every target afresh.

Bad input: an invalid layout file stops the node at start with the file and field named (exit code 2); a later
parameter change to an invalid file is rejected with the same message and the old layout stays in force.

Names and parameters (docs/nodes.md "Namespaces and parameters"): every topic name is relative (the defaults
``fullperc/{target}/pose``, ``omc/base/pose``, ...), so the names above are those of the default namespace and
``-r __ns:=/or1`` moves them all to ``/or1/...``; ``/diagnostics`` stays global. ``layout_file``,
``threshold_deg``, ``map_resolution``, ``publish_map`` and ``hysteresis.*`` are validated and applied at run time
(:meth:`MarginNode.on_set_parameters`); the others are read-only and a run-time set is refused with the reason.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np
from geometry_msgs.msg import Point, PoseStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from fullperc_common import diagnostics as _diag
from fullperc_common.diagnostics import Diagnostics, as_level
from fullperc_common.drain import take_queued
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare, declare_fixed
from fullperc_common.ros_conv import pose_to_T, stamp_to_ns
from fullperc_common.subscribers import SubscriberLog
from fullperc_common.transforms import is_finite_pose, make_T
from fullperc_fusion.margin.hysteresis import HysteresisParams, RegionFilter
from fullperc_fusion.margin.layout import Layout, LayoutError, default_layout_path, load_layout
from fullperc_fusion.margin.map import REGION_COLORS, MarginMap, compute_margin_map
from fullperc_fusion.margin.view_margin import BVV, GVV, PVV, REGION_NAMES, UNKNOWN, label_point
from fullperc_msgs.msg import Region

APPLY_PERIOD_S = 0.1   # [s] how soon a run-time layout change is applied (after the parameter set was answered)

OK, WARN, ERROR = as_level(_diag.OK), as_level(_diag.WARN), as_level(_diag.ERROR)
MAP_TOPIC = "fullperc/margin_map"   # relative: -r __ns:=/or1 gives /or1/fullperc/margin_map
_ALPHA = {BVV: 0.35, GVV: 0.12, PVV: 0.25}


def load_configured_layout(path: str, threshold_deg: float) -> Layout:
    """The layout file (default: the installed or_layout.yaml), with the threshold overridden when >= 0."""
    layout = load_layout(path or default_layout_path())
    return layout.with_threshold(threshold_deg) if threshold_deg >= 0 else layout


def map_markers(mmap: MarginMap, layout: Layout, stamp) -> MarkerArray:
    """MarkerArray: one CUBE_LIST per region, the cameras, and the OTS frustum edges, in the layout frame.

    PVV cubes are drawn only where at least two cameras see the point (the OMC still triangulates, but poorly);
    space without a cube is outside OMC coverage.
    """
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    out.markers.append(clear)
    pts = mmap.points()
    labels = mmap.labels.ravel()
    seeing = mmap.cameras_seeing.ravel()
    for mid, region in enumerate((BVV, GVV, PVV)):
        sel = labels == region
        if region == PVV:
            sel &= seeing >= 2
        m = _marker(layout.frame_id, stamp, REGION_NAMES[region], mid, Marker.CUBE_LIST)
        m.scale.x = m.scale.y = m.scale.z = mmap.resolution * 0.9
        r, g, b = REGION_COLORS[region]
        m.color = ColorRGBA(r=r, g=g, b=b, a=_ALPHA[region])
        m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in pts[sel]]
        out.markers.append(m)
    cams = _marker(layout.frame_id, stamp, "cameras", 10, Marker.SPHERE_LIST)
    cams.scale.x = cams.scale.y = cams.scale.z = 0.12
    cams.color = ColorRGBA(r=0.1, g=0.1, b=0.1, a=1.0)
    cams.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in layout.cam_pos]
    out.markers.append(cams)
    if layout.ots is not None:
        fr = _marker(layout.frame_id, stamp, "ots_volume", 11, Marker.LINE_LIST)
        fr.scale.x = 0.01
        fr.color = ColorRGBA(r=0.1, g=0.7, b=0.2, a=1.0)
        T = layout.ots.T_omc_ots
        corners = layout.ots.frustum.corners() @ T[:3, :3].T + T[:3, 3]
        segs = []
        for k in range(len(corners)):
            segs += [(corners[k][a], corners[k][(a + 1) % 4]) for a in range(4)]
            if k + 1 < len(corners):
                segs += [(corners[k][a], corners[k + 1][a]) for a in range(4)]
        fr.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for s in segs for p in s]
        out.markers.append(fr)
    return out


UNKNOWN_COLOR = (0.6, 0.6, 0.6)


def region_marker(region: Region) -> Marker:
    """A sphere at ``region.position`` (in ``region.header.frame_id``), coloured by ``region.label``."""
    m = _marker(region.header.frame_id, region.header.stamp, f"region/{region.target}", 0, Marker.SPHERE)
    m.pose.position = region.position
    m.scale.x = m.scale.y = m.scale.z = 0.04
    r, g, b = REGION_COLORS.get(region.label, UNKNOWN_COLOR)
    m.color = ColorRGBA(r=r, g=g, b=b, a=0.9)
    return m


def _marker(frame_id: str, stamp, ns: str, mid: int, kind: int) -> Marker:
    m = Marker()
    m.header.frame_id = frame_id
    m.header.stamp = stamp
    m.ns = ns
    m.id = mid
    m.type = kind
    m.action = Marker.ADD
    m.pose.orientation.w = 1.0
    return m


class MarginNode(Node):
    def __init__(self, **kw) -> None:
        super().__init__("margin_node", **kw)
        self._lock = threading.Lock()
        self.layout_file = declare(self, "layout_file", "", description="camera layout YAML; '' = installed default")
        self.threshold_override = declare(
            self, "threshold_deg", -1.0, lambda v: math.isfinite(v), "must be finite",
            "GVV threshold [deg] overriding the layout's; < 0 = use the layout's")
        self._last_label: dict[str, int] = {}
        # read-only (declare_fixed): the topics and T_omc_base shape the node's subscriptions and publishers at start
        self.targets = declare_fixed(self, "targets", ["tool"], lambda v: len(v) > 0 and all(v),
                                     "need at least one name", "target names; one region topic each")
        self.pose_topic = declare_fixed(self, "pose_topic", "fullperc/{target}/pose",
                                        lambda v: "{target}" in v, "must contain {target}",
                                        "input pose topic pattern (fused or raw, e.g. omc/{target}/pose)")
        self.region_topic = declare_fixed(self, "region_topic", "fullperc/{target}/region",
                                          lambda v: "{target}" in v, "must contain {target}")
        self.base_pose_topic = declare_fixed(self, "base_pose_topic", "omc/base/pose",
                                             description="PoseStamped of the base marker in the layout frame")
        self.base_frame = declare_fixed(self, "base_frame", "base", bool, "must not be empty",
                                        "frame of the fused poses (fusion_node's frames.base)")
        t_param = declare_fixed(self, "T_omc_base", [0.0], lambda v: len(v) in (1, 7), "needs [x y z qx qy qz qw]",
                                "fixed T_omc_base instead of base_pose_topic; [0.0] = not given")
        self.map_resolution = declare(self, "map_resolution", 0.1, lambda v: 0.01 <= v <= 1.0,
                                      "must be within [0.01, 1.0] m", "margin map grid step [m]")
        self.publish_map = declare(self, "publish_map", True)
        nonneg = lambda v: math.isfinite(v) and v >= 0  # noqa: E731
        self.hysteresis = HysteresisParams(
            margin_band_deg=declare(self, "hysteresis.margin_band_deg", HysteresisParams.margin_band_deg, nonneg,
                                    "must be finite and >= 0 [deg]",
                                    "band around the GVV threshold against label flicker [deg]; 0 = none"),
            min_dwell_s=declare(self, "hysteresis.min_dwell", HysteresisParams.min_dwell_s, nonneg,
                                "must be finite and >= 0 [s]",
                                "a label is held at least this long after a change [s of pose stamps]; 0 = none"),
        ).validate()
        # fusion_node publishes up to its qos_depth (2000) poses in one burst when it catches up after a stall: a
        # shallower queue here drops labels (with 50, a demo under the test suite's load recorded 1,098 tool labels for
        # about 2,800 fused poses)
        self.qos_depth = declare_fixed(self, "qos_depth", 2000, lambda v: v > 0, "must be > 0")

        self.layout = load_configured_layout(self.layout_file, self.threshold_override)
        self.T_omc_base: np.ndarray | None = None
        self.base_from_param = len(t_param) == 7
        if self.base_from_param:
            if not is_finite_pose(t_param[:3], t_param[3:], unit_tol=1e-3):
                raise ParameterError(f"parameter 'T_omc_base' = {list(t_param)} is invalid: needs a unit quaternion")
            self.T_omc_base = make_T(t_param[:3], np.asarray(t_param[3:]) / np.linalg.norm(t_param[3:]))

        self.diag = Diagnostics(self, hardware_id="view-margin model")
        map_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.map_pub = self.create_publisher(MarkerArray, MAP_TOPIC, map_qos)
        self.region_pubs = {}
        self.marker_pubs = {}
        self.counts: dict[str, int] = {}
        self.region_filters: dict[str, RegionFilter] = {}
        self._pose_subs: dict[str, object] = {}
        for target in self.targets:
            self.region_filters[target] = RegionFilter(self.hysteresis)
            self.region_pubs[target] = self.create_publisher(
                Region, self.region_topic.format(target=target), self.qos_depth)
            self.marker_pubs[target] = self.create_publisher(Marker, f"fullperc/{target}/region_marker",
                                                             self.qos_depth)
            self.counts[target] = 0
            self._pose_subs[target] = self.create_subscription(
                PoseStamped, self.pose_topic.format(target=target), lambda msg, t=target: self.on_pose(t, msg),
                self.qos_depth)
            self.diag.set(f"target {target}", WARN, "no pose received yet")
        if not self.base_from_param and self.base_pose_topic:
            self.create_subscription(PoseStamped, self.base_pose_topic, self.on_base, self.qos_depth)
        # "subscribers on /fullperc/tool/region: 1": supervisor demo starts the task once the recorder has the labels
        self.subscribers = SubscriberLog(self, lambda: self.region_pubs)

        self._pending: Layout | None = None
        # a changed layout is applied here after the set-parameters answer went out (a map takes ~0.1-1 s): polled by a
        # timer, not woken by a guard condition, which rclpy 7.1's EventsExecutor cannot run (executor_choice)
        self.create_timer(APPLY_PERIOD_S, self.apply_pending)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.report_layout()
        self.publish_margin_map()

    # ------------------------------------------------------------------------------------------------ layout
    def report_layout(self, mmap: MarginMap | None = None) -> None:
        L = self.layout
        vals = {"file": L.source, "cameras": L.n_cameras, "threshold_deg": f"{L.threshold_deg:.1f}",
                "threshold_mode": L.threshold.mode, "convergence_deg": L.convergence_deg,
                "occluders": len(L.occluders), "ots": "none" if L.ots is None else f"{L.ots.name} ({L.ots.volume})"}
        if mmap is not None:
            vals.update({f"map_{k}": f"{100 * v:.1f} %" for k, v in mmap.fractions().items()})
        self.diag.set("layout", OK, f"{L.n_cameras} cameras, threshold {L.threshold_deg:.0f} deg", vals)

    def publish_margin_map(self) -> None:
        if not self.publish_map:
            return
        with self._lock:
            layout = self.layout
        mmap = compute_margin_map(layout, self.map_resolution)
        self.map_pub.publish(map_markers(mmap, layout, self.get_clock().now().to_msg()))
        self.report_layout(mmap)
        self.get_logger().info(
            f"margin map published: {mmap.shape} at {mmap.resolution:g} m, "
            + ", ".join(f"{k} {100 * v:.1f} %" for k, v in mmap.fractions().items()))

    def on_set_parameters(self, params) -> SetParametersResult:
        """Validate changes (an invalid layout is rejected, naming file and field); the map is rebuilt afterwards.

        Only the parameters applied here are writable; rclpy refuses the read-only ones before this runs."""
        path, thr = self.layout_file, self.threshold_override
        res, publish = self.map_resolution, self.publish_map
        hyst = {"margin_band_deg": self.hysteresis.margin_band_deg, "min_dwell_s": self.hysteresis.min_dwell_s}
        for p in params:
            if p.name in ("hysteresis.margin_band_deg", "hysteresis.min_dwell"):
                v = p.value
                if isinstance(v, bool) or not isinstance(v, float) or not math.isfinite(v) or v < 0:
                    return SetParametersResult(successful=False, reason=f"'{p.name}' must be a finite float >= 0")
                hyst["margin_band_deg" if p.name.endswith("band_deg") else "min_dwell_s"] = v
            elif p.name == "layout_file":
                path = p.value
            elif p.name == "threshold_deg":
                thr = p.value
            elif p.name == "map_resolution":
                if not (isinstance(p.value, float) and 0.01 <= p.value <= 1.0):
                    return SetParametersResult(successful=False, reason="map_resolution must be within [0.01, 1.0] m")
                res = p.value
            elif p.name == "publish_map":
                publish = bool(p.value)
        try:
            if not (isinstance(thr, float) and math.isfinite(thr)):
                raise LayoutError(f"parameter 'threshold_deg' = {thr!r} must be finite")
            layout = load_configured_layout(path, thr)
        except (LayoutError, FileNotFoundError) as e:
            self.get_logger().error(f"parameter change rejected: {e}")
            return SetParametersResult(successful=False, reason=str(e))
        self.layout_file, self.threshold_override = path, thr
        self.map_resolution, self.publish_map = res, publish
        self.hysteresis = HysteresisParams(**hyst)
        for f in self.region_filters.values():
            f.params = self.hysteresis
        with self._lock:
            self._pending = layout
        return SetParametersResult(successful=True)

    def apply_pending(self) -> None:
        """The layout of an accepted parameter change, if one is pending: labels start afresh, the map is rebuilt."""
        if self._pending is None:   # the timer's usual round: nothing to do (read without the lock: a stale None
            return                  # only defers the change to the next round)
        with self._lock:
            layout, self._pending = self._pending, None
            if layout is not None:
                self.layout = layout
        if layout is not None:
            for f in self.region_filters.values():
                f.reset()
            self.publish_margin_map()

    # ------------------------------------------------------------------------------------------------- poses
    def on_base(self, msg: PoseStamped) -> None:
        if msg.header.frame_id != self.layout.frame_id:
            self.diag.set("base pose", ERROR, f"{self.base_pose_topic} is in frame '{msg.header.frame_id}', "
                          f"expected the layout frame '{self.layout.frame_id}'")
            return
        try:
            T = pose_to_T(msg.pose)
        except ValueError as e:
            self.diag.set("base pose", WARN, f"ignored a bad base pose: {e}")
            return
        if not np.all(np.isfinite(T)):
            self.diag.set("base pose", WARN, "ignored a non-finite base pose")
            return
        self.T_omc_base = T
        self.diag.set("base pose", OK, "T_omc_base from " + self.base_pose_topic,
                      {"position": np.round(T[:3, 3], 4).tolist()})

    def on_pose(self, target: str, msg: PoseStamped) -> None:
        p_in = np.array([msg.pose.position.x, msg.pose.position.y, msg.pose.position.z])
        out = Region()
        out.header = msg.header
        out.target = target
        out.label = UNKNOWN
        with self._lock:
            layout = self.layout
        out.threshold_deg = float(layout.threshold_deg)
        frame = msg.header.frame_id
        if not np.all(np.isfinite(p_in)):
            self.diag.set(f"target {target}", WARN, "ignored a pose with NaN/inf position")
            return
        out.position = Point(x=float(p_in[0]), y=float(p_in[1]), z=float(p_in[2]))
        p_omc = None
        if frame == layout.frame_id:
            p_omc = p_in
        elif frame == self.base_frame:
            T = self.T_omc_base
            if T is None:
                self.diag.set(f"target {target}", WARN,
                              f"pose in '{frame}' but T_omc_base unknown: waiting for {self.base_pose_topic}")
            else:
                p_omc = T[:3, :3] @ p_in + T[:3, 3]
        else:
            self.diag.set(f"target {target}", ERROR,
                          f"pose frame '{frame}' is neither the layout frame '{layout.frame_id}' nor "
                          f"'{self.base_frame}'")
        if p_omc is not None:
            rf = self.region_filters[target]
            r = rf.update(stamp_to_ns(msg.header.stamp), label_point(layout, p_omc), float(layout.threshold_deg))
            lab = r.evidence
            out.label = r.label
            out.threshold_deg = float(r.threshold_deg)
            out.margin_deg = float(lab.margin_deg)
            out.valid_pairs = int(lab.valid_pairs)
            out.cameras_seeing = int(lab.cameras_seeing)
            out.in_local_volume = bool(lab.in_local_volume)
            self.counts[target] += 1
            prev = self._last_label.get(target)
            if r.label != prev:
                # one line per region change: the demo shows these live
                self._last_label[target] = r.label
                self.get_logger().info(
                    f"region {target}: {REGION_NAMES.get(prev, 'none')} -> "
                    f"{REGION_NAMES[r.label]} (margin {lab.margin_deg:.0f} deg, {lab.valid_pairs} pairs, "
                    f"p_omc=({p_omc[0]:.3f}, {p_omc[1]:.3f}, {p_omc[2]:.3f}) m)")
            self.diag.set(f"target {target}", OK, f"{REGION_NAMES[r.label]} (margin {lab.margin_deg:.0f} deg)"
                          + (f"; model says {REGION_NAMES[r.raw_label]}, held by the hysteresis" if r.held else ""),
                          {"labelled": self.counts[target], "valid_pairs": lab.valid_pairs,
                           "cameras_seeing": lab.cameras_seeing, "label_changes": rf.changes,
                           "model_label_changes": rf.raw_changes})
        self.region_pubs[target].publish(out)
        if self.marker_pubs[target].get_subscription_count():   # for RViz: built only while one is matched (volatile:
            self.marker_pubs[target].publish(region_marker(out))   # a marker no reader is matched to reaches nobody)


    def close(self) -> None:
        """Shutdown (run_node): label what the pose queues still hold. The demo stops fusion_node first, which
        publishes its drained backlog as it exits; dropped here, the task's last region was never labelled (a
        busy CI run recorded B-G for B-G-P)."""
        for target, sub in self._pose_subs.items():
            while batch := take_queued(sub):
                for msg in batch:
                    self.on_pose(target, msg)


def main(args=None) -> int:
    return run_node(MarginNode, "margin_node", (LayoutError, ParameterError, FileNotFoundError), args,
                    params_file=("fullperc_fusion", "margin.yaml"))


if __name__ == "__main__":
    sys.exit(main())
