"""SO(3) helpers, the project's one copy: the skew matrix, Exp/Log of rotation vectors, quaternion (x y z w) <-> R.

Plain numpy on 3-vectors and 3x3 matrices: the ``fullperc`` filter calls them once or twice per sample, where
scipy's ``Rotation`` objects cost more than the arithmetic (and drivers import fullperc_common without scipy).
``fullperc_fusion/test/test_fullperc_filter.py`` holds them to scipy.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["skew", "so3_exp", "so3_log", "quat_to_R", "R_to_quat"]

_I3 = np.eye(3)


def skew(a: np.ndarray) -> np.ndarray:
    """[a]x, the matrix of the cross product: skew(a) @ b == np.cross(a, b)."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Exp of a rotation vector (Rodrigues); series below 1e-8 rad."""
    th = math.sqrt(float(w @ w))
    K = skew(w)
    if th < 1e-8:
        return _I3 + K + 0.5 * K @ K
    return _I3 + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / (th * th)) * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Log of a rotation matrix as a rotation vector, |w| <= pi (robust near 0 and near pi)."""
    c = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    th = math.acos(c)
    if th < 1e-6:
        return 0.5 * v
    if th > math.pi - 1e-4:   # near pi: axis from the symmetric part
        B = 0.5 * (R + _I3)
        i = int(np.argmax(np.diag(B)))
        ax = B[:, i] / math.sqrt(max(B[i, i], 1e-300))
        if ax @ v < 0:
            ax = -ax
        return th * ax / np.linalg.norm(ax)
    return (th / (2.0 * math.sin(th))) * v


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion x y z w (normalised here)."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion x y z w (w >= 0) of a rotation matrix (Shepperd)."""
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q
