"""fusion_node's per-output publishing: pose, pose_cov, status and /tf of every fused output, cheaply.

Why its own module and why this shape (issue 16 profile, one target at 240 + 400 Hz): building and publishing
the messages of each output took ~20 % of the node's CPU per fused pose -- new message objects every time
(each nested field a Python object whose setters check types), numpy per-element conversions, the covariance as
a 36-element list checked element by element. Here:

* one set of messages per publisher is built once and refilled (rclpy's ``publish`` converts the message to its
  C form synchronously, so nothing keeps a reference to it after the call);
* the pose is checked (finite, unit within 1e-3 -- :func:`fullperc_common.ros_conv.pose_msg`'s rule) and the
  quaternion normalised on Python floats, the covariance handed over as one float64 array;
* lazy outputs (issue "node cost"): every per-sample topic except the primary's ``/fullperc/<target>/pose`` --
  pose_cov, status, the side-by-side filters' ``/fullperc/<target>/<filter>/...``, ``final`` and /tf -- is built
  and published only while a subscription is matched. With volatile QoS a message no reader is matched to
  reaches nobody; rclpy serialises it all the same (measured: 17 us per PoseStamped published to nobody, 2 us per
  ``get_subscription_count``). The counts are cached (:class:`Listeners`) and read again at the first wake-up
  at least :data:`LISTENERS_REFRESH_S` after the last read, so a subscriber that matches late gets every output
  of the wake-ups that start more than that after its match (before it, as before, nothing).
* /tf (:class:`TfBatch`): one TFMessage per wake-up of the node (an input callback with everything it drained, a
  timer tick, the shutdown flush) carrying the transform of every primary output of every target fused in it;
  with ``tf.rate`` > 0 at most one TFMessage per ``1 / tf.rate`` s of the node's clock, carrying the newest
  transform of each target fused since the last one.
* status at a capped rate (``status_rate`` [Hz], issue 16 item 4: many targets per node): at most one FusionStatus
  per ``1 / status_rate`` of fused stamps per topic set -- by stamp, not by the host clock, so a replay gives the
  same messages -- except that an output flagged as a hop, or whose ``link_bumped`` differs from the last status
  sent, always goes out: a reader never misses the events the status exists for. 0 = every output.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from geometry_msgs.msg import Pose, PoseStamped, PoseWithCovarianceStamped, TransformStamped

from fullperc_fusion.pipeline.ordered import FusedOutput
from fullperc_msgs.msg import FusionStatus
from tf2_msgs.msg import TFMessage

__all__ = ["LISTENERS_REFRESH_S", "Listeners", "OutputPublisher", "TfBatch", "fill_pose", "publish_outputs"]

LISTENERS_REFRESH_S = 0.1   # [s] subscriber counts are read again at the first wake-up this long after the last read


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


class Listeners:
    """Whether each lazy publisher has a matched subscription, read at most every ``refresh_s`` (module docstring).

    :meth:`refresh` is called at the start of every wake-up with the node's monotonic clock; :meth:`wanted` is a
    dict lookup. Before the first read every publisher counts as unwanted."""

    def __init__(self, refresh_s: float = LISTENERS_REFRESH_S) -> None:
        self.refresh_s = refresh_s
        self._pubs: list[Any] = []
        self._on: dict[int, bool] = {}
        self._next = -math.inf
        self.reads = 0      # how often the counts were read (for the tests and the bench)

    def add(self, pub: Any) -> Any:
        """Register ``pub`` (returned); it is read at the next :meth:`refresh`."""
        self._pubs.append(pub)
        self._next = -math.inf
        return pub

    def refresh(self, now: float) -> None:
        """Read every registered publisher's subscription count when the last read is ``refresh_s`` old."""
        if now < self._next:
            return
        self._next = now + self.refresh_s
        self.reads += 1
        self._on = {id(p): p.get_subscription_count() > 0 for p in self._pubs}

    def wanted(self, pub: Any) -> bool:
        return self._on.get(id(pub), False)


class TfBatch:
    """/tf of the node: the transforms of one wake-up in one TFMessage; with ``rate`` [Hz] > 0 at most one per
    ``1 / rate`` s of the caller's clock, the newest transform of each target since the last one (module
    docstring). ``pub``: the /tf publisher (lazy: nothing is kept while nobody listens)."""

    def __init__(self, pub: Any, listeners: Listeners, rate: float = 0.0) -> None:
        self.pub, self.listeners = listeners.add(pub), listeners
        self.period = 1.0 / rate if rate > 0 else 0.0
        self._next = -math.inf
        self._pending: list[tuple[str, PoseStamped]] = []     # rate 0: every output of this wake-up
        self._newest: dict[str, tuple[str, PoseStamped]] = {}  # rate > 0: the newest per target

    def add(self, target: str, ps: PoseStamped) -> None:
        """The transform ``base -> target`` of a published primary pose ``ps`` (its values are copied now)."""
        if not self.listeners.wanted(self.pub):
            return
        t = TransformStamped()   # values copied: ``ps`` is refilled by the next output
        h, src = ps.header, ps.pose
        t.header.stamp.sec, t.header.stamp.nanosec = h.stamp.sec, h.stamp.nanosec
        t.header.frame_id = h.frame_id
        t.child_frame_id = target
        tr, pos, ori = t.transform, src.position, src.orientation
        tr.translation.x, tr.translation.y, tr.translation.z = pos.x, pos.y, pos.z
        r = tr.rotation
        r.x, r.y, r.z, r.w = ori.x, ori.y, ori.z, ori.w
        if self.period:
            self._newest[target] = (target, t)
        else:
            self._pending.append((target, t))

    def flush(self, now: float) -> int:
        """The end of a wake-up: publish what is due as one TFMessage; returns the transforms sent."""
        if self.period:
            if not self._newest or now < self._next:
                return 0
            # on a grid of 1 / rate while the wake-ups keep up (a 10 ms timer tick is no drift); restarted from
            # now after a gap (no burst to catch up)
            late = now - self._next
            self._next = (self._next if late < self.period else now) + self.period
            items, self._newest = list(self._newest.values()), {}
        else:
            if not self._pending:
                return 0
            items, self._pending = self._pending, []
        self.pub.publish(TFMessage(transforms=[t for _, t in items]))
        return len(items)


class OutputPublisher:
    """The messages of one (target, key) topic set, built once and refilled per output (module docstring)."""

    def __init__(self, pose_pub: Any, cov_pub: Any | None, status_pub: Any, always_pose: bool,
                 status_rate: float = 0.0, listeners: Listeners | None = None) -> None:
        self.listeners = listeners if listeners is not None else Listeners(refresh_s=0.0)
        for pub in (cov_pub, status_pub) if always_pose else (pose_pub, cov_pub, status_pub):
            if pub is not None:
                self.listeners.add(pub)
        self.pose_pub, self.cov_pub, self.status_pub = pose_pub, cov_pub, status_pub
        self.always_pose = always_pose      # the primary's pose is never skipped
        self.status_period_ns = int(round(1e9 / status_rate)) if status_rate > 0 else 0
        self._status_last: tuple[int, bool] | None = None   # (stamp, link_bumped) of the last status sent
        self.ps = PoseStamped()
        self.ps.header.frame_id = "base"
        self.pc = PoseWithCovarianceStamped()
        self.pc.header.frame_id = "base"
        self.st = FusionStatus()
        self.st.header.frame_id = "base"

    def publish(self, target: str, o: FusedOutput, region: int) -> None:
        """Publish ``o`` on this set's topics (those wanted); a refused pose raises ValueError (:func:`fill_pose`)
        before anything is published. ``self.ps`` holds the pose afterwards (the /tf transform is copied from it)."""
        fill_pose(self.ps.pose, o.p, o.q)   # checked even when nothing goes out: the refusal is counted as before
        wanted = self.listeners.wanted
        pose_on = self.always_pose or wanted(self.pose_pub)
        cov_on = self.cov_pub is not None and wanted(self.cov_pub)
        st_on = wanted(self.status_pub) and self._status_due(o)
        sec, nsec = divmod(int(o.t_ns), 1_000_000_000)
        stamp = self.ps.header.stamp
        stamp.sec, stamp.nanosec = sec, nsec
        if pose_on:
            self.pose_pub.publish(self.ps)
        if cov_on:
            pc = self.pc
            stamp = pc.header.stamp
            stamp.sec, stamp.nanosec = sec, nsec
            src, dst = self.ps.pose, pc.pose.pose
            dst.position, dst.orientation = src.position, src.orientation
            pc.pose.covariance = np.array(o.cov, dtype=np.float64).reshape(36)
            self.cov_pub.publish(pc)
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


def publish_outputs(sets: dict[tuple[str, str], OutputPublisher], target: str, outs: Iterable[FusedOutput],
                    primary: str, extra: Iterable[str], region: int,
                    on_primary: Callable[[FusedOutput], None], on_error: Callable[[FusedOutput, str], None],
                    tf: TfBatch | None) -> None:
    """fusion_node's per-output loop: the primary's outputs on ``/fullperc/<target>/...`` (and into the wake-up's
    /tf batch ``tf``), a side-by-side filter's on ``/fullperc/<target>/<filter>/...``. ``on_primary``: the health
    monitor's hook; ``on_error``: a refused (non-finite) pose."""
    extra = set(extra)
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
            if key == "" and tf is not None:
                tf.add(target, sets[(target, key)].ps)
