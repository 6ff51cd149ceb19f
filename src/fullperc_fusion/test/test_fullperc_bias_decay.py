"""The OMC position bias b's decay with distance once the local source has lost the target (issue 41 item 1;
``FullpercParams.bias_length``, ``bias_field_std``; the model in fullperc_reference's module docstring):

* one prediction on the reference: b' = f b, b's rows and columns of P times f and bias_field_std^2 (1 - f^2) on its
  variance, f = exp(-(d - d_max) / bias_length); nothing before ``local_lost_s``, nothing on the way back towards
  where the local source last saw the target, only the part beyond d_max when it leaves again; far away b is at its
  prior (mean 0, variance bias_field_std^2);
* a run on the fast form: a constant OMC offset learnt while the Vega sees the tool; the tool moves on without the
  Vega and b decays by the distance; with the Vega still seeing it, or with bias_length 0, b is kept;
* 0 is off: with bias_length 0 the reference's every step is bit for bit what it was before the decay existed (the
  previous spatial-decay rule, beta's and mu's alone, restated below) on a stream where the Vega loses the tool.

test_fullperc_fast.py holds the fast form to the reference with the decay acting.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.so3 import R_to_quat
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_reference import FullpercReference
from fullperc_fusion.filters.rot_noise_scale import scale_decay

MS = 1_000_000
B = slice(6, 9)
OFFSET = np.array([2e-3, -1e-3, 0.5e-3])    # the OMC's position error in the test runs


def _m(t, src, p, q=None):
    return Measurement(t, src, np.asarray(p, dtype=float), q)


def _learnt(f, n: int = 300) -> None:
    """n pairs at rest at (0, 0, 0.5), the OMC off by OFFSET: b (with g) learns it."""
    q = R_to_quat(Rot.from_euler("x", 40, degrees=True).as_matrix())
    for k in range(n):
        t = k * 8 * MS
        f.predict(t)
        f.update(_m(t, SOURCE_GLOBAL, np.array([0, 0, 0.5]) + OFFSET, q), _m(t, SOURCE_LOCAL, [0, 0, 0.5], q))


def test_the_default_is_off_and_values_are_checked():
    """Off by default (b kept as learnt, as before; the field's s_f and L_f, spec's fit, act on the output's covariance
    only: test_fullperc_field_cov.py): a room's noise-model file sets the decay from its own fit
    (test/test_model_constants.py: what fit_noise_model writes for the spec and the paper bags)."""
    pr = FullpercParams()
    assert pr.bias_length == 0.0
    with pytest.raises(ValueError, match="bias_length"):
        FullpercParams(bias_length=-1.0).validate()
    with pytest.raises(ValueError, match="bias_field_std"):
        FullpercParams(bias_field_std=float("nan")).validate()


def test_decay_of_one_prediction_on_the_reference():
    pr = FullpercParams(bias_walk=0.0, bias_length=0.1, bias_field_std=0.3e-3)
    f = FullpercReference(pr)
    _learnt(f)
    t0, a = f.t_ns, f.s.p.copy()
    np.testing.assert_array_equal(f.s.rot_anchor, a)
    assert np.linalg.norm(f.s.b) > 1e-3                    # learnt (most of the offset is in b)
    f.s.v = np.array([0.2, 0.0, 0.0])
    b0, P0 = f.s.b.copy(), f.s.P.copy()
    f.predict(t0 + 50 * MS)                                  # 0.05 s: the Vega has not lost the tool yet
    np.testing.assert_array_equal(f.s.b, b0)
    np.testing.assert_array_equal(f.s.P[B, B], P0[B, B])
    f.predict(t0 + 300 * MS)                                 # 0.3 s, 60 mm away
    d = float(np.linalg.norm(f.s.p - a))
    assert d == pytest.approx(0.06, abs=1e-9)
    g = math.exp(-d / pr.bias_length)
    np.testing.assert_allclose(f.s.b, g * b0, rtol=1e-12)
    expected = g * g * P0[B, B] + pr.bias_field_std**2 * (1 - g * g) * np.eye(3)
    np.testing.assert_allclose(f.s.P[B, B], expected, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(f.s.P[B, 0:3], g * (P0[B, 0:3] + 0.3 * P0[B, 3:6]), rtol=1e-9, atol=1e-20)
    f.s.v = np.array([-0.1, 0.0, 0.0])                       # back towards a: no change
    b1, P1 = f.s.b.copy(), f.s.P[B, B].copy()
    f.predict(t0 + 400 * MS)
    np.testing.assert_array_equal(f.s.b, b1)
    np.testing.assert_array_equal(f.s.P[B, B], P1)
    f.s.v = np.array([0.3, 0.0, 0.0])                        # out again to 80 mm: only the 20 mm beyond d_max count
    f.predict(t0 + 500 * MS)
    np.testing.assert_allclose(f.s.b, math.exp(-(0.08 - 0.06) / pr.bias_length) * b1, rtol=1e-9)
    f.s.v = np.array([10.0, 0.0, 0.0])                       # 2 m away: b at its prior, mean 0, std bias_field_std
    f.predict(t0 + 700 * MS)
    assert np.abs(f.s.b).max() < 1e-6 * np.abs(b0).max()
    np.testing.assert_allclose(np.diag(f.s.P[B, B]), pr.bias_field_std**2, rtol=1e-6)


def _moving_run(params: FullpercParams, local_while_moving: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """The fast form: 2.4 s at rest with the Vega (OMC off by OFFSET), then 1.5 s at 0.1 m/s along x with the Vega or
    without. Returns (b when the tool started moving, b at the end, the distance moved)."""
    f = FullpercFilter(params)
    _learnt(f)
    b_learnt = f.state.b.copy()
    q = R_to_quat(Rot.from_euler("x", 40, degrees=True).as_matrix())
    p0, t0 = np.array([0.0, 0.0, 0.5]), f.t_ns
    for k in range(1, 189):
        t = t0 + k * 8 * MS
        p = p0 + [0.1 * k * 8e-3, 0.0, 0.0]
        f.predict(t)
        ms = [_m(t, SOURCE_GLOBAL, p + OFFSET, q)]
        if local_while_moving:
            ms.append(_m(t, SOURCE_LOCAL, p, q))
        f.update(*ms)
    return b_learnt, f.state.b, float(p[0] - p0[0])


def test_b_decays_with_the_distance_from_where_the_vega_lost_the_tool():
    """OMC alone, b is not observable: what is left of it is the decay by distance (to the slight pull of the OMC
    samples on b, which the motion model cannot tell from a move), so the output falls back towards the raw OMC.
    The time decay of g is the same in every run; b's own random walk does not move its mean."""
    pr = FullpercParams(bias_length=0.05, bias_field_std=0.3e-3)
    learnt, end, d = _moving_run(pr, local_while_moving=False)
    assert d == pytest.approx(0.1504, abs=1e-3)
    decay = math.exp(-(d - 0.1 * 0.1) / pr.bias_length)     # the first 0.1 s (local_lost_s) does not count
    assert decay < 0.1
    np.testing.assert_allclose(end, decay * learnt, atol=0.1 * np.abs(learnt).max())
    assert np.linalg.norm(end) < 0.2 * np.linalg.norm(learnt)
    # off: b kept as learnt (to the same pull); with the Vega still seeing the tool: kept too (observed, no decay)
    _, kept, _ = _moving_run(FullpercParams(bias_length=0.0), False)
    assert np.linalg.norm(kept - learnt) < 0.2 * np.linalg.norm(learnt)
    _, seen, _ = _moving_run(pr, local_while_moving=True)
    assert np.linalg.norm(seen - learnt) < 0.2 * np.linalg.norm(learnt)


def _previous_spatial_decay(self, P: np.ndarray, t: int) -> None:
    """FullpercReference's spatial decay as it was before b's (beta's and mu's alone), for the bit-identity test."""
    s, pr = self.s, self.params
    if s.rot_anchor is None or (t - s.t_local_ns) * 1e-9 <= pr.local_lost_s:
        return
    d = math.dist(s.p, s.rot_anchor)
    if d <= s.rot_dmax:
        return
    s.rot_scale = scale_decay(s.rot_scale, d - s.rot_dmax, pr.rot_noise_length)
    if pr.rot_bias_length > 0.0:
        f = math.exp(-(d - s.rot_dmax) / pr.rot_bias_length)
        s.beta = f * s.beta
        P[15:18, :] *= f
        P[:, 15:18] *= f
        P[15:18, 15:18] += pr.rot_sys_std**2 * (1.0 - f * f) * np.eye(3)
    s.rot_dmax = d


def _outage_stream(seed: int, n: int):
    """Pairs and OMC-only items on a moving path; no Vega in items 100-199 of every 200 (it has lost the tool)."""
    rng = np.random.default_rng(seed)
    q = R_to_quat(Rot.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix())
    out, t = [], 0
    for k in range(n):
        t += int(rng.integers(6 * MS, 10 * MS))
        z = np.array([0.3 * np.sin(k / 150), 0.2 * np.cos(k / 90), 0.5 + 0.05 * np.sin(k / 40)])
        ms = [_m(t, SOURCE_GLOBAL, z + OFFSET + rng.normal(0, 2e-4, 3), q)]
        if k % 200 < 100 and rng.random() < 0.7:
            ms.append(_m(t, SOURCE_LOCAL, z + rng.normal(0, 1e-4, 3), q))
        out.append(ms)
    return out


def test_bias_length_zero_is_bit_identical_to_the_model_without_the_decay(monkeypatch):
    items = _outage_stream(5, 1000)
    pr = FullpercParams(bias_length=0.0, bias_field_std=0.3e-3)   # the std alone changes no state
    new = []
    f = FullpercReference(pr)
    for ms in items:
        f.predict(max(m.t_ns for m in ms))
        new.append(f.update(*ms))
    monkeypatch.setattr(FullpercReference, "_spatial_decay", _previous_spatial_decay)
    g = FullpercReference(pr)
    moved = 0
    for ms, a in zip(items, new, strict=True):
        g.predict(max(m.t_ns for m in ms))
        b = g.update(*ms)
        for k in ("p", "v", "b", "P", "q", "innovation"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), k
        moved += g.s.rot_dmax > 0.0
    assert moved > 100            # the local source was lost and the tool moved on: the decay's branch was reached
