"""Rigid transforms as 4x4 numpy arrays, and the one place quaternion order is converted.

Conventions (pinned by test_transforms.py):
  * topics and our code use quaternions in ROS order (x, y, z, w), scalar last;
  * NDI replies give (q0, qx, qy, qz), scalar first -> :func:`quat_wxyz_to_xyzw`;
  * ``T_a_b`` maps points from frame b into frame a: p_a = T_a_b @ p_b.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

ArrayLike = Sequence[float] | np.ndarray


def quat_wxyz_to_xyzw(q: ArrayLike) -> np.ndarray:
    """NDI/pinocchio-coefficient order (w, x, y, z) -> ROS order (x, y, z, w)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 1:4], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(q: ArrayLike) -> np.ndarray:
    """ROS order (x, y, z, w) -> scalar-first (w, x, y, z)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def is_finite_pose(p: ArrayLike, q_xyzw: ArrayLike, unit_tol: float = 1e-3) -> bool:
    """True when position and quaternion are finite and the quaternion is unit within ``unit_tol``."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q_xyzw, dtype=float)
    if p.shape != (3,) or q.shape != (4,):
        return False
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return False
    return abs(float(np.linalg.norm(q)) - 1.0) <= unit_tol


def make_T(p: ArrayLike, q_xyzw: ArrayLike | None = None, R: np.ndarray | None = None) -> np.ndarray:
    """Homogeneous transform from a translation and a quaternion (x y z w) or a 3x3 rotation."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    elif q_xyzw is not None:
        T[:3, :3] = Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()
    T[:3, 3] = np.asarray(p, dtype=float)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (R^T, -R^T p) without a general matrix inverse."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def T_to_pq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a transform into position and quaternion (x y z w, w >= 0)."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return T[:3, 3].copy(), q


def apply_T(T: np.ndarray, pts: ArrayLike) -> np.ndarray:
    """Apply a transform to one point (3,) or many points (N, 3)."""
    pts = np.asarray(pts, dtype=float)
    return pts @ T[:3, :3].T + T[:3, 3]


def mean_T(Ts: Sequence[np.ndarray]) -> np.ndarray:
    """Average of rigid transforms: arithmetic mean of translations, chordal L2 mean of rotations.

    The rotation mean is scipy's ``Rotation.mean`` (the quaternion-outer-product eigenvector),
    not a component-wise average, which would not even be a rotation.
    """
    Ts = list(Ts)
    if not Ts:
        raise ValueError("mean_T needs at least one transform")
    R = Rotation.from_matrix(np.stack([T[:3, :3] for T in Ts])).mean().as_matrix()
    p = np.mean(np.stack([T[:3, 3] for T in Ts]), axis=0)
    return make_T(p, R=R)
