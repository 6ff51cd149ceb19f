"""Calibration of the static links: robust SE(3) mean, covariance, static check, links, bump, collector.

Every sample stream is synthetic with a fixed seed; stamps are made up (no wall clock). Noise levels are
the ones the module is meant to tell apart: a Vega sees a marker at ~2 m with ~0.2 mm and a few mrad per
frame, an OMC with ~0.1-1 mm and ~2 mrad.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from fullperc_common.transforms import T_to_pq, inv_T, make_T, mean_T
from fullperc_fusion.calibration.collector import Collector
from fullperc_fusion.calibration.links import link_bump, link_T_base_ots, link_T_omc_base, link_T_rig_ots, pair_by_stamp
from fullperc_fusion.calibration.se3_stats import (
    COV_FLOOR,
    LINK_NAMES,
    BumpThresholds,
    CalibrationBodies,
    CalibrationError,
    CalibrationSettings,
    LinkEstimate,
    StaticThresholds,
    compose_jacobian,
    mean_estimate,
    robust_se3_mean,
    se3_residuals,
    se3_retract,
)
from fullperc_fusion.calibration.static_check import check_static, hotelling_threshold

S = 1_000_000_000  # ns per s
MS = 1_000_000
T_TRUE = make_T([0.31, -0.42, 1.27], Rotation.from_euler("xyz", [12.0, -35.0, 70.0], degrees=True).as_quat())
SIG_OMC = np.array([1e-3, 1e-3, 1e-3, 2e-3, 2e-3, 2e-3])       # m, rad per sample
SIG_VEGA = np.array([0.1e-3, 0.1e-3, 0.3e-3, 3e-3, 3e-3, 3e-3])


def noisy(T0, n, sig, rng, L=None):
    """n samples about T0 with tangent noise diag(sig) (or L @ N(0, I)), parent-frame convention: ``se3_retract(T0,
    d)`` of each row, as one batch (one ``Rotation.from_rotvec`` for the stack, not one per sample: the Monte Carlo
    tests draw tens of thousands)."""
    d = rng.normal(size=(n, 6)) * sig if L is None else rng.normal(size=(n, 6)) @ L.T
    Ts = np.zeros((n, 4, 4))
    Ts[:, :3, :3] = Rotation.from_rotvec(d[:, 3:]).as_matrix() @ T0[:3, :3]
    Ts[:, :3, 3] = T0[:3, 3] + d[:, :3]
    Ts[:, 3, 3] = 1.0
    return Ts


def nees(T_est, cov, T_true):
    d = se3_residuals(T_est, T_true[None])[0]
    return float(d @ np.linalg.solve(cov, d))


# ------------------------------------------------------------------------------------------ conventions

def test_tangent_convention_is_parent_frame():
    # R_mean = Rz(90 deg): the body x axis is the parent y axis.
    T0 = make_T([1.0, 2.0, 3.0], Rotation.from_euler("z", 90, degrees=True).as_quat())
    d = np.array([1e-3, 2e-3, 3e-3, 1e-3, 0.0, 0.0])
    assert np.allclose(se3_residuals(T0, se3_retract(T0, d)[None])[0], d, atol=1e-12)
    # rotating about the BODY x axis (right-multiplied) shows up as rotation about PARENT y
    T_body = T0 @ make_T([0, 0, 0], Rotation.from_rotvec([1e-3, 0, 0]).as_quat())
    assert np.allclose(se3_residuals(T0, T_body[None])[0], [0, 0, 0, 0, 1e-3, 0], atol=1e-12)
    # the position residual is the plain difference in the parent frame
    T_move = T0.copy()
    T_move[:3, 3] += [0.0, 0.0, 5e-3]
    assert np.allclose(se3_residuals(T0, T_move[None])[0], [0, 0, 5e-3, 0, 0, 0], atol=1e-15)


def test_covariance_axes_follow_the_convention():
    # noise only about the parent x axis lands in cov[3, 3], whatever the mean's orientation
    rng = np.random.default_rng(1)
    T0 = make_T([0, 0, 1], Rotation.from_euler("z", 90, degrees=True).as_quat())
    est = robust_se3_mean(noisy(T0, 400, np.array([0, 0, 0, 2e-3, 0, 0]), rng))
    var = np.diag(est.cov)
    assert var[3] > 100 * max(var[4], var[5])
    assert np.all(var[:3] < 1e-10)


def test_quaternion_order_xyzw():
    th = 0.3
    q = np.array([0.0, 0.0, np.sin(th / 2), np.cos(th / 2)])  # x y z w: rotation of 0.3 rad about z
    P = np.tile([0.1, 0.2, 0.3], (5, 1))
    est = robust_se3_mean((P, np.tile(q, (5, 1))))
    assert np.allclose(est.T[:3, :3], Rotation.from_euler("z", th).as_matrix(), atol=1e-12)
    assert np.allclose(est.quat_xyzw, q, atol=1e-12)  # scalar last, w >= 0
    c = Collector(links=("T_omc_base",))
    for t in stamps(40):
        assert c.add("omc", "base", int(t), [0.1, 0.2, 0.3], q)
    assert np.allclose(c.finish().T("T_omc_base")[:3, :3], Rotation.from_euler("z", th).as_matrix(), atol=1e-12)


def test_a_list_of_two_transforms_is_not_positions_and_quaternions():
    Ts = [T_TRUE, se3_retract(T_TRUE, [1e-3, 0, 0, 0, 0, 0])]
    est = robust_se3_mean(Ts)
    assert est.n_samples == 2 and est.position == pytest.approx(T_TRUE[:3, 3] + [0.5e-3, 0, 0])


def test_input_checked():
    Ts = noisy(T_TRUE, 10, SIG_OMC, np.random.default_rng(0))
    with pytest.raises(CalibrationError, match="1 sample"):
        robust_se3_mean(Ts[:1])
    bad = Ts.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(CalibrationError, match="non-finite"):
        robust_se3_mean(bad, what="OMC body 'base'")
    with pytest.raises(CalibrationError, match="norm"):
        robust_se3_mean((np.zeros((3, 3)), np.tile([0, 0, 0, 0.9], (3, 1))))
    bad = Ts.copy()
    bad[2, :3, :3] *= 1.1
    with pytest.raises(CalibrationError, match="not a rotation"):
        robust_se3_mean(bad)


# ------------------------------------------------------------------------------------------ robust mean

@pytest.mark.parametrize("seed", range(5))
def test_mean_recovers_known_pose(seed):
    rng = np.random.default_rng(seed)
    n = 300
    est = robust_se3_mean(noisy(T_TRUE, n, SIG_OMC, rng))
    # the error of the mean is consistent with its covariance (6 dof, 99.9 %)
    assert nees(est.T, est.cov, T_TRUE) <= chi2.ppf(0.999, 6)
    assert est.n_samples == n and est.n_inliers >= n - 3  # the gate drops ~0.2 % of clean Gaussian samples
    # per-sample residuals: E|d|^2 = 3 sigma^2 per block
    assert est.rms_trans_mm == pytest.approx(np.sqrt(3) * 1.0, rel=0.1)
    assert est.rms_rot_mrad == pytest.approx(np.sqrt(3) * 2.0, rel=0.1)
    assert est.max_trans_mm >= est.rms_trans_mm and est.max_rot_mrad >= est.rms_rot_mrad


def test_covariance_is_sample_covariance_over_n_plus_floor():
    rng = np.random.default_rng(2)
    Ts = noisy(T_TRUE, 200, SIG_OMC, rng)
    est = robust_se3_mean(Ts)
    r = se3_residuals(est.T, Ts[est.inliers])
    expect = np.cov(r, rowvar=False, ddof=1) / est.n_inliers + np.diag(np.repeat(np.square(COV_FLOOR), 3))
    assert np.allclose(est.cov, expect, rtol=1e-9, atol=0)
    assert np.allclose(est.T, mean_T(list(Ts[est.inliers])), atol=0)  # the mean is mean_T of the inliers


def test_covariance_matches_monte_carlo():
    # correlated, anisotropic noise like T_base_ots (rotation x lever leaks into translation)
    A = np.diag([0.3e-3, 0.2e-3, 0.5e-3, 3e-3, 2e-3, 1e-3])
    A[0, 4] = 2.0 * 2e-3   # 2 m lever: rotation about y moves x
    A[1, 3] = -2.0 * 3e-3
    rng = np.random.default_rng(3)
    n, draws = 40, 600     # a ratio of variances from 600 draws scatters by ~6 %: 20 % is > 3 sigma
    errs, covs = [], []
    for _ in range(draws):
        est = robust_se3_mean(noisy(T_TRUE, n, None, rng, L=A))
        errs.append(se3_residuals(T_TRUE, est.T[None])[0])
        covs.append(est.cov)
    emp = np.cov(np.array(errs), rowvar=False)
    pred = np.mean(covs, axis=0)
    truth = A @ A.T / n
    assert np.allclose(np.diag(emp) / np.diag(pred), 1.0, atol=0.2)
    assert np.allclose(np.diag(pred) / np.diag(truth), 1.0, atol=0.05)
    # the correlation the lever creates is carried, not only the diagonal
    corr = pred[0, 4] / np.sqrt(pred[0, 0] * pred[4, 4])
    assert corr == pytest.approx(emp[0, 4] / np.sqrt(emp[0, 0] * emp[4, 4]), abs=0.1)
    assert corr > 0.8
    # NEES with a covariance estimated from n samples is Hotelling's T^2: mean p nu / (nu - p - 1), nu = n - 1
    mean_nees = np.mean([e @ np.linalg.solve(c, e) for e, c in zip(errs, covs, strict=True)])
    assert mean_nees == pytest.approx(6 * (n - 1) / (n - 1 - 6 - 1), rel=0.1)


def test_gross_outliers_rejected_and_mean_unaffected():
    rng = np.random.default_rng(4)
    n = 400
    Ts = noisy(T_TRUE, n, SIG_OMC, rng)
    out_idx = rng.choice(n, size=n // 20, replace=False)  # 5 %
    clean = robust_se3_mean(np.delete(Ts, out_idx, axis=0))  # what the other 95 % say on their own
    bad = Ts.copy()
    for i in out_idx:  # 5-50 mm and 20-200 mrad off, random directions
        d = rng.normal(size=6)
        d[:3] *= rng.uniform(5e-3, 50e-3) / np.linalg.norm(d[:3])
        d[3:] *= rng.uniform(20e-3, 200e-3) / np.linalg.norm(d[3:])
        bad[i] = se3_retract(Ts[i], d)
    est = robust_se3_mean(bad)
    assert not est.inliers[out_idx].any()
    assert est.n_inliers >= n - len(out_idx) - 3
    # the mean is where the clean data put it, to a small fraction of its own uncertainty
    assert nees(est.T, clean.cov, clean.T) < 1e-6
    assert nees(est.T, est.cov, T_TRUE) <= chi2.ppf(0.999, 6)
    # without rejection the same outliers pull the mean far off: the test is not vacuous
    assert nees(mean_T(list(bad)), clean.cov, clean.T) > 50


def test_gate_floor_keeps_quantised_samples():
    # identical samples (noise-free or quantised stream) + one 20 um off: below the floor, kept
    Ts = np.repeat(T_TRUE[None], 50, axis=0)
    Ts[7, 0, 3] += 20e-6
    est = robust_se3_mean(Ts)
    assert est.n_inliers == 50
    Ts[9, 1, 3] += 5e-3  # but a 5 mm jump is an outlier
    est = robust_se3_mean(Ts)
    assert est.n_inliers == 49 and not est.inliers[9]
    np.linalg.cholesky(est.cov)  # always positive definite thanks to COV_FLOOR


# ------------------------------------------------------------------------------------------ static check

def stamps(n, dur_s=10.0, t0=5 * S):
    return t0 + np.round(np.linspace(0, dur_s, n) * S).astype(np.int64)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("sig,n", [(SIG_VEGA, 600), (SIG_OMC, 1000), (SIG_OMC, 30), (SIG_VEGA, 30)])
def test_static_noise_is_not_motion(seed, sig, n):
    rng = np.random.default_rng(100 + seed)
    check_static("OMC body 'base'", stamps(n), noisy(T_TRUE, n, sig, rng))


def test_an_omc_hop_is_not_motion():
    # the set of seeing cameras changes half way: a 0.5 mm / 1 mrad step, significant but below the limits
    rng = np.random.default_rng(5)
    Ts = noisy(T_TRUE, 1000, SIG_OMC * 0.3, rng)
    Ts[500:] = np.stack([se3_retract(T, [0.5e-3, 0, 0, 1e-3, 0, 0]) for T in Ts[500:]])
    check_static("OMC body 'base'", stamps(1000), Ts)


def moved_mm(msg):
    return float(re.search(r"moved during the collection: ([0-9.]+) mm", msg).group(1))


@pytest.mark.parametrize("kind", ["step", "drift"])
def test_body_moving_5mm_is_refused(kind):
    rng = np.random.default_rng(6)
    n = 600
    Ts = noisy(T_TRUE, n, SIG_OMC, rng)
    frac = (np.arange(n) >= n // 2).astype(float) if kind == "step" else np.linspace(0, 1, n)
    Ts[:, 1, 3] += 5e-3 * frac
    with pytest.raises(CalibrationError) as e:
        check_static("OMC body 'base'", stamps(n), Ts)
    msg = str(e.value)
    assert "OMC body 'base' moved" in msg and "allowed 1.00 mm" in msg
    if kind == "step":
        assert moved_mm(msg) == pytest.approx(5.0, abs=0.5)
        assert "0.0-2.5 s" in msg and "5.0-7.5 s" in msg and "10.0 s collection" in msg
    else:  # window means 0-2.5 s and 7.5-10 s are 3/4 of the drift apart
        assert moved_mm(msg) == pytest.approx(3.75, abs=0.5)
        assert "0.0-2.5 s" in msg and "7.5-10.0 s" in msg


def test_body_turning_is_refused_with_vega_noise():
    rng = np.random.default_rng(7)
    Ts = noisy(T_TRUE, 600, SIG_VEGA, rng)
    Ts[300:] = np.stack([se3_retract(T, [0, 0, 0, 0, 0, 10e-3]) for T in Ts[300:]])
    with pytest.raises(CalibrationError, match=r"OTS tool 'base' moved .* 10\.\d\d mrad"):
        check_static("OTS tool 'base'", stamps(600), Ts)


def test_hotelling_threshold():
    # tends to chi^2_3 with many degrees of freedom; far above it with few (the covariance is estimated)
    assert hotelling_threshold(1e-4, 100_000) == pytest.approx(chi2.ppf(1 - 1e-4, 3), rel=1e-3)
    assert hotelling_threshold(1e-4, 26) > 1.5 * chi2.ppf(1 - 1e-4, 3)
    assert hotelling_threshold(1e-4, 2) == np.inf


@pytest.mark.parametrize("alpha", [1e-4, 1e-3, 0.01, 0.05])
def test_quantiles_from_scipy_special_are_scipy_stats_ones(alpha):
    """calibration takes its chi^2 and F quantiles from scipy.special (start-up cost, its imports say why): they are
    scipy.stats' ppf to rounding, so the gates and thresholds did not move."""
    from scipy.special import chdtri
    from scipy.stats import f

    for k in (1, 3, 6):
        assert chdtri(k, alpha) == pytest.approx(chi2.ppf(1 - alpha, k), rel=1e-12)
    for dof in (3, 10, 26, 1000):
        assert hotelling_threshold(alpha, dof) == pytest.approx(3 * dof / (dof - 2) * f.ppf(1 - alpha, 3, dof - 2),
                                                                rel=1e-12)



def test_large_noise_short_collection_is_not_refused_for_noise():
    # 2 mm of noise and 30 samples: window means differ by > 1 mm, but not beyond their own noise
    rng = np.random.default_rng(8)
    for _ in range(5):
        check_static("OMC body 'base'", stamps(30), noisy(T_TRUE, 30, SIG_OMC * 2, rng))


def test_sightings_in_one_window_only_are_refused():
    rng = np.random.default_rng(9)
    t = np.r_[stamps(40, dur_s=2.0), 5 * S + 10 * S]  # 40 in the first 2 s, one at the end
    with pytest.raises(CalibrationError, match="OTS tool 'base': sightings fill only 1 of 4"):
        check_static("OTS tool 'base'", t, noisy(T_TRUE, 41, SIG_VEGA, rng))


def test_static_thresholds_are_parameters():
    rng = np.random.default_rng(10)
    Ts = noisy(T_TRUE, 600, SIG_OMC * 0.1, rng)
    Ts[300:, 0, 3] += 0.6e-3
    check_static("b", stamps(600), Ts)
    with pytest.raises(CalibrationError, match="moved"):
        check_static("b", stamps(600), Ts, StaticThresholds(max_drift_m=0.5e-3))


# ------------------------------------------------------------------------------------------ links

def test_T_omc_base_is_the_robust_mean():
    Ts = noisy(T_TRUE, 100, SIG_OMC, np.random.default_rng(11))
    a = link_T_omc_base(Ts)
    b = robust_se3_mean(Ts)
    assert np.array_equal(a.T, b.T) and np.array_equal(a.cov, b.cov)
    assert a.source == "OMC body 'base'"


def test_T_base_ots_is_mean_of_inverses_as_frame_chain():
    rng = np.random.default_rng(12)
    T_ots_base = make_T([0.3, -0.2, 2.2], Rotation.from_euler("xyz", [170, 5, -20], degrees=True).as_quat())
    Ts = noisy(T_ots_base, 600, SIG_VEGA, rng)
    est = link_T_base_ots(Ts)
    assert np.allclose(est.T, robust_se3_mean(np.stack([inv_T(T) for T in Ts])).T, atol=0)
    # it is T_base_ots: composed with the true T_ots_base it gives the identity
    assert nees(est.T, est.cov, inv_T(T_ots_base)) <= chi2.ppf(0.999, 6)
    # 3 mrad of rotation noise over 2.2 m: the translation of the inverse scatters by mm, and is correlated
    assert est.rms_trans_mm > 5
    assert "eq. 2" in est.source


def test_too_many_inconsistent_samples_refused():
    rng = np.random.default_rng(13)
    Ts = noisy(T_TRUE, 100, SIG_OMC, rng)
    Ts[:55] = noisy(se3_retract(T_TRUE, [0.02, 0, 0, 0, 0, 0]), 55, SIG_OMC, rng)
    with pytest.raises(CalibrationError, match=r"OMC body 'base': only 55 of 100 samples .* \(need 60%\)"):
        link_T_omc_base(Ts, CalibrationSettings(min_inlier_fraction=0.6))


def test_compose_jacobian_matches_finite_differences():
    rng = np.random.default_rng(14)
    A = se3_retract(np.eye(4), rng.normal(size=6))
    X = se3_retract(np.eye(4), rng.normal(size=6))
    B = se3_retract(np.eye(4), rng.normal(size=6))
    J = compose_jacobian(A, X, B)
    T0 = A @ X @ B
    h = 1e-6
    Jn = np.zeros((6, 6))
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        Jn[:, k] = (se3_residuals(T0, (A @ se3_retract(X, e) @ B)[None])[0]
                    - se3_residuals(T0, (A @ se3_retract(X, -e) @ B)[None])[0]) / (2 * h)
    assert np.allclose(J, Jn, atol=1e-7)


T_OMC_BASE = make_T([-0.6, 0.35, 1.10], Rotation.from_euler("z", 30, degrees=True).as_quat())
T_RIG_OTS = make_T([0.05, 0.02, -0.1], Rotation.from_euler("xyz", [0, 90, 10], degrees=True).as_quat())
T_OMC_RIG = make_T([1.2, -1.0, 1.6], Rotation.from_euler("xyz", [0, 0, 140], degrees=True).as_quat())
T_OTS_BASE = inv_T(T_RIG_OTS) @ inv_T(T_OMC_RIG) @ T_OMC_BASE  # consistent setup


def rig_setup(rng, n=200, sig_omc=SIG_OMC, sig_ots=SIG_VEGA):
    t_omc = stamps(n)
    t_ots = stamps(n) + 3 * MS
    return (t_omc, noisy(T_OMC_BASE, n, sig_omc, rng), noisy(T_OMC_RIG, n, sig_omc, rng),
            t_ots, noisy(T_OTS_BASE, n, sig_ots, rng))


def test_T_rig_ots_recovers_the_hand_eye_link():
    rng = np.random.default_rng(15)
    t_omc, base, rig, t_ots, ots = rig_setup(rng)
    Lb = link_T_omc_base(base)
    est = link_T_rig_ots(t_omc, rig, t_ots, ots, Lb)
    assert est.n_samples == 200 and "eq. 1" in est.source
    assert nees(est.T, est.cov, T_RIG_OTS) <= chi2.ppf(0.999, 6)
    # its covariance carries the shared T_omc_base term on top of the pairs' own spread
    own = robust_se3_mean(np.stack([inv_T(R) @ Lb.T @ inv_T(O) for R, O in zip(rig, ots, strict=True)]))
    assert np.all(np.diag(est.cov) > 1.15 * np.diag(own.cov))


def test_T_rig_ots_covariance_matches_monte_carlo():
    # the shared T_omc_base term is 20-75 % of the variances here (see the test above); it must be in
    rng = np.random.default_rng(60)
    errs, covs = [], []
    for _ in range(400):   # ratio scatter ~7 %: 20 % is ~3 sigma
        t_omc, base, rig, t_ots, ots = rig_setup(rng, n=30)
        est = link_T_rig_ots(t_omc, rig, t_ots, ots, link_T_omc_base(base))
        errs.append(se3_residuals(T_RIG_OTS, est.T[None])[0])
        covs.append(est.cov)
    emp = np.cov(np.array(errs), rowvar=False)
    assert np.allclose(np.diag(emp) / np.diag(np.mean(covs, axis=0)), 1.0, atol=0.2)


def test_T_rig_ots_needs_pairs():
    rng = np.random.default_rng(17)
    t_omc, base, rig, t_ots, ots = rig_setup(rng)
    with pytest.raises(CalibrationError, match=r"OMC body 'ots_rig' x OTS tool 'base' pairs: 0 pairs within 20 ms"):
        link_T_rig_ots(t_omc, rig, t_ots + S // 40, ots, link_T_omc_base(base))  # 25 ms apart
    with pytest.raises(CalibrationError, match=r"OTS tool 'base': \(199,\) stamps for 200 poses"):
        link_T_rig_ots(t_omc, rig, t_ots[1:], ots, link_T_omc_base(base))


def test_pair_by_stamp_mutual_nearest():
    ta = [0, 10, 20, 30, 40]
    tb = [11, 12, 29, 100, 1]
    ia, ib = pair_by_stamp(ta, tb, tol_ns=5)
    pairs = sorted(zip(ia.tolist(), ib.tolist(), strict=True))
    # 10<->11 (12 is nearer to 10 than to 20 but 10 already has 11), 30<->29, 0<->1; 100 too far
    assert pairs == [(0, 4), (1, 0), (3, 2)]
    assert pair_by_stamp([], tb, 5)[0].size == 0
    ia, ib = pair_by_stamp([5], [4, 6], 5)  # tie -> earlier
    assert ib.tolist() == [0]


# ------------------------------------------------------------------------------------------ link bump

def test_link_bump_thresholds():
    th = BumpThresholds(trans_m=1e-3, rot_rad=3e-3)
    moved = T_TRUE.copy()
    moved[:3, 3] += [0.6e-3, 0.0, 0.0]
    assert link_bump(T_TRUE, moved, th) == (False, pytest.approx(0.6e-3), pytest.approx(0.0, abs=1e-12))
    moved[:3, 3] += [0.0, 0.9e-3, 0.0]  # |d| = 1.08 mm
    bumped, dt, dr = link_bump(T_TRUE, moved, th)
    assert bumped and dt == pytest.approx(np.hypot(0.6e-3, 0.9e-3))
    turned = se3_retract(T_TRUE, [0, 0, 0, 0, 2.9e-3, 0])
    assert link_bump(T_TRUE, turned, th)[0] is False
    bumped, dt, dr = link_bump(T_TRUE, se3_retract(T_TRUE, [0, 0, 0, 0, 3.1e-3, 0]), th)
    assert bumped and dr == pytest.approx(3.1e-3) and dt < 1e-12
    # at the threshold exactly is not a bump (strictly beyond)
    at = T_TRUE.copy()
    at[:3, 3] += [0.0, 0.0, 1e-3]
    assert link_bump(T_TRUE, at, BumpThresholds(trans_m=float(np.linalg.norm(at[:3, 3] - T_TRUE[:3, 3]))))[0] is False
    # a LinkEstimate works as the calibrated side
    est = robust_se3_mean(np.repeat(T_TRUE[None], 3, axis=0))
    assert isinstance(est, LinkEstimate) and link_bump(est, moved, th)[0]


# ------------------------------------------------------------------------------------------ collector

def feed(c, device, body, t, Ts):
    for ti, T in zip(t, Ts, strict=True):
        p, q = T_to_pq(T)
        c.add(device, body, int(ti), p, q)


def test_collector_produces_the_links():
    rng = np.random.default_rng(18)
    t_omc, base, rig, t_ots, ots = rig_setup(rng, n=300)
    c = Collector(links=("T_rig_ots", "T_base_ots"), duration_s=10.0)
    assert c.links == LINK_NAMES  # T_rig_ots brings T_omc_base along
    feed(c, "omc", "base", t_omc, base)
    feed(c, "omc", "ots_rig", t_omc, rig)
    feed(c, "omc", "tool", t_omc, rig)       # not a calibration body: ignored
    feed(c, "ots", "base", t_ots, ots)
    assert c.counts() == {"omc:base": 300, "omc:ots_rig": 300, "ots:base": 299}  # last OTS stamp past 10 s
    assert c.complete
    cal = c.finish(source="test")
    assert set(cal.links) == set(LINK_NAMES)
    assert cal.stamp_ns == t_omc[-1] and cal.duration_s == pytest.approx(10.0) and cal.source == "test"
    for name, T in (("T_omc_base", T_OMC_BASE), ("T_base_ots", inv_T(T_OTS_BASE)), ("T_rig_ots", T_RIG_OTS)):
        assert nees(cal.T(name), cal.links[name].cov, T) <= chi2.ppf(0.999, 6), name
    with pytest.raises(CalibrationError, match="no link 'T_x'"):
        cal.T("T_x")


def test_collector_window_and_bad_poses():
    c = Collector(links=("T_omc_base",), duration_s=1.0, start_ns=10 * S)
    q = [0, 0, 0, 1]
    assert not c.add("omc", "base", 9 * S, [0, 0, 0], q)          # before the window
    assert c.add("omc", "base", 10 * S, [0, 0, 0], q)
    assert not c.add("omc", "base", 10 * S + 1, [np.nan, 0, 0], q)  # invalid: counted, not collected
    assert not c.add("omc", "base", 10 * S + 2, [0, 0, 0], [0, 0, 0, 2])
    assert not c.complete
    assert c.add("omc", "base", 11 * S, [0, 0, 0], q)            # end of the window is inside
    assert c.complete
    assert not c.add("omc", "base", 11 * S + 1, [0, 0, 0], q)
    assert c.n_bad[("omc", "base")] == 2
    with pytest.raises(CalibrationError, match=r"too few sightings of OMC body 'base': 2 in 1 s, "
                                               r"2 invalid poses dropped, need >= 30"):
        c.finish()
    with pytest.raises(ValueError):
        Collector(links=("T_foo",))


def test_collector_refuses_listing_every_problem():
    rng = np.random.default_rng(19)
    n = 300
    base = noisy(T_OMC_BASE, n, SIG_OMC, rng)
    base[n // 2:, 2, 3] += 5e-3  # the base body is knocked 5 mm half way
    c = Collector(bodies=CalibrationBodies(omc_base="ref", ots_base="ref_tool"))
    feed(c, "omc", "ref", stamps(n), base)
    feed(c, "ots", "ref_tool", stamps(10), noisy(T_OTS_BASE, 10, SIG_VEGA, rng))
    with pytest.raises(CalibrationError) as e:
        c.finish()
    msg = str(e.value)
    assert msg.startswith("calibration refused: ")
    assert "OMC body 'ref' moved during the collection" in msg and moved_mm(msg) == pytest.approx(5.0, abs=0.5)
    assert "too few sightings of OTS tool 'ref_tool': 10 in 10 s, need >= 30" in msg


def test_bodies_from_chain_config():
    from fullperc_fusion.pipeline.frame_chain import ChainConfig
    b = CalibrationBodies.from_chain_config(ChainConfig(omc_base="B", ots_base="b", omc_rig="R"))
    assert (b.omc_base, b.ots_base, b.omc_rig) == ("B", "b", "R")
    assert CalibrationBodies() == CalibrationBodies.from_chain_config(ChainConfig())


def test_mean_estimate_keeps_every_sample_and_gives_the_covariance_of_the_mean():
    """The plain average (average mode, the bridge): no sample rejected, even an outlier; covariance of the mean
    about the mean given (or mean_T of all); fewer than 2 samples refused."""
    rng = np.random.default_rng(11)
    T = make_T([1.0, 2.0, 0.5], Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_quat())
    Ts = [se3_retract(T, rng.normal(size=6) * np.array([1e-4] * 3 + [2e-3] * 3)) for _ in range(40)]
    Ts[7] = se3_retract(T, np.array([5e-3, 0, 0, 0, 0, 0]))            # an outlier the robust mean would drop
    est = mean_estimate(Ts)
    assert est.n_samples == est.n_inliers == 40
    r = se3_residuals(mean_T(Ts), np.array(Ts))
    expected = np.cov(r, rowvar=False, ddof=1) / 40 + np.diag(np.repeat(np.square(COV_FLOOR), 3))
    np.testing.assert_allclose(est.cov, expected, rtol=1e-12, atol=0)
    assert robust_se3_mean(Ts).n_inliers < 40
    given = se3_retract(mean_T(Ts), np.full(6, 1e-4))
    np.testing.assert_allclose(mean_estimate(Ts, given).T, given, atol=1e-12)   # the mean the caller uses
    np.testing.assert_allclose(est.T, mean_T(Ts), atol=1e-12)
    with pytest.raises(CalibrationError, match="at least 2"):
        mean_estimate(Ts[:1])
