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
        # (bags/*/eval.json, rel 1e-9) amplifies that through ill-conditioned NEES values past its tolerance. Its
        # own steps for a 1-D float vector (linalg.norm: ravel, the BLAS dot, sqrt), without its dispatch (~1.3 us)
        qr = q.ravel(order="K")
        n = math.sqrt(qr.dot(qr))
        if abs(n - 1.0) > unit_tol:
            raise BadSample(f"non-unit quaternion (norm {n:.4g})")
        r0, r1, r2 = quat_to_R_rows(x / n, y / n, z / n, w / n)
        return np.array(((*r0, px), (*r1, py), (*r2, pz), (0.0, 0.0, 0.0, 1.0)))
    T = np.asarray(pose, dtype=float)
    if T.shape != (4, 4):
        raise BadSample(f"transform has shape {T.shape}; expected (4, 4)")
    rows = T.tolist()
    if not all(map(math.isfinite, rows[0] + rows[1] + rows[2] + rows[3])):
        raise BadSample("non-finite pose (NaN/inf)")
    if not _is_rotation(T, rows, unit_tol):
        raise BadSample("rotation block is not a rotation")
    if rows[3] != [0.0, 0.0, 0.0, 1.0]:
        raise BadSample("last row of transform is not [0 0 0 1]")
    return T


_DECIDE_MARGIN = 1e-9   # the float and the numpy Gram error differ by ~1e-16: nearer the tolerance, numpy decides


def _is_rotation(T: np.ndarray, rows: list[list[float]], unit_tol: float) -> bool:
    """The 4x4 form's rotation test, ``max|R^T R - I| <= unit_tol and det(R) >= 0``, with numpy's answer.

    Why on floats: the 4x4 form is every sighting a static-link calibration collects (the batched evaluator's and
    the node's), and the numpy expression (a matmul, ``eye``, ``max``, an LAPACK determinant) cost ~20 us per
    sample. The Gram entries on floats round differently from numpy's matmul only in the last bits, so outside
    ``_DECIDE_MARGIN`` of the tolerance both give the same answer; within it numpy's own expression decides. The
    determinant only matters once the Gram test passed, where the eigenvalues of R^T R are within 3 unit_tol of 1
    (Gershgorin) and so |det R| >= (1 - 3 unit_tol)^(3/2) is far from 0 (0.955 at the default 1e-2): its sign is the
    same however it is rounded. A tolerance of 1/4 or more (no caller has one) goes to numpy's expression.
    """
    (a, b, c, _), (d, e, f, _), (g, h, i, _) = rows[0], rows[1], rows[2]
    err = max(abs(a * a + d * d + g * g - 1.0), abs(b * b + e * e + h * h - 1.0), abs(c * c + f * f + i * i - 1.0),
              abs(a * b + d * e + g * h), abs(a * c + d * f + g * i), abs(b * c + e * f + h * i))
    if abs(err - unit_tol) <= _DECIDE_MARGIN or not unit_tol < 0.25:   # borderline, or a tolerance this test
        R = T[:3, :3]                                                # does not vouch for: numpy's expression
        return not (np.max(np.abs(R.T @ R - np.eye(3))) > unit_tol or np.linalg.det(R) < 0)
    if err > unit_tol:
        return False
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) >= 0.0
