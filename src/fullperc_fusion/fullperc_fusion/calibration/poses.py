"""Pose validation shared by the frame chain and the calibration: :func:`pose_to_T` and :class:`BadSample`.

Its own module so that :mod:`fullperc_fusion.calibration.collector` (which validates sightings) and
:mod:`fullperc_fusion.pipeline.frame_chain` (whose static links are estimated with the calibration) can both import it
without an import cycle; ``frame_chain`` re-exports both names.
"""

from __future__ import annotations

import math

import numpy as np

from fullperc_common.transforms import quat_to_R_rows


class BadSample(ValueError):
    """A pose that cannot be used (non-finite, non-unit quaternion, not a rotation)."""


def pose_to_T(pose, unit_tol: float = 1e-2) -> np.ndarray:
    """A validated 4x4 transform from a 4x4 array or a (p, q_xyzw) pair; raises :class:`BadSample`.

    Quaternions within ``unit_tol`` of unit norm are renormalised (drivers round to float32);
    anything further off is rejected rather than silently normalised, since it signals a corrupt
    sample, not rounding.

    The (p, q) form -- every sample the fusion node receives -- is checked and converted on Python floats
    (the same tests, :func:`~fullperc_common.transforms.quat_to_R_rows` for the matrix, bit-identical to the
    former ``make_T`` through scipy): numpy's per-call overhead on 3- and 4-vectors, and scipy's Rotation, were
    ~16 % of the node's CPU per fused pose (issue 16). Only the norm stays numpy's (the comment below says why).
    """
    if isinstance(pose, tuple | list) and len(pose) == 2:
        p = np.asarray(pose[0], dtype=float)
        q = np.asarray(pose[1], dtype=float)
        if p.shape != (3,) or q.shape != (4,):
            raise BadSample(f"pose has shapes {p.shape}, {q.shape}; expected (3,), (4,)")
        px, py, pz = p.tolist()
        x, y, z, w = q.tolist()
        isf = math.isfinite
        if not (isf(px) and isf(py) and isf(pz) and isf(x) and isf(y) and isf(z) and isf(w)):
            raise BadSample("non-finite pose (NaN/inf)")
        # numpy's norm, not math.sqrt of the sum: BLAS rounds differently in the last bit, and the evaluation
        # (bags/*/eval.json, rel 1e-9) amplifies that through ill-conditioned NEES values past its tolerance
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > unit_tol:
            raise BadSample(f"non-unit quaternion (norm {n:.4g})")
        r0, r1, r2 = quat_to_R_rows(x / n, y / n, z / n, w / n)
        return np.array(((*r0, px), (*r1, py), (*r2, pz), (0.0, 0.0, 0.0, 1.0)))
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
