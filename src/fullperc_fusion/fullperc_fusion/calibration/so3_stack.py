"""scipy's ``Rotation`` conversions of stacks of rotation matrices, bit for bit, without its per-call cost.

Why: the robust SE(3) mean (:func:`.se3_stats.robust_se3_mean`) runs for every static-link calibration and, in
the link monitor, every half second of OTS base sightings -- each call a few dozen to a few hundred matrices,
converted to quaternions (medoid, means) and rotation vectors (residuals) three or four times. For ~60 matrices
``Rotation.from_matrix`` costs ~100 us, most of it not the conversion: the array-API wrapper, a copy, an LAPACK
determinant per matrix and ``np.isclose`` on the Gram matrices; the robust means were ~19 % of an offline
evaluation. Here the same numbers come from the same compiled code, with the checks done once and cheaply:

* :func:`quats` = ``Rotation.from_matrix(R).as_quat()``: scipy tests det(R) > 0 (else it raises) and
  |R R^T - I| <= 1e-12 + 1e-5 |I| entrywise (``isclose``; else it projects R onto SO(3) by an SVD first), then
  converts with Shepperd's method (``_from_matrix_orthogonal``). Here that conversion runs first and the tests
  afterwards, on its result: if every R is within ``_NEAR`` = 1e-13 (entrywise) of the rotation matrix of its
  quaternion (``as_matrix``, orthogonal to a few 1e-16), R = Q + E with |E_ij| <= 1e-13, so
  |R R^T - I| <= 2 sqrt(3) 1e-13 + 1e-15 < 1e-12 and det R = 1 + O(1e-13) > 0: scipy's own tests pass and its answer
  is that conversion. Anything else (a matrix further off, a reflection, NaN) goes through
  ``Rotation.from_matrix`` itself. (Checked this way, the tests cost ~8 us for 60 matrices; the Gram products and
  LAPACK determinants ~50 us.)
* :func:`rotvecs` = ``Rotation.from_matrix(R).as_rotvec()``: :func:`quats`, then scipy's ``as_rotvec``.
* :func:`mean_rotation` = ``Rotation.from_matrix(R[rows]).mean().as_matrix()`` from :func:`quats` of the whole
  stack: scipy converts each matrix on its own (per-matrix loop, determinant, Gram product and SVD per matrix),
  so the quaternions of a subset are the rows of the quaternions of the stack -- converted once, averaged often.

The compiled functions are scipy's private Cython backend (what ``Rotation`` dispatches numpy input to); where
a scipy release lacks them, every function here falls back to the public ``Rotation`` calls (slower, the same
numbers). test_exact_fast_paths.py pins each function to the public calls, bit for bit.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

try:   # scipy's numpy backend of Rotation (scipy >= 1.16)
    from scipy.spatial.transform import _rotation_cy as _cy

    _FROM_ORTHOGONAL = _cy._from_matrix_orthogonal
    _AS_ROTVEC = _cy.as_rotvec
    _MEAN = _cy.mean
    _AS_MATRIX = _cy.as_matrix
    HAVE_BACKEND = True
except (ImportError, AttributeError):   # pragma: no cover - another scipy: the public calls below
    HAVE_BACKEND = False

__all__ = ["HAVE_BACKEND", "mean_rotation", "near_quats", "quats", "rotvecs"]

_NEAR = 1e-13   # a matrix this close (entrywise) to its quaternion's rotation passes scipy's tests (module docstring)


def near_quats(R: np.ndarray) -> np.ndarray | None:
    """:func:`quats` of ``R`` when every matrix is within ``_NEAR`` of its quaternion's rotation (the fast path),
    else None. Such a stack is a stack of rotations to ~1e-12 (module docstring): it also passes the pose checks'
    rotation test (:func:`.se3_stats.as_pose_stack`: max|R^T R - I| <= 1e-2, det R >= 0), which the robust mean
    then need not run."""
    m = np.array(R, dtype=float)   # scipy's own copy (C order)
    if HAVE_BACKEND and m.ndim == 3 and m.shape[1:] == (3, 3) and len(m):
        q = np.asarray(_FROM_ORTHOGONAL(m))
        if np.abs(m - np.asarray(_AS_MATRIX(q))).max() <= _NEAR:   # False for NaN
            return q
    return None


def quats(R: np.ndarray) -> np.ndarray:
    """``Rotation.from_matrix(R).as_quat()`` of a stack ``R`` (N, 3, 3), (N, 4) x y z w, bit for bit."""
    q = near_quats(R)
    return Rotation.from_matrix(R).as_quat() if q is None else q


def rotvecs(R: np.ndarray) -> np.ndarray:
    """``Rotation.from_matrix(R).as_rotvec()`` of a stack ``R`` (N, 3, 3): (N, 3), bit for bit."""
    if not HAVE_BACKEND:   # pragma: no cover
        return Rotation.from_matrix(R).as_rotvec()
    return np.asarray(_AS_ROTVEC(quats(R), False))


def mean_rotation(R: np.ndarray, q_all: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``Rotation.from_matrix(R[rows]).mean().as_matrix()`` (3, 3) of the stack ``R`` (N, 3, 3), bit for bit, given
    ``q_all`` = :func:`quats` of ``R`` and a boolean or index selection ``rows`` (module docstring: the quaternions of
    a subset are rows of the stack's)."""
    if not HAVE_BACKEND:   # pragma: no cover
        return Rotation.from_matrix(R[rows]).mean().as_matrix()
    q = np.ascontiguousarray(q_all[rows])   # the (n, 4) array Rotation would hold
    mean = np.asarray(_MEAN(q, None, None))
    return np.asarray(_AS_MATRIX(mean[None, :]))[0]
