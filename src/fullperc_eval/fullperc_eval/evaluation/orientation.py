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


def _valid_quats(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1)
    return np.all(np.isfinite(q), axis=1) & (n > 0.5)


def _valid_rots(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    return np.all(np.isfinite(R), axis=(1, 2))


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
        rel = Rotation.from_matrix(R_true[ok]).inv() * Rotation.from_quat(q_est[ok])
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
        out[ok, 3:] = (Rotation.from_matrix(R_true[ok]) * Rotation.from_quat(q_est[ok]).inv()).as_rotvec()
    return out


def orientation_and_pose_error(p_true: np.ndarray, R_true: np.ndarray, p_est: np.ndarray,
                               q_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(orientation_error_deg(R_true, q_est), pose_error(p_true, R_true, p_est, q_est))``, the same numbers, with
    the truth's and the estimate's scipy Rotations built once for both (the evaluator needs both of every method;
    ``Rotation.from_matrix`` of a few thousand matrices was the larger part of each). test_orientation_pair.py pins it
    to the two functions bit for bit."""
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
        Rt, Re = Rotation.from_matrix(R_true[ok]), Rotation.from_quat(q_est[ok])
        ang[ok] = np.degrees((Rt.inv() * Re).magnitude())
        d[ok, 3:] = (Rt * Re.inv()).as_rotvec()
    return ang, d
