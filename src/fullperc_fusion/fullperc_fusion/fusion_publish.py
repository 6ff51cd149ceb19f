"""fusion_node's per-output publishing: pose, pose_cov and status of every fused output, cheaply.

Why its own module and why this shape (issue 16 profile, one target at 240 + 400 Hz): building and publishing
the messages of each output took ~20 % of the node's CPU per fused pose -- new message objects every time
(each nested field a Python object whose setters check types), numpy per-element conversions, the covariance as
a 36-element list checked element by element. Here:

* one set of messages per publisher is built once and refilled (rclpy's ``publish`` converts the message to its
  C form synchronously, so nothing keeps a reference to it after the call);
* the pose is checked (finite, unit within 1e-3 -- :func:`fullperc_common.ros_conv.pose_msg`'s rule) and the
  quaternion normalised on Python floats, the covariance handed over as one float64 array;
* every topic -- pose, pose_cov, velocity, status, a side-by-side filter's ``/fullperc/<target>/<filter>/...`` --
  is built and published only while a subscription is matched (``get_subscription_count``, ~1 us): with volatile
  QoS a message no reader is matched to reaches nobody, so skipping it cannot be observed (a reader that matches
  later gets the next message, as it would have anyway). rclpy's per-message path, not the maths, is most of the
  node's cost (``bench/bench_node_cost.py``), so a message nobody reads is the cheapest saving: a
  consumer of the fused pose only no longer pays for pose_cov, status and /tf (fusion_node checks /tf the same
  way, ``tf.Broadcaster.wanted``).
* status at a capped rate (``status_rate`` [Hz], issue 16 item 4: many targets per node): at most one FusionStatus
  per ``1 / status_rate`` of fused stamps per topic set -- by stamp, not by the host clock, so a replay gives the
  same messages -- except that an output flagged as a hop, or whose ``link_bumped`` differs from the last status
  sent, always goes out: a reader never misses the events the status exists for. 0 = every output.
* velocity (``publish_velocity``, issue 39): a TwistWithCovarianceStamped per output of the primary filter, in the
  outputs' frame (``frames.base``). Linear: the filter's constant-velocity state v and its covariance block
  (:meth:`FusedOutput.velocity`, read only here: nothing else the pipeline computes changes). Angular: not estimated
  by the paper's filters, so zero with a variance of :data:`ANGULAR_VAR_UNKNOWN` per axis -- "unknown" in ROS terms,
  which a consumer's fusion then ignores -- rather than a finite difference of orientations, whose noise (the OMC's
  few mrad per sample at 120 Hz: ~1 rad/s) would be presented as a measurement. The raw ``omc`` filter has no
  velocity state: nothing is published for it.
* the poses array (``publish_poses``, issue 38 item 1): ``fullperc/poses`` (fullperc_msgs/FusedPoseArray), once per
  wake-up, the newest primary output of every target that had one -- the field comments of FusedPoseArray.msg say
  what each holds. Why: a consumer of many targets otherwise matches a pose_cov subscription per target and pays
  rclpy's per-message path per target and output; one message per wake-up costs it (and the node) one. It is
  collected as /tf is (``tf.Broadcaster``: ``add`` per output, one message at the end of the wake-up), keeps only a
  reference per target until then (the last output a target's pose topic got, so an entry equals the newest
  ``/fullperc/<target>/pose_cov`` of the wake-up), and builds and publishes nothing while no reader is matched.

Every header's frame is the node's ``frames.base`` (``frame`` here).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from geometry_msgs.msg import Pose, PoseStamped, PoseWithCovarianceStamped, TwistWithCovarianceStamped

from fullperc_common.ros_conv import ns_to_stamp, pose_msg
from fullperc_fusion.pipeline.ordered import FusedOutput
from fullperc_msgs.msg import FusedPose, FusedPoseArray, FusionStatus

__all__ = ["ANGULAR_VAR_UNKNOWN", "OutputPublisher", "PosesPublisher", "fill_pose", "publish_final",
           "publish_outputs"]

ANGULAR_VAR_UNKNOWN = 1.0e6   # [(rad/s)^2] variance of the angular velocity, which no filter estimates (docstring)


def covariance36(cov: Any) -> np.ndarray:
    """A pose covariance as pose_cov carries it: 36 float64, row-major, a copy (the message keeps what it is given);
    ValueError unless a finite 6x6."""
    c = np.array(cov, dtype=np.float64)
    if c.shape != (6, 6) or not np.isfinite(c).all():   # a filter fault; no covariance topic carries NaN
        raise ValueError(f"refusing to publish a non-finite or malformed covariance (shape {c.shape})")
    return c.reshape(36)


def fill_pose(pose: Pose, p: Any, q_xyzw: Any) -> None:
    """Write position and normalised quaternion into ``pose``; ValueError on NaN/inf or a non-unit quaternion
    (off by more than 1e-3, as ``pose_msg``), before anything is written."""
    try:
        px, py, pz = np.asarray(p, dtype=float).tolist()
        x, y, z, w = np.asarray(q_xyzw, dtype=float).tolist()
    except (TypeError, ValueError):
        raise ValueError(f"refusing to publish a malformed pose: p={p}, q={q_xyzw}") from None
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz) and math.isfinite(n)
            and abs(n - 1.0) <= 1e-3):
        raise ValueError(f"refusing to publish a non-finite or non-unit pose: p={p}, q={q_xyzw}")
    pos, ori = pose.position, pose.orientation
    pos.x, pos.y, pos.z = px, py, pz
    ori.x, ori.y, ori.z, ori.w = x / n, y / n, z / n, w / n


def _fill_vector3(v: Any, xyz: Any) -> None:
    v.x, v.y, v.z = (float(c) for c in xyz)


class OutputPublisher:
    """The messages of one (target, key) topic set, built once and refilled per output (module docstring)."""

    def __init__(self, pose_pub: Any, cov_pub: Any | None, status_pub: Any,
                 status_rate: float = 0.0, frame: str = "base", vel_pub: Any | None = None) -> None:
        self.pose_pub, self.cov_pub, self.status_pub, self.vel_pub = pose_pub, cov_pub, status_pub, vel_pub
        self.status_rate = status_rate
        self._status_last: tuple[int, bool] | None = None   # (stamp, link_bumped) of the last status sent
        self.ps = PoseStamped()
        self.ps.header.frame_id = frame
        self.pc = PoseWithCovarianceStamped()
        self.pc.header.frame_id = frame
        self.st = FusionStatus()
        self.st.header.frame_id = frame
        self.tw = TwistWithCovarianceStamped()
        self.tw.header.frame_id = frame
        cov = np.zeros((6, 6))
        cov[3:6, 3:6] = np.eye(3) * ANGULAR_VAR_UNKNOWN
        self._twist_cov = cov

    @property
    def status_rate(self) -> float:
        """[Hz] the status cap (0: every output); settable at run time (``status_rate`` is a live parameter)."""
        return 1e9 / self.status_period_ns if self.status_period_ns else 0.0

    @status_rate.setter
    def status_rate(self, rate: float) -> None:
        self.status_period_ns = int(round(1e9 / rate)) if rate > 0 else 0

    @staticmethod
    def _wanted(pub: Any) -> bool:
        return pub.get_subscription_count() > 0

    def publish(self, target: str, o: FusedOutput, region: int) -> None:
        """Publish ``o`` on this set's topics (those wanted); a refused pose raises ValueError (:func:`fill_pose`)
        before anything is published."""
        fill_pose(self.ps.pose, o.p, o.q)   # checked even when nothing goes out: the refusal is counted as before
        cov = covariance36(o.cov)
        pose_on = self._wanted(self.pose_pub)
        cov_on = self.cov_pub is not None and self._wanted(self.cov_pub)
        st_on = self._wanted(self.status_pub) and self._status_due(o)
        sec, nsec = divmod(int(o.t_ns), 1_000_000_000)
        if pose_on:
            stamp = self.ps.header.stamp
            stamp.sec, stamp.nanosec = sec, nsec
            self.pose_pub.publish(self.ps)
        if cov_on:
            pc = self.pc
            stamp = pc.header.stamp
            stamp.sec, stamp.nanosec = sec, nsec
            src, dst = self.ps.pose, pc.pose.pose
            dst.position, dst.orientation = src.position, src.orientation
            pc.pose.covariance = cov
            self.cov_pub.publish(pc)
        if self.vel_pub is not None and self._wanted(self.vel_pub) and (vel := o.velocity()) is not None \
                and np.isfinite(vel[1]).all() and np.isfinite(vel[0]).all():
            tw = self.tw
            stamp = tw.header.stamp
            stamp.sec, stamp.nanosec = sec, nsec
            _fill_vector3(tw.twist.twist.linear, vel[0])
            cov = self._twist_cov
            cov[0:3, 0:3] = vel[1]
            tw.twist.covariance = cov.reshape(36)
            self.vel_pub.publish(tw)
        if st_on:
            st = self.st
            stamp = st.header.stamp
            stamp.sec, stamp.nanosec = sec, nsec
            st.target = target
            st.filter = o.filter
            st.sources = int(o.sources)
            st.orientation_source = int(o.orientation_source)
            _fill_vector3(st.bias, o.bias)
            _fill_vector3(st.innovation, o.innovation)
            st.nis = float(o.nis)
            st.hop = bool(o.hop)
            st.time_since_local = float(o.time_since_local)
            st.region = region
            st.link_bumped = bool(o.link_bumped)
            self.status_pub.publish(st)
            self._status_last = (int(o.t_ns), st.link_bumped)

    def _status_due(self, o: FusedOutput) -> bool:
        """The status cap (module docstring): due when uncapped, first, a hop, a link_bumped change, or a period of
        fused stamps after the last one sent (a stamp earlier than that one -- a restarted timeline -- too)."""
        last = self._status_last
        if not self.status_period_ns or last is None or o.hop or bool(o.link_bumped) != last[1]:
            return True
        dt = int(o.t_ns) - last[0]
        return dt >= self.status_period_ns or dt < 0


class PosesPublisher:
    """``fullperc/poses``: one FusedPoseArray per wake-up with the newest primary output of every target that had one
    (module docstring). :meth:`add` per published output, :meth:`flush` at the end of the wake-up.

    ``pub`` None (``publish_poses: false``): no topic, every call a no-op. ``targets`` fixes the entries' order (the
    node's ``targets``: a consumer reads the array the same way every time). ``on_error(target, output, why)``: an
    output refused here (:func:`fill_pose`'s checks, or a non-finite covariance) -- left out, never sent as NaN."""

    def __init__(self, pub: Any | None, frame: str, targets: Iterable[str],
                 on_error: Callable[[str, FusedOutput, str], None] | None = None) -> None:
        self.pub = pub
        self.on_error = on_error
        self.msg = FusedPoseArray()
        self.msg.header.frame_id = frame
        self._entries = {t: FusedPose(target=t) for t in targets}   # built once, refilled (as OutputPublisher's)
        self._newest: dict[str, FusedOutput] = {}   # target -> its last output of this wake-up

    def add(self, target: str, o: FusedOutput) -> None:
        """``o`` was published as ``target``'s fused pose: the entry of this wake-up, unless a later one comes."""
        if self.pub is not None:
            self._newest[target] = o

    def flush(self) -> FusedPoseArray | None:
        """Publish the wake-up's entries as one message (returned; None when nothing went out: no entry, no reader,
        or every entry refused) and start the next wake-up."""
        newest, self._newest = self._newest, {}
        if not newest or not self.pub.get_subscription_count():
            return None
        poses, t_max = [], None
        for target, e in self._entries.items():
            o = newest.get(target)
            if o is None:
                continue
            try:
                fill_pose(e.pose.pose, o.p, o.q)
                cov = covariance36(o.cov)
            except ValueError as err:
                if self.on_error is not None:
                    self.on_error(target, o, f"fullperc/poses: {err}")
                continue
            e.pose.covariance = cov
            e.stamp.sec, e.stamp.nanosec = divmod(int(o.t_ns), 1_000_000_000)
            poses.append(e)
            t_max = int(o.t_ns) if t_max is None else max(t_max, int(o.t_ns))
        if t_max is None:
            return None
        msg = self.msg
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_max, 1_000_000_000)
        msg.poses = poses
        self.pub.publish(msg)
        return msg


def publish_outputs(sets: dict[tuple[str, str], OutputPublisher], target: str, outs: Iterable[FusedOutput],
                    primary: str, extra: Iterable[str], region: int,
                    on_primary: Callable[[FusedOutput], None], on_error: Callable[[FusedOutput, str], None],
                    tf_of: Callable[[FusedOutput], Any] | None, poses: PosesPublisher | None = None) -> list:
    """fusion_node's per-output loop: the primary's outputs on ``/fullperc/<target>/...`` (and /tf: the returned
    transforms; ``fullperc/poses``: added to ``poses``), a side-by-side filter's on ``/fullperc/<target>/<filter>/...``.
    ``on_primary``: the health monitor's hook; ``on_error``: a refused (non-finite) pose; ``tf_of``: the /tf transform
    of an output."""
    extra = set(extra)
    tfs = []
    for o in outs:
        is_primary = o.filter == primary
        if is_primary:
            on_primary(o)
        keys = ([""] if is_primary else []) + ([o.filter] if o.filter in extra else [])
        for key in keys:
            try:
                sets[(target, key)].publish(target, o, region)
            except ValueError as e:   # never publish NaN; the pipeline should have caught it already
                on_error(o, str(e))
                continue
            if key == "":
                if tf_of is not None:
                    tfs.append(tf_of(o))
                if poses is not None:
                    poses.add(target, o)
    return tfs


def publish_final(pub: Any | None, outs: Iterable[FusedOutput], frame: str) -> None:
    """``fullperc/<target>/final``: the primary filter's estimates of the items that left the history, while a reader
    is matched (volatile, as every output here); a pose ``pose_msg`` refuses (NaN) is skipped."""
    if pub is None or not pub.get_subscription_count():
        return
    for o in outs:
        ps = PoseStamped()
        ps.header.stamp = ns_to_stamp(o.t_ns)
        ps.header.frame_id = frame
        try:
            ps.pose = pose_msg(o.p, o.q)
        except ValueError:
            continue
        pub.publish(ps)
