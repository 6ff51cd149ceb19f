"""The global rotation-noise scale mu (rot_noise_scale) and how ``fullperc`` uses it (both filter forms).

Each rule of the module docstring pinned: the pair estimate is unbiased for the OMC's true rotation variance over
the model's, the step is an exponential average with a clip, the decay goes by distance not time, the scaled
covariance is D R D; in the filter: mu falls where the OMC agrees with the Vega better than its model says, rises
where it agrees worse, is not learnt from a global sample alone, returns to 1 with the distance from where the Vega
lost the tool,
starts at 1 after a re-initialisation, is in the snapshot, and a lower mu gives a better orientation there.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fullperc_common.so3 import R_to_quat, quat_to_R, so3_exp, so3_log
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_reference import FullpercReference
from fullperc_fusion.filters.rot_noise_scale import pair_estimate, scale_decay, scale_step, scaled_cov

S = 1_000_000_000
SG, SL = 2.4e-3, 1.0e-3       # model std of the OMC's and the Vega's rotation per axis [rad]


def test_pair_estimate_is_unbiased_for_the_variance_ratio():
    """E est = mu_true when the OMC's rotation noise is sqrt(mu_true) x its model's (beta known: tr P_beta = 0)."""
    rng = np.random.default_rng(1)
    for mu_true in (0.05, 0.3, 1.0, 4.0):
        ests = []
        for _ in range(4000):
            Rt = so3_exp(rng.normal(size=3))
            Rg = so3_exp(rng.normal(0, SG * math.sqrt(mu_true), 3)) @ Rt
            Rl = so3_exp(rng.normal(0, SL, 3)) @ Rt
            d = so3_log(Rg @ Rl.T).tolist()
            ests.append(pair_estimate(d, 3 * SL**2, 0.0, 3 * SG**2))
        se = np.std(ests) / math.sqrt(len(ests))
        assert abs(np.mean(ests) - mu_true) < 4 * se + 1e-3, mu_true
    # the bias's own uncertainty is taken off: a pair that differs by exactly what P_beta explains gives 0
    assert pair_estimate([1e-3, 0.0, 0.0], 0.0, 1e-6, 1e-5) == pytest.approx(0.0, abs=1e-12)


def test_scale_step_is_an_exponential_average_with_a_clip():
    assert scale_step(1.0, None, 5 * S, 0.2, 1.0, 0.05, 25.0) == 1.0          # the first pair starts the clock
    a = 1 - math.exp(-0.5)
    assert scale_step(1.0, 0, S // 2, 0.2, 1.0, 0.05, 25.0) == pytest.approx((1 - a) + a * 0.2, rel=1e-15)
    assert scale_step(0.06, 0, 10 * S, -3.0, 1.0, 0.05, 25.0) == 0.05         # floor
    assert scale_step(20.0, 0, 10 * S, 400.0, 1.0, 0.05, 25.0) == 25.0       # ceiling
    assert scale_step(0.5, 0, S, float("nan"), 1.0, 0.05, 25.0) == 0.5       # a bad estimate changes nothing
    assert scale_step(0.5, 2 * S, S, 0.1, 1.0, 0.05, 25.0) == 0.5            # time going backwards: dt 0


def test_scale_decay_goes_by_distance():
    assert scale_decay(0.2, 0.0565, 0.0565) == pytest.approx(1 - 0.8 / math.e, rel=1e-15)
    assert scale_decay(3.0, 0.0565 * 2, 0.0565) == pytest.approx(1 + 2 / math.e**2, rel=1e-15)
    assert scale_decay(0.2, 0.0, 0.0565) == 0.2
    assert scale_decay(0.2, 1.0, 0.0) == 0.2                                  # L = 0: kept


def test_scaled_cov_is_d_r_d_and_leaves_its_input():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 6))
    R = A @ A.T + np.eye(6) * 0.1
    R0 = R.copy()
    out = scaled_cov(R, 0.09)
    D = np.diag([1, 1, 1, 0.3, 0.3, 0.3])
    assert np.allclose(out, D @ R @ D, rtol=1e-14, atol=0) and np.array_equal(R, R0)
    assert np.all(np.linalg.eigvalsh(out) > 0)


# ---------------------------------------------------------------------------------------------- in the filter
def _stream(seed: int, n: int, ratio: float, local_until: int | None = None, speed: float = 0.05):
    """Items at 120 Hz of a turning, moving tool: OMC every item, Vega every other one until ``local_until``;
    the OMC's rotation noise ``ratio`` x its model's std."""
    rng = np.random.default_rng(seed)
    cov_g = np.diag([1e-8] * 3 + [SG**2] * 3)
    cov_l = np.diag([4e-9] * 3 + [SL**2] * 3)
    sg = SG * ratio
    w = np.array([0.3, -0.2, 0.1])
    beta = np.array([2e-3, -1e-3, 0.5e-3])
    out, truth = [], []
    for k in range(n):
        t = S + k * S // 120
        Rt = so3_exp(w * k / 120) @ so3_exp(np.array([0.3, 0.2, 0.1]))
        pt = np.array([0.4 + speed * k / 120, 0.1, 0.2])
        ms = [Measurement(t, SOURCE_GLOBAL, pt + rng.normal(0, 1e-4, 3),
                          R_to_quat(so3_exp(beta) @ so3_exp(rng.normal(0, sg, 3)) @ Rt), cov_g)]
        if k % 2 == 0 and (local_until is None or k < local_until):
            ms.append(Measurement(t, SOURCE_LOCAL, pt + rng.normal(0, 6e-5, 3),
                                  R_to_quat(so3_exp(rng.normal(0, SL, 3)) @ Rt), cov_l))
        out.append(ms)
        truth.append(Rt)
    return out, truth


@pytest.fixture(scope="module")
def stream():
    """:func:`_stream` with the same arguments, made once per module: the two filter forms of each test below run
    the same streams (they used to make them once per form). Read-only arrays: a filter that changed a measurement in
    place would raise instead of changing the other form's input."""
    made: dict[tuple, tuple] = {}

    def get(*args, **kw):
        key = (args, tuple(sorted(kw.items())))
        if key not in made:
            items, truth = _stream(*args, **kw)
            for m in (m for ms in items for m in ms):
                for a in (m.p, m.q, m.cov):
                    a.flags.writeable = False
            made[key] = items, truth
        return made[key]
    return get


def _state(f):
    """The filter's state in the reference's form, for either form."""
    return f.s if isinstance(f, FullpercReference) else f.state


def _run(f, items, truth=None):
    mus, errs = [], []
    for k, ms in enumerate(items):
        st = f.update(*ms)
        mus.append(_state(f).rot_scale)
        if truth is not None:
            errs.append(float(np.linalg.norm(so3_log(quat_to_R(st.q) @ truth[k].T))))
    return np.array(mus), np.array(errs)


@pytest.mark.parametrize("form", [FullpercReference, FullpercFilter])
def test_mu_follows_the_omc_where_the_vega_sees_the_tool(form, stream):
    """OMC at 0.3x its model's rotation std (variance ratio 0.09): mu settles near 0.09, and the orientation is
    closer to the truth than with the scale off; an OMC at 2x (ratio 4) drives it up instead."""
    items, truth = stream(3, 1800, 0.3, speed=0.0)
    mus, errs = _run(form(), items, truth)
    assert 0.05 <= np.median(mus[900:]) < 0.2
    _, errs_off = _run(form(FullpercParams(rot_noise_adapt_time=0.0)), items, truth)
    assert np.sqrt(np.mean(errs[900:] ** 2)) < 0.95 * np.sqrt(np.mean(errs_off[900:] ** 2))
    mus_hi, _ = _run(form(), stream(4, 1800, 2.0, speed=0.0)[0])
    assert 2.5 < np.median(mus_hi[900:]) < 6.0


@pytest.mark.parametrize("form", [FullpercReference, FullpercFilter])
def test_mu_is_not_learnt_from_the_omc_alone_and_returns_to_1_with_distance(form, stream):
    """After the Vega has lost the tool: held still, mu stays what it was (the distance from where the Vega lost it
    grows only by the estimate's jitter); moved 0.3 m (5.3 L), it is back at 1 within 1 %. With the OMC alone from
    the start it never leaves 1, however quiet the OMC is."""
    still, _ = _run(form(), stream(5, 1500, 0.3, local_until=900, speed=0.0)[0])
    assert still[899] < 0.3 and abs(still[-1] - still[899]) < 0.02   # the estimate's jitter at rest: < 1 mm
    moving, _ = _run(form(), stream(5, 1500, 0.3, local_until=900, speed=0.06)[0])
    assert moving[899] < 0.3 and abs(moving[-1] - 1.0) < 0.01
    alone, _ = _run(form(), stream(6, 600, 0.1, local_until=0)[0])
    assert np.all(alone == 1.0)


@pytest.mark.parametrize("form", [FullpercReference, FullpercFilter])
def test_mu_starts_at_1_after_a_reinitialisation_and_is_in_the_snapshot(form, stream):
    items, _ = stream(7, 900, 0.3, speed=0.0)
    f = form()
    _run(f, items)
    mu = _state(f).rot_scale
    assert mu < 0.2
    snap = f.snapshot()
    last = items[-1][0]
    f.update(Measurement(last.t_ns + 2 * S, SOURCE_GLOBAL, last.p, last.q, last.cov))   # a gap: re-initialised
    assert _state(f).rot_scale == 1.0 and _state(f).t_rot_scale_ns is None
    f.restore(snap)
    assert _state(f).rot_scale == mu


def test_mu_bounds_are_validated():
    for bad in ({"rot_noise_adapt_min": 0.0}, {"rot_noise_adapt_min": 1.5}, {"rot_noise_adapt_max": 0.9},
                {"rot_noise_adapt_max": float("inf")}, {"rot_noise_adapt_time": -1.0}, {"rot_noise_length": -0.1}):
        with pytest.raises(ValueError, match="rot_noise"):
            FullpercParams(**bad).validate()
