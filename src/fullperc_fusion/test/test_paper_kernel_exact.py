"""The paper filters' closed-form kernel (:mod:`fullperc_fusion.filters.paper_kernel`) held bit for bit to plain
loops: its update (one pass per axis, a hop redoing it) on every kind, source mix and a hop; its prediction, alone
and fused with the update (the batched replay's step); and the hop that redoes an update which divided by zero.
Each reference below is the arithmetic written out the plain way, so a change of the kernel's order of operations
shows as a changed float (``repr``), not as a tolerance.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams
from fullperc_fusion.filters.paper_kernel import axis_form, predict_axes, update_axes

sys.path.insert(0, str(Path(__file__).parent))
from test_batch_filter import _kernel_samples, _state  # noqa: E402  (same directory: random kernel inputs)


def _reference_update(form, X, C, t, tg, zg, rg, tl, zl, rl):
    """The update as one loop over the axes with the per-axis tests of which samples there are (the kernel's form
    before the loops were split by source combination): the same arithmetic, written the plain way."""
    (has_bias, biased, prior, sp, sv, sb, *_, gate, inflate_hops, max_gap) = form
    has_g, has_l = zg is not None, zl is not None
    lg = (t - tg) * 1e-9 if has_g else 0.0
    ll = (t - tl) * 1e-9 if has_l else 0.0
    hb = 1.0 if has_bias else 0.0
    ax, nis_g = [], 0.0
    ug0 = ug1 = ug2 = sgg = yg = ul0 = ul1 = ul2 = sll = yl = sgl = 0.0
    for a in range(3):
        pp, pv, pb, vv, vb, bb = C[a]
        p, v = X[a], X[3 + a]
        b = X[6 + a] if has_bias else 0.0
        if has_g:
            ug0, ug1, ug2 = pp - lg * pv + hb * pb, pv - lg * vv + hb * vb, pb - lg * vb + hb * bb
            sgg = ug0 - lg * ug1 + hb * ug2 + rg[a]
            yg = zg[a] - (p - lg * v + hb * b)
            nis_g += yg * yg / sgg
        if has_l:
            ul0, ul1, ul2 = pp - ll * pv, pv - ll * vv, pb - ll * vb
            sll = ul0 - ll * ul1 + rl[a]
            yl = zl[a] - (p - ll * v)
            if has_g:
                sgl = ul0 - lg * ul1 + hb * ul2
        ax.append((ug0, ug1, ug2, sgg, yg, ul0, ul1, ul2, sll, yl, sgl))
    hop = has_g and nis_g > gate
    inflate = hop and inflate_hops
    Xn, Cn = [0.0] * len(X), []
    for a in range(3):
        ug0, ug1, ug2, sgg, yg, ul0, ul1, ul2, sll, yl, sgl = ax[a]
        c0, c1, c2, c3, c4, c5 = C[a]
        if inflate:
            d = yg * yg
            c5, ug2, sgg = c5 + d, ug2 + d, sgg + d
        if has_g and has_l:
            lgl = sgl / sgg
            d2 = sll - lgl * sgl
            e = yl - lgl * yg
            w0, w1, w2 = ul0 - lgl * ug0, ul1 - lgl * ug1, ul2 - lgl * ug2
            kg0, kg1, kg2 = ug0 / sgg, ug1 / sgg, ug2 / sgg
            kl0, kl1, kl2 = w0 / d2, w1 / d2, w2 / d2
            dx0, dx1, dx2 = kg0 * yg + kl0 * e, kg1 * yg + kl1 * e, kg2 * yg + kl2 * e
            n0, n1 = c0 - (kg0 * ug0 + kl0 * w0), c1 - (kg0 * ug1 + kl0 * w1)
            n2, n3 = c2 - (kg0 * ug2 + kl0 * w2), c3 - (kg1 * ug1 + kl1 * w1)
            n4, n5 = c4 - (kg1 * ug2 + kl1 * w2), c5 - (kg2 * ug2 + kl2 * w2)
        else:
            u0, u1, u2, s, y = (ug0, ug1, ug2, sgg, yg) if has_g else (ul0, ul1, ul2, sll, yl)
            k0, k1, k2 = u0 / s, u1 / s, u2 / s
            dx0, dx1, dx2 = k0 * y, k1 * y, k2 * y
            n0, n1, n2 = c0 - k0 * u0, c1 - k0 * u1, c2 - k0 * u2
            n3, n4, n5 = c3 - k1 * u1, c4 - k1 * u2, c5 - k2 * u2
        xp, xv = X[a] + dx0, X[3 + a] + dx1
        xb = X[6 + a] + dx2 if has_bias else 0.0
        if biased:
            def bf(x, var):
                return 1.0 if var <= 0 else (x * x / (var + x * x) if var + x * x > 0 else 1.0)
            mp, mv, mb = bf(xp, n0) if sp else 1.0, bf(xv, n3) if sv else 1.0, bf(xb, n5) if sb else 1.0
            b0, b1, b2, b3, b4, b5 = (c0, c1, c2, c3, c4, c5) if prior else (n0, n1, n2, n3, n4, n5)
            n0, n1, n2 = b0 * (mp * mp), b1 * (mp * mv), b2 * (mp * mb)
            n3, n4, n5 = b3 * (mv * mv), b4 * (mv * mb), b5 * (mb * mb)
            xp, xv, xb = mp * xp, mv * xv, mb * xb
        if not has_bias:
            n2 = n4 = n5 = 0.0
        Xn[a], Xn[3 + a] = xp, xv
        if has_bias:
            Xn[6 + a] = xb
        Cn.append([n0, n1, n2, n3, n4, n5])
    return Xn, Cn, hop, nis_g


def _reference_predict(form, X, C, dt):
    """Eq. (9)-(10) as the plain loop over the axes (predict_axes before it became update_axes without a sample),
    on copies."""
    qa = form.accel_noise
    q_pp, q_pv, q_vv = qa * dt**3 / 3, qa * dt**2 / 2, qa * dt
    q_bb = form.bias_walk * dt if form.has_bias else 0.0
    X, C = list(X), list(C)
    for a in range(3):
        X[a] = X[a] + dt * X[3 + a]
        pp, pv, pb, vv, vb, bb = C[a]
        pvdt = pv + dt * vv
        C[a] = [pp + dt * pv + dt * pvdt + q_pp, pvdt + q_pv, pb + dt * vb, vv + q_vv, vb, bb + q_bb]
    return X, C


@pytest.mark.parametrize("kind", FILTER_KINDS)
@pytest.mark.parametrize("params", [FilterParams(hop_gate=3.0),
                                    FilterParams(hop_gate=3.0, shrink_blocks=("p", "v", "b"), eq14_covariance="prior")])
def test_kernel_update_equals_the_plain_loop(kind, params):
    rng = np.random.default_rng(9)
    form = axis_form(kind, params)
    t = 10 * 10**9
    hops = 0
    for k in range(600):
        X, C = _state(rng, form.has_bias)
        tg, zg, tl, zl = _kernel_samples(rng, X, k, t)
        got = update_axes(form, X, C, t, tg, zg, form.global_var, tl, zl, form.local_var)
        want = _reference_update(form, X, C, t, tg, zg, form.global_var, tl, zl, form.local_var)
        assert repr((got[0], got[1], got[2], got[4])) == repr(want)
        hops += got[2]
    assert hops > 0


@pytest.mark.parametrize("kind", FILTER_KINDS)
def test_kernel_predict_and_the_fused_step_equal_the_plain_loops(kind):
    """predict_axes (update_axes without a sample) is the plain predict; update_axes(..., dt) -- the batched
    replay's predict and update in one pass -- is the plain predict then the plain update, and reports (NIS,
    innovation, M) what predict_axes then update_axes report."""
    rng = np.random.default_rng(10)
    form = axis_form(kind, FilterParams(hop_gate=3.0))
    t = 10 * 10**9
    hops = 0
    for k in range(600):
        X, C = _state(rng, form.has_bias)
        dt = float(rng.uniform(0.0, 0.02)) if k % 5 else 0.0
        Xp, Cp = _reference_predict(form, X, C, dt)
        X1, C1 = list(X), list(C)
        predict_axes(form, X1, C1, dt)
        assert repr((X1, C1)) == repr((Xp, Cp))
        tg, zg, tl, zl = _kernel_samples(rng, X, k, t)
        got = update_axes(form, X, C, t, tg, zg, form.global_var, tl, zl, form.local_var, True, dt)
        want = _reference_update(form, Xp, Cp, t, tg, zg, form.global_var, tl, zl, form.local_var)
        assert repr((got[0], got[1], got[2], got[4])) == repr(want)
        assert repr(got) == repr(update_axes(form, X1, C1, t, tg, zg, form.global_var, tl, zl, form.local_var))
        lean = update_axes(form, X, C, t, tg, zg, form.global_var, tl, zl, form.local_var, False, dt)
        assert repr(lean[0:3] + lean[4:5]) == repr(got[0:3] + got[4:5])
        hops += got[2]
    assert hops > 0


@pytest.mark.parametrize("kind", ["ckf", "cbkf"])
def test_kernel_hop_redoes_an_update_that_divided_by_zero(kind):
    """A pair whose S is singular until a hop inflates it (no noise, no lag): the speculative update (as if there
    were no hop) divides by zero; with a hop the result is the inflated update, the plain loop's; without one, or
    with the full report (its NIS divides by the uninflated terms), the ZeroDivisionError stands, as before."""
    t, r0 = 10 * 10**9, (0.0, 0.0, 0.0)
    X, C = [0.1, 0.2, 0.3] + [0.0] * 6, [[1e-4, 0.0, 0.0, 1e-2, 0.0, 0.0] for _ in range(3)]
    zg, zl = [0.2, 0.3, 0.4], [0.1, 0.2, 0.3]
    form = axis_form(kind, FilterParams(hop_gate=0.5))
    got = update_axes(form, X, C, t, t, zg, r0, t, zl, r0, False)
    assert got[2] and repr((got[0], got[1], got[2], got[4])) == repr(_reference_update(form, X, C, t, t, zg, r0,
                                                                                          t, zl, r0))
    with pytest.raises(ZeroDivisionError):
        update_axes(form, X, C, t, t, zg, r0, t, zl, r0)
    with pytest.raises(ZeroDivisionError):
        update_axes(axis_form(kind, FilterParams(hop_gate=1e9)), X, C, t, t, zg, r0, t, zl, r0, False)
