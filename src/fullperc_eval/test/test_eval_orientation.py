"""Orientation error, pose-error vectors and NEES (evaluation/orientation.py, consistency.py), the source tap.

Expected values come from constructed rotations and covariances (a known rotation angle, errors drawn from a known
covariance), never from running the code and copying its output.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_eval.evaluation.consistency import bound, nees, summary
from fullperc_eval.evaluation.orientation import orientation_error_deg, pose_error
from fullperc_eval.evaluation.sources import SourceTap
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement


def _random_rots(n: int, seed: int) -> Rotation:
    return Rotation.random(n, random_state=seed)


def test_orientation_error_is_the_angle_of_a_known_relative_rotation():
    rng = np.random.default_rng(1)
    R_true = _random_rots(50, 2)
    axes = rng.normal(size=(50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ang = rng.uniform(1e-6, 179.0, 50)                      # down to a micro-degree
    for side in ("body", "world"):                            # the angle does not depend on the frame
        d = Rotation.from_rotvec(axes * np.radians(ang)[:, None])
        R_est = R_true * d if side == "body" else d * R_true
        q = R_est.as_quat()
        q[::2] *= -1.0                                        # either quaternion sign is the same orientation
        got = orientation_error_deg(R_true.as_matrix(), q)
        np.testing.assert_allclose(got, ang, rtol=1e-9, atol=1e-9)


def test_orientation_error_is_nan_without_an_orientation():
    R = np.tile(np.eye(3), (4, 1, 1))
    q = np.array([[0, 0, 0, 1], [np.nan, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 1.0]])
    R[3, 0, 0] = np.nan
    got = orientation_error_deg(R, q)
    assert got[0] == 0.0 and np.isnan(got[1:]).all()
    with pytest.raises(ValueError):
        orientation_error_deg(R[:2], q)


def test_pose_error_follows_the_filter_api_convention():
    """R_true = exp([dtheta]x) R_est, dtheta about the axes of base: the rotation vector applied on the left."""
    R_est = _random_rots(20, 3)
    dth = np.random.default_rng(4).normal(scale=0.05, size=(20, 3))
    R_true = Rotation.from_rotvec(dth) * R_est
    p_est = np.random.default_rng(5).normal(size=(20, 3))
    dp = np.random.default_rng(6).normal(scale=1e-3, size=(20, 3))
    e = pose_error(p_est + dp, R_true.as_matrix(), p_est, R_est.as_quat())
    np.testing.assert_allclose(e[:, :3], dp, atol=1e-12)
    np.testing.assert_allclose(e[:, 3:], dth, atol=1e-12)


def test_nees_of_known_errors_and_bad_covariances():
    sig = 3e-4
    e = np.array([[3e-3, 1e-3, -2e-3], [sig, 0, 0], [1, 1, 1], [1, 0, 0]])
    C = np.tile(np.eye(3) * sig**2, (4, 1, 1))
    C[2] = np.diag([1.0, -1.0, 1.0])                          # not positive definite
    C[3, 0, 0] = np.nan
    got = nees(e, C)
    assert got[0] == pytest.approx(14e-6 / sig**2, rel=1e-12)
    assert got[1] == pytest.approx(1.0, rel=1e-12)
    assert np.isnan(got[2]) and np.isnan(got[3])              # one bad covariance spoils only its own sample


@pytest.mark.parametrize("dof", [3, 6])
def test_share_inside_the_bound_is_95_percent_for_errors_drawn_from_their_covariance(dof):
    """Consistent by construction: e ~ N(0, C_k) with a different random C_k per sample. An over-confident
    covariance (C/4 reported) must fall far below 95 % and give a mean NEES of about 4 dof."""
    rng = np.random.default_rng(dof)
    n = 20000
    A = rng.normal(size=(n, dof, dof)) * 1e-3
    C = A @ np.swapaxes(A, 1, 2) + np.eye(dof) * 1e-8
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, dof)))
    s = summary(nees(e, C), dof)
    assert s["n"] == n
    assert s["share_95"] == pytest.approx(0.95, abs=0.006)    # binomial sd at n=20000: 0.0015
    assert s["mean"] == pytest.approx(dof, rel=0.03)
    over = summary(nees(e, C / 4), dof)
    assert over["share_95"] < 0.6 and over["mean"] == pytest.approx(4 * dof, rel=0.03)
    assert s["bound"] == bound(dof)


def test_bound_is_scipy_stats_chi2_ppf_bit_for_bit():
    """consistency takes the quantile from scipy.special (scipy.stats costs every evaluate process ~0.6 s of
    start-up): chi2.ppf's own formula, so the bound -- and every share_95 in eval.json -- did not move."""
    from scipy.stats import chi2

    for dof in range(1, 13):
        for confidence in (0.5, 0.9, 0.95, 0.99, 0.999):
            assert bound(dof, confidence) == float(chi2.ppf(confidence, dof)), (dof, confidence)


def test_summary_of_nothing():
    s = summary(np.array([np.nan]), 6)
    assert s["n"] == 0 and s["share_95"] is None and s["mean"] is None


def test_source_tap_records_what_the_filters_get_and_forgets_on_restore():
    tap = SourceTap()
    q = np.array([0, 0, 0, 1.0])
    tap.predict(10)
    assert tap.update(Measurement(10, SOURCE_GLOBAL, [1, 2, 3], q), Measurement(9, SOURCE_LOCAL, [4, 5, 6])) is None
    snap = tap.snapshot()
    tap.update(Measurement(20, SOURCE_LOCAL, [7, 8, 9], q))
    a = tap.arrays()
    assert a["local"]["t_ns"].tolist() == [9, 20] and a["global"]["t_ns"].tolist() == [10]
    assert np.isnan(a["local"]["q"][0]).all() and a["local"]["q"][1].tolist() == q.tolist()
    tap.restore(snap)                                         # a rewind: what came after the snapshot is gone
    assert tap.arrays()["local"]["t_ns"].tolist() == [9]
    np.testing.assert_array_equal(tap.arrays()["local"]["p"], [[4, 5, 6]])
