"""Rigid transforms as 4x4 numpy arrays, and the one place quaternion order is converted.

Conventions (pinned by test_transforms.py):
  * topics and our code use quaternions in ROS order (x, y, z, w), scalar last;
  * NDI replies give (q0, qx, qy, qz), scalar first -> :func:`quat_wxyz_to_xyzw`;
  * ``T_a_b`` maps points from frame b into frame a: p_a = T_a_b @ p_b.

Speed: :func:`make_T` and :func:`T_to_pq` run once or twice per sample in the fusion node (validation of every
pose, the measurement of every item). scipy's ``Rotation`` costs ~15-30 us per single conversion (object
construction, array-API dispatch, shape checks); the same formulas on Python floats cost ~2-4 us (issue 16
profile: scipy conversions were a third of the node's CPU per fused pose). So the single-pose conversions are
written here in closed form, with scipy's own formulas and branch rules (quaternion normalisation, Shepperd's
method with numpy's first-maximum tie rule, a non-orthogonal matrix projected by scipy itself), and
test_transforms.py pins them to scipy on random and edge-case inputs. Batch math (:func:`mean_T`) keeps scipy.

Imports: scipy is imported where it is used, not here: a driver that only converts poses (ros_conv) would pay
scipy.spatial's imports (kd-trees, qhull, sparse: ~0.3-0.5 s of every process start) for a fallback it never takes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

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


def quat_to_R_rows(x: float, y: float, z: float, w: float) -> tuple[tuple[float, float, float], ...]:
    """Rotation matrix rows of the quaternion (x y z w), normalised first; scipy's ``from_quat().as_matrix()``.

    Plain floats (see the module docstring for why). A zero or NaN quaternion raises ValueError as scipy does
    (its message); an infinite one gives a NaN matrix, as in scipy.
    """
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not n > 0.0:
        raise ValueError("Found zero norm quaternions in `quat`.")
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return ((x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)),
            (2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)),
            (2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2))


def make_T(p: ArrayLike, q_xyzw: ArrayLike | None = None, R: np.ndarray | None = None) -> np.ndarray:
    """Homogeneous transform from a translation and a quaternion (x y z w) or a 3x3 rotation.

    The quaternion is normalised (as scipy's ``Rotation.from_quat`` does); one pose, closed form on floats.
    """
    if R is None and q_xyzw is not None:
        q = np.asarray(q_xyzw, dtype=float)
        if q.shape != (4,):
            raise ValueError(f"Expected `quat` to have shape (4,), got {q.shape}.")
        pp = np.asarray(p, dtype=float)
        if pp.shape != (3,):   # the generic path below raises numpy's error for a wrong translation
            T = make_T(pp, R=np.asarray(quat_to_R_rows(*q.tolist())))
            return T
        r0, r1, r2 = quat_to_R_rows(*q.tolist())
        px, py, pz = pp.tolist()
        return np.array(((*r0, px), (*r1, py), (*r2, pz), (0.0, 0.0, 0.0, 1.0)))
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = np.asarray(p, dtype=float)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (R^T, -R^T p) without a general matrix inverse."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def R_to_quat(m: Sequence[Sequence[float]]) -> tuple[float, float, float, float] | None:
    """Quaternion (x y z w, sign as scipy returns it) of a 3x3 rotation given as nested float rows; closed form.

    scipy's ``Rotation.from_matrix`` for an orthogonal matrix: Shepperd's method, the largest of (m00, m11, m22,
    trace) picks the branch (first one on ties, like ``numpy.argmax``), then normalisation. None when scipy
    would do something else -- the Gram matrix off identity by more than scipy's ``isclose(atol=1e-12)`` (scipy
    then projects with an SVD) or a non-positive determinant (scipy raises): the caller asks scipy.
    """
    (a, b, c), (d, e, f), (g, h, i) = m
    # scipy: isclose(M M^T, I, atol=1e-12) with numpy's default rtol 1e-5 (relative to I's entry)
    tol_d = 1e-12 + 1e-5
    if not (abs(a * a + b * b + c * c - 1.0) <= tol_d and abs(d * d + e * e + f * f - 1.0) <= tol_d
            and abs(g * g + h * h + i * i - 1.0) <= tol_d and abs(a * d + b * e + c * f) <= 1e-12
            and abs(a * g + b * h + c * i) <= 1e-12 and abs(d * g + e * h + f * i) <= 1e-12):
        return None
    if not a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0.0:
        return None
    tr = a + e + i
    k = 0
    best = a
    if e > best:
        k, best = 1, e
    if i > best:
        k, best = 2, i
    if tr > best:
        k = 3
    if k == 0:
        q = (1 - tr + 2 * a, d + b, g + c, h - f)
    elif k == 1:
        q = (b + d, 1 - tr + 2 * e, h + f, c - g)
    elif k == 2:
        q = (c + g, f + h, 1 - tr + 2 * i, d - b)
    else:
        q = (h - f, c - g, d - b, 1 + tr)
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return x / n, y / n, z / n, w / n


def T_to_pq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a transform into position and quaternion (x y z w, w >= 0).

    Closed form (:func:`R_to_quat`, the module docstring says why); scipy where the closed form defers to it.
    """
    rows = T[:3].tolist()
    q4 = R_to_quat((rows[0][:3], rows[1][:3], rows[2][:3]))
    if q4 is None or not all(map(math.isfinite, q4)):
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(T[:3, :3]).as_quat()
    else:
        q = np.array(q4)
    if q[3] < 0:
        q = -q
    return np.array((rows[0][3], rows[1][3], rows[2][3])), q


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
    from scipy.spatial.transform import Rotation

    R = Rotation.from_matrix(np.stack([T[:3, :3] for T in Ts])).mean().as_matrix()
    p = np.mean(np.stack([T[:3, 3] for T in Ts]), axis=0)
    return make_T(p, R=R)
