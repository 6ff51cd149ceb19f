"""Orientation error and pose-error vectors against the ground truth (issue 18 item 5).

The position error alone hides what a surgeon sees at the tip: 1 deg of axis error is 2.6 mm at 150 mm. So every
method is also judged on its orientation:

* **orientation error** [deg] of an estimate R_est against the truth R_true (Diana FK, :mod:`.ground_truth`) is
  the angle of the relative rotation R_true^T R_est -- the smallest rotation that takes one onto the other,
  independent of the frame it is expressed in and of the quaternion sign;
* the **pose error vector** (for the NEES, :mod:`.consistency`) follows the covariance convention of
  :mod:`fullperc_fusion.filters.api`: delta = [p_true - p_est, dtheta] with R_true = exp([dtheta]x) R_est, the
  rotation part a small rotation vector about the axes of ``base``. Using the same convention as the filters' 6x6
  covariance is what makes the cross terms of a full pose covariance meaningful.

Pure numpy/scipy; every function takes stacked arrays (N, ...) and returns NaN where an input is missing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_fusion.calibration.so3_stack import near_quats


def _valid_quats(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1)
    return np.all(np.isfinite(q), axis=1) & (n > 0.5)


def _valid_rots(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    return np.all(np.isfinite(R), axis=(1, 2))


def _from_matrix(R: np.ndarray) -> Rotation:
    """``Rotation.from_matrix(R)`` of a stack (N, 3, 3), the same quaternions: scipy's own conversion of each matrix
    (:func:`~fullperc_fusion.calibration.so3_stack.near_quats`, which vouches for its checks) held as they are, as
    from_matrix holds them. Why: from_matrix's checks (an LAPACK determinant and a Gram product per matrix) cost ~0.3
    us per matrix, ten times the conversion; matrices that need them go through from_matrix itself."""
    q = near_quats(R)
    return Rotation.from_matrix(R) if q is None else Rotation(q, normalize=False, copy=False)


def _compose(a: Rotation, b: Rotation) -> Rotation:
    """``a * b`` of two stacks of N rotations, the same quaternions: scipy's composition (its Cython loop
    ``_compose_quat_single``: p_w q_v + q_w p_v + p_v x q_v and p_w q_w - p_v . q_v, each sum from the left) and the
    normalisation ``Rotation(., normalize=True)`` applies (divide by sqrt(x^2 + y^2 + z^2 + w^2), summed from the
    left) written on arrays in the same order of operations, which gives the same floats (neither has a fused
    multiply-add). Why: that loop takes ~0.4 us per rotation, the larger part of the evaluator's orientation
    figures. A zero norm (scipy raises), and anything but two stacks of one length, go through ``a * b`` itself."""
    p, q = a.as_quat(), b.as_quat()
    if p.ndim != 2 or p.shape != q.shape:
        return a * b
    p0, p1, p2, p3 = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    q0, q1, q2, q3 = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty(p.shape)
    r[:, 0] = p3 * q0 + q3 * p0 + (p1 * q2 - p2 * q1)
    r[:, 1] = p3 * q1 + q3 * p1 + (p2 * q0 - p0 * q2)
    r[:, 2] = p3 * q2 + q3 * p2 + (p0 * q1 - p1 * q0)
    r[:, 3] = p3 * q3 - p0 * q0 - p1 * q1 - p2 * q2
    n = np.sqrt(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1] + r[:, 2] * r[:, 2] + r[:, 3] * r[:, 3])
    if not (n > 0).all():
        return a * b
    return Rotation(r / n[:, None], normalize=False, copy=False)


def orientation_error_deg(R_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """Angle [deg] of R_true^T R_est for (N, 3, 3) true rotations and (N, 4) estimated quaternions x y z w.

    NaN where either is missing (non-finite, or a quaternion of norm < 0.5 -- not an orientation). The angle is
    taken with scipy's ``Rotation.magnitude`` (2 atan2(|v|, |w|) of the relative quaternion), which stays
    accurate for small angles where ``arccos((tr - 1) / 2)`` loses half the digits.
    """
    R_true = np.asarray(R_true, dtype=float).reshape(-1, 3, 3)
    q_est = np.asarray(q_est, dtype=float).reshape(-1, 4)
    if len(R_true) != len(q_est):
        raise ValueError(f"orientation error: {len(R_true)} true rotations, {len(q_est)} estimates")
    out = np.full(len(q_est), np.nan)
    ok = _valid_quats(q_est) & _valid_rots(R_true)
    if ok.any():
        rel = _compose(_from_matrix(R_true[ok]).inv(), Rotation.from_quat(q_est[ok]))
        out[ok] = np.degrees(rel.magnitude())
    return out


def pose_error(p_true: np.ndarray, R_true: np.ndarray, p_est: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """(N, 6) error vectors [p_true - p_est (m), dtheta (rad)], R_true = exp([dtheta]x) R_est (filter_api).

    The rotation part is NaN where the estimate has no orientation; the position part where it has no position.
    """
    p_true = np.asarray(p_true, dtype=float).reshape(-1, 3)
    p_est = np.asarray(p_est, dtype=float).reshape(-1, 3)
    R_true = np.asarray(R_true, dtype=float).reshape(-1, 3, 3)
    q_est = np.asarray(q_est, dtype=float).reshape(-1, 4)
    out = np.full((len(p_est), 6), np.nan)
    out[:, :3] = p_true - p_est
    ok = _valid_quats(q_est) & _valid_rots(R_true)
    if ok.any():
        out[ok, 3:] = _compose(_from_matrix(R_true[ok]), Rotation.from_quat(q_est[ok]).inv()).as_rotvec()
    return out


def orientation_and_pose_error(p_true: np.ndarray, R_true: np.ndarray, p_est: np.ndarray,
                               q_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(orientation_error_deg(R_true, q_est), pose_error(p_true, R_true, p_est, q_est))``, the same numbers, with
    the truth's and the estimate's scipy Rotations built once for both (the evaluator needs both of every method;
    ``Rotation.from_matrix`` of a few thousand matrices was the larger part of each). test_orientation_pair.py pins it
    to the two functions bit for bit, and :func:`_from_matrix` / :func:`_compose` (all three use them) to scipy's
    ``Rotation.from_matrix`` and product."""
    R_true = np.asarray(R_true, dtype=float).reshape(-1, 3, 3)
    q_est = np.asarray(q_est, dtype=float).reshape(-1, 4)
    p_true = np.asarray(p_true, dtype=float).reshape(-1, 3)
    p_est = np.asarray(p_est, dtype=float).reshape(-1, 3)
    if not (len(R_true) == len(q_est) == len(p_true) == len(p_est)):
        return orientation_error_deg(R_true, q_est), pose_error(p_true, R_true, p_est, q_est)   # their errors
    ang = np.full(len(q_est), np.nan)
    d = np.full((len(p_est), 6), np.nan)
    d[:, :3] = p_true - p_est
    ok = _valid_quats(q_est) & _valid_rots(R_true)
    if ok.any():
        Rt, Re = _from_matrix(R_true[ok]), Rotation.from_quat(q_est[ok])
        ang[ok] = np.degrees(_compose(Rt.inv(), Re).magnitude())
        d[ok, 3:] = _compose(Rt, Re.inv()).as_rotvec()
    return ang, d
