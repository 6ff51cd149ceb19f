"""SO(3) on 9-tuples of Python floats: :mod:`fullperc_common.so3`'s formulas, specialised for ``fullperc``'s fast form.

``fullperc_common.so3`` is the project's SO(3) module; this is the one specialised copy, kept because the shared one
costs measurably where these run. :class:`~.fullperc.FullpercFilter` calls them about 14 times per step (per
predict + update on the benchmark's 6-dof items: 4 Exp, 7 products, 2 Log, 1.5 quaternion -> R, 1 R -> quaternion)
on rotations it keeps as 9-tuples (row-major). Measured (busy 2-core machine, minimum of 15 runs): Exp 0.9 us here
against 13 us in numpy, Log 1.5 against 5.7, quaternion -> R 2.1 against 13.6, R -> quaternion 2.2 against 9.8, a
3x3 product 1.1 against 3.1; a whole fullperc step with the numpy functions in their place took 1.7x as long.

Same formulas and branches as ``fullperc_common.so3`` (Rodrigues with its series below 1e-8 rad; Log robust near 0
and pi -- the branch near pi, rare, calls the shared ``so3_log``; Shepperd's quaternion with w >= 0);
test_fullperc_fast.py holds each to the shared function, test_imm_fast.py :func:`exp9` and :func:`log9` to their
plain forms bit for bit (written with fewer operations, the same roundings).
"""

from __future__ import annotations

import math

import numpy as np

from fullperc_common.so3 import so3_log

__all__ = ["R9_IDENT", "R9_to_quat", "exp9", "log9", "mul9", "mul9_t", "quat_to_R9"]

R9_IDENT = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def exp9(a: float, b: float, c: float) -> tuple:
    """Exp of the rotation vector (a, b, c): I + s K + k K^2 (Rodrigues), the series below 1e-8 rad. Each product
    once (the squares shared with th; s K's entries written as differences, -s c + k a b = k a b - s c exactly)."""
    aa = a * a
    bb = b * b
    cc = c * c
    th = math.sqrt(aa + bb + cc)
    if th < 1e-8:
        s = 1.0
        k = 0.5
    else:
        s = math.sin(th) / th
        k = (1.0 - math.cos(th)) / (th * th)
    kab = k * (a * b)
    kac = k * (a * c)
    kbc = k * (b * c)
    sa = s * a
    sb = s * b
    sc = s * c
    return (1.0 - k * (bb + cc), kab - sc, sb + kac,
            sc + kab, 1.0 - k * (aa + cc), kbc - sa,
            kac - sb, sa + kbc, 1.0 - k * (aa + bb))


def mul9(A: tuple, B: tuple) -> tuple:
    """A B of two row-major 3x3 tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def mul9_t(A: tuple, B: tuple) -> tuple:
    """A B^T of two row-major 3x3 tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return (a0 * b0 + a1 * b1 + a2 * b2, a0 * b3 + a1 * b4 + a2 * b5, a0 * b6 + a1 * b7 + a2 * b8,
            a3 * b0 + a4 * b1 + a5 * b2, a3 * b3 + a4 * b4 + a5 * b5, a3 * b6 + a4 * b7 + a5 * b8,
            a6 * b0 + a7 * b1 + a8 * b2, a6 * b3 + a7 * b4 + a8 * b5, a6 * b6 + a7 * b7 + a8 * b8)


def log9(R: tuple) -> list[float]:
    """Log of a rotation (|w| <= pi); near pi (rare) the shared ``so3_log`` on an array. The cosine clamped to
    [-1, 1] by comparisons (max(-1, min(1, c)) without the calls; NaN goes to 1 as there)."""
    c = 0.5 * (R[0] + R[4] + R[8] - 1.0)
    if not c < 1.0:
        c = 1.0
    elif not c > -1.0:
        c = -1.0
    th = math.acos(c)
    if th < 1e-6:
        return [0.5 * (R[7] - R[5]), 0.5 * (R[2] - R[6]), 0.5 * (R[3] - R[1])]
    if th > math.pi - 1e-4:
        return so3_log(np.array(R).reshape(3, 3)).tolist()
    f = th / (2.0 * math.sin(th))
    return [f * (R[7] - R[5]), f * (R[2] - R[6]), f * (R[3] - R[1])]


def quat_to_R9(q: np.ndarray) -> tuple:
    """Rotation of a quaternion x y z w, normalised first (``so3.quat_to_R``)."""
    x, y, z, w = q.tolist()
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y))


def R9_to_quat(R: tuple) -> np.ndarray:
    """Quaternion x y z w (w >= 0) of a rotation (Shepperd, as ``so3.R_to_quat``)."""
    t = R[0] + R[4] + R[8]
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [(R[7] - R[5]) / s, (R[2] - R[6]) / s, (R[3] - R[1]) / s, 0.25 * s]
    else:
        d = (R[0], R[4], R[8])
        i = 0 if d[0] >= d[1] and d[0] >= d[2] else 1 if d[1] >= d[2] else 2   # np.argmax: first maximum
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + d[i] - d[j] - d[k], 1e-300))
        q = [0.0, 0.0, 0.0, 0.0]
        q[i] = 0.25 * s
        q[j] = (R[3 * j + i] + R[3 * i + j]) / s
        q[k] = (R[3 * k + i] + R[3 * i + k]) / s
        q[3] = (R[3 * k + j] - R[3 * j + k]) / s
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[3] < 0:
        n = -n
    return np.array([q[0] / n, q[1] / n, q[2] / n, q[3] / n])
