"""KF / BKF / CKF / CBKF: each equation against hand-computed values, then behaviour on synthetic streams.

Hand-computed cases use isotropic numbers (every axis identical) so the 9x9 algebra reduces to the
3x3 per-axis arithmetic written out in the comments.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_fusion.filters.paper_family import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    FilterParams,
    FusionFilter,
    PassThrough,
    biased_factors,
    kalman_update,
    measurement_matrix,
    process_noise,
    transition,
)

I3 = np.eye(3)
S = 1_000_000_000  # ns per s


# ------------------------------------------------------------------------------------------ equations

def test_transition_eq9():
    F = transition(0.5, has_bias=True)
    x = np.r_[1, 2, 3, 10, 20, 30, 7, 8, 9.0]
    # p + dt v, v, b
    assert np.allclose(F @ x, [6, 12, 18, 10, 20, 30, 7, 8, 9])
    assert transition(0.5, has_bias=False).shape == (6, 6)


def test_process_noise_eq10():
    Q = process_noise(0.5, accel_noise=2.0, bias_walk=0.1, has_bias=True)
    # q dt^3/3 = 2*0.125/3, q dt^2/2 = 2*0.25/2, q dt = 1, q_b dt = 0.05
    assert np.allclose(Q[0:3, 0:3], I3 * (0.25 / 3))
    assert np.allclose(Q[0:3, 3:6], I3 * 0.25)
    assert np.allclose(Q[3:6, 0:3], I3 * 0.25)
    assert np.allclose(Q[3:6, 3:6], I3 * 1.0)
    assert np.allclose(Q[6:9, 6:9], I3 * 0.05)
    assert np.allclose(Q[0:6, 6:9], 0)


def test_measurement_matrices_eq11():
    Hg = measurement_matrix(SOURCE_GLOBAL, has_bias=True)
    Hl = measurement_matrix(SOURCE_LOCAL, has_bias=True)
    assert np.array_equal(Hg, np.hstack([I3, 0 * I3, I3]))
    assert np.array_equal(Hl, np.hstack([I3, 0 * I3, 0 * I3]))
    # without a bias state both sources measure p
    assert np.array_equal(measurement_matrix(SOURCE_GLOBAL, has_bias=False), np.hstack([I3, 0 * I3]))
    # an older sample: p(t - lag) = p - lag v
    assert np.array_equal(measurement_matrix(SOURCE_LOCAL, True, 0.25)[:, 3:6], -0.25 * I3)


def test_biased_factor_eq7():
    # m = x^2 / (var + x^2)
    assert np.allclose(biased_factors([2.0, 1.0, 0.0, 3.0], [1.0, 3.0, 1.0, 0.0]), [0.8, 0.25, 0.0, 1.0])
    # eq. (8): the biased MSE m^2 var + (1-m)^2 x^2 is never above the unbiased var
    x, var = 0.7, 0.4
    m = biased_factors([x], [var])[0]
    assert m**2 * var + (1 - m) ** 2 * x**2 <= var
    # and m minimises it (derivative zero): compare neighbours
    mse = lambda mm: mm**2 * var + (1 - mm) ** 2 * x**2  # noqa: E731
    assert mse(m) <= mse(m + 1e-3) and mse(m) <= mse(m - 1e-3)


def _filter_at(kind, x_axis, P_axis, **kw):
    """A filter at t = 0 whose per-axis state is x_axis=(p, v[, b]) and covariance P_axis (same on x, y, z)."""
    prm = dict(accel_noise=0.0, bias_walk=0.0, global_std=1.0, local_std=1.0, hop_gate=1e9, max_gap_s=10.0)
    prm.update(kw)
    f = FusionFilter(kind, FilterParams(**prm))
    k = len(x_axis)
    f.x = np.kron(np.asarray(x_axis, float), np.ones(3))
    f.P = np.kron(np.asarray(P_axis, float), I3)
    assert f.n == 3 * k
    f.t_ns = 0
    return f


def test_ckf_global_update_by_hand_eq12_13():
    # per axis: p=0, v=0, b=0, P = diag(4, 1, 4), Q = 0, dt = 1 s, global z = 10, r = 1
    f = _filter_at("ckf", [0, 0, 0], np.diag([4.0, 1.0, 4.0]))
    st = f.step(z_global=[10, 10, 10], t_global=1 * S)
    # P' = F P F^T: pp = 4 + 1 = 5, pv = 1, vv = 1, bb = 4
    # H = [1 0 1]: S = 5 + 4 + 1 = 10; G = [5, 1, 4] / 10; y = 10
    assert np.allclose(st.p, 5.0) and np.allclose(st.v, 1.0) and np.allclose(st.b, 4.0)
    # P = P' - G S G^T
    expect = np.array([[5 - 2.5, 1 - 0.5, 0 - 2.0],
                       [1 - 0.5, 1 - 0.1, 0 - 0.4],
                       [0 - 2.0, 0 - 0.4, 4 - 1.6]])
    assert np.allclose(f.P, np.kron(expect, I3))
    assert st.nis == pytest.approx(3 * 100 / 10)   # y^2/S per axis, 3 axes
    assert np.allclose(st.innovation, 10.0)
    assert st.sources == SOURCE_GLOBAL and not st.reset


def test_cbkf_applies_M_after_update_eq14():
    f = _filter_at("cbkf", [0, 0, 0], np.diag([4.0, 1.0, 4.0]))
    st = f.step(z_global=[10, 10, 10], t_global=1 * S)
    # unbiased update as above: p'' = 5 with var 2.5 -> m_p = 25 / 27.5 (position block only)
    m = 25 / 27.5
    assert np.allclose(st.m, np.kron([m, 1, 1], np.ones(3)))
    assert np.allclose(st.p, 5 * m) and np.allclose(st.v, 1.0) and np.allclose(st.b, 4.0)
    # P = M P_updated M^T (our reading of eq. 14, see paper_family.py)
    expect = np.array([[2.5 * m * m, 0.5 * m, -2.0 * m],
                       [0.5 * m, 0.9, -0.4],
                       [-2.0 * m, -0.4, 2.4]])
    assert np.allclose(f.P, np.kron(expect, I3))


def test_bkf_without_bias_state_by_hand():
    # 6 states, per axis p=0, v=0, P=diag(3, 0), Q=0, dt=1; local z=8, r=1 -> S=4, G=[3/4, 0], p''=6
    f = _filter_at("bkf", [0, 0], np.diag([3.0, 0.0]))
    st = f.step(z_local=[8, 8, 8], t_local=1 * S)
    p_var = 3 - 9 / 4
    m = 36 / (p_var + 36)
    assert np.allclose(st.p, 6 * m)
    assert np.allclose(st.b, 0) and f.n == 6


def test_stacked_pair_equals_sequential_updates():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(9, 9))
    P0 = A @ A.T + np.eye(9)
    x0 = rng.normal(size=9)
    zg, zl = rng.normal(size=3), rng.normal(size=3)
    f = FusionFilter("ckf", FilterParams(accel_noise=0.3, bias_walk=0.01, hop_gate=1e9))
    f.x, f.P, f.t_ns = x0.copy(), P0.copy(), 0
    st = f.step(z_global=zg, t_global=S // 10, z_local=zl, t_local=S // 10)
    # oracle: predict, then two independent sequential updates
    F, Q = transition(0.1, True), process_noise(0.1, 0.3, 0.01, True)
    x, P = F @ x0, F @ P0 @ F.T + Q
    x, P, *_ = kalman_update(x, P, zg, measurement_matrix(SOURCE_GLOBAL, True), f.params.global_std**2 * I3)
    x, P, *_ = kalman_update(x, P, zl, measurement_matrix(SOURCE_LOCAL, True), f.params.local_std**2 * I3)
    assert np.allclose(f.x, x) and np.allclose(f.P, P)
    assert st.sources == SOURCE_GLOBAL | SOURCE_LOCAL


def test_pair_with_different_stamps_is_exact_under_constant_velocity():
    # With Q = 0, predicting to the older stamp, updating, predicting on and updating again is exact;
    # the stacked update with the lag in H must give the same posterior.
    rng = np.random.default_rng(4)
    A = rng.normal(size=(9, 9))
    P0 = A @ A.T + np.eye(9)
    x0 = rng.normal(size=9)
    zg, zl = rng.normal(size=3), rng.normal(size=3)
    tg, tl = 100_000_000, 104_000_000   # global 4 ms older
    f = FusionFilter("ckf", FilterParams(accel_noise=0.0, bias_walk=0.0, hop_gate=1e9))
    f.x, f.P, f.t_ns = x0.copy(), P0.copy(), 0
    f.step(z_global=zg, t_global=tg, z_local=zl, t_local=tl)
    F1, F2 = transition(0.1, True), transition(0.004, True)
    x, P = F1 @ x0, F1 @ P0 @ F1.T
    x, P, *_ = kalman_update(x, P, zg, measurement_matrix(SOURCE_GLOBAL, True), f.params.global_std**2 * I3)
    x, P = F2 @ x, F2 @ P @ F2.T
    x, P, *_ = kalman_update(x, P, zl, measurement_matrix(SOURCE_LOCAL, True), f.params.local_std**2 * I3)
    assert f.t_ns == tl
    assert np.allclose(f.x, x) and np.allclose(f.P, P)


def _plain_cv_kf(zs, ts, q, r, p0_var, v0_var):
    """Independent 6-state constant-velocity KF (textbook form), the oracle for the reduction test."""
    x = P = None
    t_prev = None
    out = []
    for z, t in zip(zs, ts, strict=True):
        if x is None:
            x = np.r_[z, 0, 0, 0]
            P = np.diag([p0_var] * 3 + [v0_var] * 3)
        else:
            dt = (t - t_prev) / 1e9
            F = np.block([[I3, dt * I3], [0 * I3, I3]])
            Q = q * np.block([[dt**3 / 3 * I3, dt**2 / 2 * I3], [dt**2 / 2 * I3, dt * I3]])
            x = F @ x
            P = F @ P @ F.T + Q
            H = np.hstack([I3, 0 * I3])
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + r * I3)
            x = x + K @ (z - H @ x)
            P = (np.eye(6) - K @ H) @ P
        t_prev = t
        out.append(x.copy())
    return np.array(out)


def test_nine_state_with_zero_bias_and_no_local_data_is_the_plain_cv_kf():
    rng = np.random.default_rng(7)
    ts = np.cumsum(rng.integers(7_000_000, 10_000_000, size=300))
    zs = np.cumsum(rng.normal(0, 1e-3, size=(300, 3)), axis=0)
    prm = FilterParams(init_bias_std=0.0, bias_walk=0.0, hop_to_bias=False)
    ckf = FusionFilter("ckf", prm)
    kf = FusionFilter("kf", prm)
    got9 = np.array([ckf.step(z_global=z, t_global=int(t)).p for z, t in zip(zs, ts, strict=True)])
    got6 = np.array([kf.step(z_global=z, t_global=int(t)).p for z, t in zip(zs, ts, strict=True)])
    want = _plain_cv_kf(zs, ts, prm.accel_noise, prm.global_std**2, prm.init_pos_std**2, prm.init_vel_std**2)
    assert np.allclose(got9, want[:, 0:3], atol=1e-12)
    assert np.allclose(got6, want[:, 0:3], atol=1e-12)
    assert np.allclose(ckf.bias, 0)


def test_eq14_posterior_choice_keeps_P_bounded_literal_prior_diverges():
    """Our reading of eq. (14) (M P_updated M^T) vs the literal one (M P' M^T)."""
    rng = np.random.default_rng(5)
    runs = {}
    for choice in ("posterior", "prior"):
        f = FusionFilter("bkf", FilterParams(eq14_covariance=choice))
        trace = []
        for k in range(2000):
            f.step(z_global=np.r_[0.5, 0.2, 0.3] + rng.normal(0, 3e-4, 3), t_global=(k + 1) * S // 120)
            trace.append(f.P[0, 0])
        runs[choice] = np.array(trace)
    post, prior = runs["posterior"], runs["prior"]
    # posterior: P_pp settles below the measurement variance
    assert post[-1] < FilterParams().global_std**2
    assert abs(post[-1] - post[-500]) < 0.01 * post[-1]
    # literal prior: measurements never reduce P, it keeps growing (here from 25e-6 m^2 upward)
    assert np.all(np.diff(prior[100:]) > 0)
    assert prior[-1] > 1000 * post[-1]


# ------------------------------------------------------------------------------------------ behaviour

def _truth(t):
    """Target on an arc, radius 0.2 m at 0.25 rad/s (5 cm/s), in base."""
    w = 0.25
    return np.array([0.5 + 0.2 * np.cos(w * t), 0.2 * np.sin(w * t), 0.3])


OFFSET = np.array([3e-3, -2e-3, 1e-3])   # constant global bias
HOP_B = (3.0, np.array([4e-3, 0, 0]))    # hop while the local source is visible
HOP_P = (6.5, np.array([0, 3e-3, 0]))    # hop after the local source disappeared
LOCAL_VISIBLE = (1.0, 5.0)


def _offset(t):
    o = OFFSET.copy()
    for th, d in (HOP_B, HOP_P):
        if t >= th:
            o = o + d
    return o


def _run(kind, seed=11, **prm):
    """B->P stream: global 120 Hz throughout; local 60 Hz during LOCAL_VISIBLE only."""
    rng = np.random.default_rng(seed)
    ev = [(k / 120, "g") for k in range(int(8 * 120))]
    ev += [(0.003 + k / 60, "l") for k in range(8 * 60) if LOCAL_VISIBLE[0] <= 0.003 + k / 60 < LOCAL_VISIBLE[1]]
    ev.sort()
    f = FusionFilter(kind, FilterParams(**prm))
    rows = []
    for t, s in ev:
        ns = int(round(t * 1e9)) + S
        if s == "g":
            st = f.step(z_global=_truth(t) + _offset(t) + rng.normal(0, 3e-4, 3), t_global=ns)
        else:
            st = f.step(z_local=_truth(t) + rng.normal(0, 1e-4, 3), t_local=ns)
        rows.append((t, np.linalg.norm(st.p - _truth(t)), *st.b, st.hop))
    return np.array(rows)


def _mae_mm(r, t0, t1):
    m = (r[:, 0] >= t0) & (r[:, 0] < t1)
    return 1e3 * r[m, 1].mean()


def _bias_at(r, t):
    i = np.searchsorted(r[:, 0], t) - 1
    return r[i, 2:5]


@pytest.mark.parametrize("kind", ["ckf", "cbkf"])
def test_compensated_filters_learn_offset_and_keep_it_after_local_disappears(kind):
    r = _run(kind)
    # bias learned while both sources are present, and re-learned after the hop at 3 s
    assert np.linalg.norm(_bias_at(r, 2.9) - OFFSET) < 0.3e-3
    assert np.linalg.norm(_bias_at(r, 4.9) - (OFFSET + HOP_B[1])) < 0.3e-3
    # B phase: sub-millimetre
    assert _mae_mm(r, 1.5, 5.0) < 0.5
    # P phase (local gone at 5 s): the compensation is kept, error stays far below the 5 mm offset
    assert _mae_mm(r, 5.1, 6.5) < 0.7
    # the P-phase hop at 6.5 s is flagged and absorbed into the bias
    hops = r[r[:, 5] > 0, 0]
    assert np.any(np.abs(hops - HOP_P[0]) < 0.02)
    assert _mae_mm(r, 6.6, 8.0) < 1.0
    assert np.linalg.norm(_bias_at(r, 7.9) - _offset(7.9)) < 1.0e-3


@pytest.mark.parametrize("kind", ["kf", "bkf"])
def test_uncompensated_filters_follow_the_global_offset(kind):
    r = _run(kind)
    off_b, off_p = np.linalg.norm(OFFSET + HOP_B[1]), np.linalg.norm(_offset(7.0))
    # while local is present KF averages the two sources: better than OMC, worse than the compensation
    assert 0.5 < _mae_mm(r, 3.5, 5.0) < 1e3 * off_b
    # after the local source disappears KF reports the biased global position
    assert _mae_mm(r, 5.5, 6.5) > 0.8e3 * off_b
    assert _mae_mm(r, 6.6, 8.0) > 0.8e3 * off_p
    assert np.allclose(r[:, 2:5], 0)


def test_bkf_default_stays_within_micrometres_of_kf():
    # M on the position block only: m_p = 1 - var_p / p^2 (see paper_family.py); same noise seed.
    # Right after initialization var_p = (5 mm)^2 and p ~ 0.5 m: a shift of var/p ~ 50 um per step,
    # which vanishes once var_p has converged to ~1e-7 m^2.
    a, b = _run("kf"), _run("bkf")
    d, t = np.abs(a[:, 1] - b[:, 1]), a[:, 0]
    assert d.max() < 0.1e-3
    assert d[t > 0.5].max() < 2e-6
    assert d.max() > 0      # M is really applied


def test_why_M_is_not_applied_to_bias_and_velocity():
    """The default shrink_blocks=('p',) is a decision; these runs show the alternatives fail."""
    default = _run("cbkf")
    with_b = _run("cbkf", shrink_blocks=("p", "b"))
    with_v = _run("cbkf", shrink_blocks=("p", "v"))
    # shrinking b: b = 0 is absorbing and b decays while only global data arrive: compensation lost
    assert _mae_mm(with_b, 5.5, 6.5) > 3 * _mae_mm(default, 5.5, 6.5)
    # shrinking v: the velocity collapses while moving at 5 cm/s and the estimate lags, even with
    # the accurate local source present
    assert _mae_mm(with_v, 1.5, 3.0) > 1.8 * _mae_mm(default, 1.5, 3.0)


def test_no_local_data_ever_compensated_equals_uncompensated_up_to_bias_split():
    # Without local data b is unobservable: CKF's p + b follows the same data as KF's p.
    rng = np.random.default_rng(1)
    kf, ckf = FusionFilter("kf"), FusionFilter("ckf", FilterParams(hop_to_bias=False))
    for k in range(600):
        z = _truth(k / 120) + OFFSET + rng.normal(0, 3e-4, 3)
        a = kf.step(z_global=z, t_global=(k + 1) * S // 120)
        b = ckf.step(z_global=z, t_global=(k + 1) * S // 120)
    assert np.linalg.norm((b.p + b.b) - a.p) < 0.3e-3


# ------------------------------------------------------------------------------------------ bad input

def test_time_backwards_and_nan_are_refused_without_corrupting_state():
    f = FusionFilter("cbkf")
    f.step(z_global=[0.1, 0.2, 0.3], t_global=2 * S)
    x = f.x.copy()
    with pytest.raises(ValueError, match="backwards"):
        f.step(z_global=[0.1, 0.2, 0.3], t_global=1 * S)
    with pytest.raises(ValueError, match="non-finite"):
        f.step(z_global=[np.nan, 0.2, 0.3], t_global=3 * S)
    with pytest.raises(ValueError):
        f.step(t_global=3 * S)
    assert np.array_equal(f.x, x) and f.t_ns == 2 * S


def test_long_gap_reinitialises_kinematics_and_keeps_bias():
    f = FusionFilter("ckf")
    f.step(z_global=[0.1, 0.2, 0.3], t_global=S)
    f.x[3:6] = [0.1, 0, 0]          # moving at 10 cm/s
    f.x[6:9] = [1e-3, 2e-3, 3e-3]   # learned bias
    st = f.step(z_global=[0.2, 0.2, 0.3], t_global=S + 300 * S)   # five minutes later
    assert st.reset
    assert np.allclose(st.v, 0)                     # no 30 m extrapolation
    assert np.allclose(st.b, [1e-3, 2e-3, 3e-3])
    assert np.allclose(st.p, [0.2 - 1e-3, 0.2 - 2e-3, 0.3 - 3e-3])
    assert np.all(np.isfinite(f.P))


def test_passthrough_only_reports_global_samples():
    f = PassThrough()
    assert f.step(z_local=[1, 2, 3], t_local=S) is None
    st = f.step(z_global=[1, 2, 3], t_global=S)
    assert np.array_equal(st.p, [1, 2, 3]) and st.sources == SOURCE_GLOBAL


def test_invalid_parameters_are_named():
    with pytest.raises(ValueError, match="global_std"):
        FilterParams(global_std=0).validate()
    with pytest.raises(ValueError, match="shrink_blocks"):
        FilterParams(shrink_blocks=("q",)).validate()
    with pytest.raises(ValueError, match="kind"):
        FusionFilter("ukf")
