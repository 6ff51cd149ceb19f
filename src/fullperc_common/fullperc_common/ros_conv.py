"""Conversion between numpy and ROS messages, with the unit and order conventions in one place.

Stamps are integer nanoseconds on the host clock (``time.time_ns()`` domain) everywhere in our
cores; only this module turns them into ``builtin_interfaces/Time``.
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Vector3

from .transforms import T_to_pq, is_finite_pose, make_T


def ns_to_stamp(ns: int) -> Time:
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def pose_msg(p, q_xyzw) -> Pose:
    """Pose from position [m] and quaternion (x y z w). Raises ValueError on NaN/inf/non-unit."""
    if not is_finite_pose(p, q_xyzw, unit_tol=1e-3):
        raise ValueError(f"refusing to publish a non-finite or non-unit pose: p={p}, q={q_xyzw}")
    q = np.asarray(q_xyzw, dtype=float)
    q = q / np.linalg.norm(q)
    return Pose(
        position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def pose_stamped(stamp_ns: int, frame_id: str, p, q_xyzw) -> PoseStamped:
    msg = PoseStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.pose = pose_msg(p, q_xyzw)
    return msg


def pose_to_pq(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    p = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=float)
    o = pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    return p, q


def pose_to_T(pose: Pose) -> np.ndarray:
    p, q = pose_to_pq(pose)
    return make_T(p, q)


def T_to_pose(T: np.ndarray) -> Pose:
    p, q = T_to_pq(T)
    return pose_msg(p, q)


def vector3(v) -> Vector3:
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))
