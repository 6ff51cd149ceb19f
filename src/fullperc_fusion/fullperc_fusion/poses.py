"""Pose validation shared by the frame chain and the calibration: :func:`pose_to_T` and :class:`BadSample`.

Its own module so that :mod:`fullperc_fusion.calibration` (which validates sightings) and
:mod:`fullperc_fusion.frame_chain` (whose static links are estimated with the calibration) can both import it
without an import cycle; ``frame_chain`` re-exports both names.
"""

from __future__ import annotations

import numpy as np

from fullperc_common.transforms import make_T


class BadSample(ValueError):
    """A pose that cannot be used (non-finite, non-unit quaternion, not a rotation)."""


def pose_to_T(pose, unit_tol: float = 1e-2) -> np.ndarray:
    """A validated 4x4 transform from a 4x4 array or a (p, q_xyzw) pair; raises :class:`BadSample`.

    Quaternions within ``unit_tol`` of unit norm are renormalised (drivers round to float32);
    anything further off is rejected rather than silently normalised, since it signals a corrupt
    sample, not rounding.
    """
    if isinstance(pose, tuple | list) and len(pose) == 2:
        p = np.asarray(pose[0], dtype=float)
        q = np.asarray(pose[1], dtype=float)
        if p.shape != (3,) or q.shape != (4,):
            raise BadSample(f"pose has shapes {p.shape}, {q.shape}; expected (3,), (4,)")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise BadSample("non-finite pose (NaN/inf)")
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > unit_tol:
            raise BadSample(f"non-unit quaternion (norm {n:.4g})")
        return make_T(p, q / n)
    T = np.asarray(pose, dtype=float)
    if T.shape != (4, 4):
        raise BadSample(f"transform has shape {T.shape}; expected (4, 4)")
    if not np.all(np.isfinite(T)):
        raise BadSample("non-finite pose (NaN/inf)")
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > unit_tol or np.linalg.det(R) < 0:
        raise BadSample("rotation block is not a rotation")
    if np.any(T[3] != [0.0, 0.0, 0.0, 1.0]):
        raise BadSample("last row of transform is not [0 0 0 1]")
    return T
