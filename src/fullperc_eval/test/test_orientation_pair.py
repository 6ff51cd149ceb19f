"""orientation_and_pose_error (one pair of scipy Rotations for both figures, issue 38 item 5) gives exactly
orientation_error_deg and pose_error: on random poses, with missing orientations (NaN, a short quaternion), a
missing truth row, a missing position, and an empty batch."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_eval.evaluation.orientation import orientation_and_pose_error, orientation_error_deg, pose_error


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_the_pair_is_the_two_functions_bit_for_bit():
    rng = np.random.default_rng(11)
    for n in (0, 1, 7, 500):
        R = Rotation.random(n, rng=rng).as_matrix() if n else np.zeros((0, 3, 3))
        q = (Rotation.from_matrix(R) * Rotation.from_rotvec(rng.normal(0, 0.02, (n, 3)))).as_quat() if n \
            else np.zeros((0, 4))
        p_true, p_est = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
        if n >= 7:
            q[1] = np.nan
            q[2] *= 0.3            # not an orientation (norm < 0.5)
            R[3] = np.nan          # no truth
            p_est[4] = np.nan      # no position
            q[5] = -q[5]           # the other sign of the same rotation
        ang, d = orientation_and_pose_error(p_true, R, p_est, q)
        assert _same(ang, orientation_error_deg(R, q))
        assert _same(d, pose_error(p_true, R, p_est, q))
