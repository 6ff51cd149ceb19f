"""TF without tf2_ros: ``TransformStamped`` from our transforms, and the two broadcasters tf2_ros would give.

The PyPI-wheel ROS has no tf2_ros; the messages are ``tf2_msgs/msg/TFMessage`` (the system's tf2_msgs, or the
workspace's stand-in ``src/tf2_msgs`` with upstream's definition and type hash), so RViz2, ``tf2_echo`` and bags
of a full ROS install see the same topics:

* :class:`Broadcaster`: ``/tf`` with tf2_ros's ``DynamicBroadcasterQoS`` (reliable, volatile, keep last 100).
* :class:`StaticBroadcaster`: ``/tf_static`` with tf2_ros's ``StaticBroadcasterQoS`` (reliable, transient local,
  keep last 1); like ``StaticTransformBroadcaster`` every message holds the union of all static transforms sent so
  far (one per child frame, the newest wins), so a late subscriber gets the whole static tree from one message.

``T_parent_child`` follows :mod:`fullperc_common.transforms`: it maps points from the child frame into the
parent frame, which is exactly what a TF ``parent -> child`` transform holds (the child's pose in the parent).
"""

from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import Quaternion, TransformStamped, Vector3
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from tf2_msgs.msg import TFMessage

from .ros_conv import ns_to_stamp
from .transforms import T_to_pq, is_finite_pose, make_T

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"


def dynamic_qos() -> QoSProfile:
    """tf2_ros.DynamicBroadcasterQoS: reliable, volatile, keep last 100."""
    return QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def static_qos() -> QoSProfile:
    """tf2_ros.StaticBroadcasterQoS: reliable, transient local, keep last 1."""
    return QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def static_listener_qos() -> QoSProfile:
    """tf2_ros.StaticListenerQoS: reliable, transient local, keep last 100. A subscriber of /tf_static needs the
    depth: each broadcaster's message lands in one keyless instance, so with depth 1 a reader that takes late keeps
    only the newest of several nodes' messages (a test listener on a busy machine lost one node's base -> ots)."""
    return QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def transform_stamped(stamp_ns: int, parent: str, child: str, T: np.ndarray | None = None, p=None,
                      q_xyzw=None) -> TransformStamped:
    """``parent -> child`` from ``T`` (= T_parent_child, 4x4) or from position [m] + quaternion (x y z w).
    Raises ValueError on an empty frame name, parent == child, or a non-finite / non-unit pose."""
    if not parent or not child or parent == child:
        raise ValueError(f"transform needs two different, non-empty frames, got '{parent}' -> '{child}'")
    if T is not None:
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"refusing a non-finite or malformed transform {parent} -> {child}")
        p, q_xyzw = T_to_pq(T)
    if p is None or q_xyzw is None or not is_finite_pose(p, q_xyzw, unit_tol=1e-3):
        raise ValueError(f"refusing a non-finite or non-unit transform {parent} -> {child}: p={p}, q={q_xyzw}")
    q = np.asarray(q_xyzw, dtype=float)
    q = q / np.linalg.norm(q)
    msg = TransformStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = parent
    msg.child_frame_id = child
    msg.transform.translation = Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
    msg.transform.rotation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
    return msg


def transform_to_T(msg: TransformStamped) -> np.ndarray:
    """T_parent_child of a TransformStamped."""
    t, r = msg.transform.translation, msg.transform.rotation
    return make_T([t.x, t.y, t.z], [r.x, r.y, r.z, r.w])


class Broadcaster:
    """``/tf``: ``send(transforms)`` publishes one TFMessage; ``add`` collects transforms and ``flush`` publishes
    everything collected as one TFMessage -- a node with many targets sends one message per wake-up instead of one
    per target (every message costs rclpy's per-message path; a tf2 listener takes the transforms alike).

    ``rate`` [Hz] > 0 caps what ``add`` keeps: per child frame, a transform stamped at least ``1 / rate`` after the
    last one kept (by stamp, not by the host clock, so a replay keeps the same ones; a stamp before the last one --
    time went back -- is kept and starts again). 0 keeps every transform. Why: a viewer or a consumer of many targets
    (RViz2, a tf2 buffer) wants the tree at its display rate, not every fused sample of every target."""

    def __init__(self, node: Node, topic: str = TF_TOPIC, rate: float = 0.0) -> None:
        if not (rate >= 0.0 and math.isfinite(rate)):
            raise ValueError(f"tf rate must be a finite number >= 0 Hz, got {rate}")
        self.pub = node.create_publisher(TFMessage, topic, dynamic_qos())
        self._pending: list[TransformStamped] = []
        self.period_ns = int(round(1e9 / rate)) if rate > 0 else 0
        self._kept: dict[str, int] = {}   # child frame -> stamp [ns] of the last transform kept

    def send(self, transforms: list[TransformStamped]) -> None:
        if transforms:
            self.pub.publish(TFMessage(transforms=list(transforms)))

    def add(self, transforms: list[TransformStamped]) -> None:
        if not self.period_ns:
            self._pending.extend(transforms)
            return
        for t in transforms:
            ns = t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec
            last = self._kept.get(t.child_frame_id)
            if last is None or ns < last or ns - last >= self.period_ns:
                self._kept[t.child_frame_id] = ns
                self._pending.append(t)

    def flush(self) -> None:
        pending, self._pending = self._pending, []
        self.send(pending)

    def wanted(self) -> bool:
        """Whether a reader is matched: /tf is volatile, so transforms built while none is reach nobody."""
        return self.pub.get_subscription_count() > 0


class StaticBroadcaster:
    """``/tf_static``: ``send(transforms)`` merges them (by child frame) into the static set and publishes the
    union; :meth:`remove` drops a child frame (published on the next send)."""

    def __init__(self, node: Node, topic: str = TF_STATIC_TOPIC) -> None:
        self.pub = node.create_publisher(TFMessage, topic, static_qos())
        self.transforms: dict[str, TransformStamped] = {}

    def send(self, transforms: list[TransformStamped]) -> None:
        for t in transforms:
            self.transforms[t.child_frame_id] = t
        self.pub.publish(TFMessage(transforms=list(self.transforms.values())))

    def remove(self, child: str) -> None:
        self.transforms.pop(child, None)
