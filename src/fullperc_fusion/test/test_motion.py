"""The motion presets and the IMM arithmetic of ``motion: auto`` (filters/motion.py).

The recursion is held to filterpy's ``IMMEstimator`` (R. Labbe; an independent implementation of Blom and
Bar-Shalom's IMM): two or three linear constant-velocity Kalman filters that differ only in their process noise, fed
the same measurements, must give filterpy's model probabilities, combined state and covariance at every step when the
mixing, the probability update and the combination are ours (:func:`mixing`, :func:`mix`, :func:`posterior`).
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import IMMEstimator, KalmanFilter

from fullperc_fusion.filters.motion import MOTIONS, PRESETS, mix, mixing, posterior, preset_fields, transition

DT = 0.01


def _kf(q: float) -> KalmanFilter:
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x = np.array([0.0, 0.0])
    kf.F = np.array([[1.0, DT], [0.0, 1.0]])
    kf.H = np.array([[1.0, 0.0]])
    kf.P = np.diag([1e-2, 1.0])
    kf.R = np.array([[1e-6]])
    kf.Q = Q_discrete_white_noise(2, DT, q)
    return kf


def _track(n: int, seed: int) -> np.ndarray:
    """Still, then a fast swing, then still: the models' weights must move both ways."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    x = np.where((t > 1.0) & (t < 2.0), 0.3 * np.sin(2 * np.pi * (t - 1.0)) ** 2, 0.0)
    return x + rng.normal(0, 1e-3, n)


@pytest.mark.parametrize("qs", [(1e-4, 10.0), (1e-4, 0.1, 10.0)])
def test_the_recursion_equals_filterpys_imm_estimator(qs):
    n = len(qs)
    M = np.full((n, n), 0.02 / (n - 1))
    np.fill_diagonal(M, 0.98)
    mu0 = np.full(n, 1.0 / n)
    ref = IMMEstimator([_kf(q) for q in qs], mu0.copy(), M)
    ours = [_kf(q) for q in qs]
    mu = mu0.copy()
    c, W = mixing(mu, M)
    seen_fast = seen_still = 0
    for z in _track(300, 3):
        # ours: interaction, then each model's prediction
        mixed = [mix(W[:, j], [f.x for f in ours], [f.P for f in ours]) for j in range(n)]
        for f, (x0, P0) in zip(ours, mixed, strict=True):
            f.x, f.P = x0, P0
            f.predict()
        ref.predict()
        for f in ours:
            f.update(np.array([z]))
        ref.update(np.array([z]))
        mu, _ = posterior(c, [f.log_likelihood for f in ours])
        c, W = mixing(mu, M)
        x, P = mix(mu, [f.x for f in ours], [f.P for f in ours])
        assert np.allclose(mu, ref.mu, rtol=1e-9, atol=1e-12)
        assert np.allclose(x, ref.x, rtol=1e-9, atol=1e-12)
        assert np.allclose(P, ref.P, rtol=1e-9, atol=1e-15)
        seen_fast += mu[-1] > 0.9
        seen_still += int(np.argmax(mu)) == 0
    assert seen_fast > 50 and seen_still > 50   # the stream moved the weights both ways


def test_posterior_survives_likelihoods_far_below_the_smallest_float():
    mu, log_l = posterior(np.array([0.5, 0.5]), [-2000.0, -2000.0 - np.log(3.0)])
    assert np.allclose(mu, [0.75, 0.25]) and np.isfinite(log_l) and abs(log_l - (-2000.0 + np.log(2 / 3))) < 1e-9


def test_transition_rows_sum_to_one_and_stay_with_the_dwell_time():
    T = transition(0.5, 3, 2.0)
    assert np.allclose(T.sum(axis=1), 1.0) and np.isclose(T[0, 0], np.exp(-0.25))
    assert np.isclose(T[0, 1], T[0, 2]) and np.array_equal(transition(0.5, 1, 2.0), np.ones((1, 1)))
    assert np.allclose(transition(0.0, 2, 2.0), np.eye(2))


def test_mix_is_the_moment_matched_mixture():
    rng = np.random.default_rng(0)
    w = np.array([0.2, 0.8])
    dx = [rng.normal(size=3), rng.normal(size=3)]
    Ps = [np.eye(3), 2 * np.eye(3)]
    m, P = mix(w, dx, Ps)
    assert np.allclose(m, 0.2 * dx[0] + 0.8 * dx[1])
    want = sum(wi * (Pi + np.outer(d - m, d - m)) for wi, d, Pi in zip(w, dx, Ps, strict=True))
    assert np.allclose(P, want)


def test_presets_set_the_motion_fields_and_auto_sets_none():
    assert MOTIONS == ("auto", "arm", "hand", "static")
    assert preset_fields("auto") == {}
    for name, fields in PRESETS.items():
        assert set(fields) == {"accel_noise", "ang_accel_noise", "init_vel_std", "hop_to_bias"}, name
        got = preset_fields(name)
        got["accel_noise"] = -1.0   # a copy: the table cannot be changed through it
        assert PRESETS[name]["accel_noise"] > 0
    # the order of the classes: a hand moves faster than an arm, an arm faster than a breathing patient
    assert PRESETS["static"]["accel_noise"] < PRESETS["arm"]["accel_noise"] < PRESETS["hand"]["accel_noise"]
    assert not PRESETS["hand"]["hop_to_bias"] and PRESETS["arm"]["hop_to_bias"]
    with pytest.raises(ValueError, match="motion must be one of"):
        preset_fields("robot")



def test_hop_mixture_is_the_two_term_mixture_in_logarithms():
    from fullperc_fusion.filters.motion import HOP_PRIOR, hop_mixture

    a, b = -3.0, -7.5
    want = np.log((1 - HOP_PRIOR) * np.exp(a) + HOP_PRIOR * np.exp(b))
    assert abs(hop_mixture(a, b) - want) < 1e-12
    assert abs(hop_mixture(-5000.0, -20.0) - (np.log(HOP_PRIOR) - 20)) < 1e-9
