"""The paper's KF / BKF / CKF / CBKF step in closed form per axis, on Python floats: the one copy of that arithmetic.

Who uses it. :class:`~.paper_fast.ClosedFormFilter` (one sample at a time: the live node and the pipeline) and
:func:`~.paper_batch.run_closed_form` (a whole replay in one loop: the offline evaluator's hot loop) both step the
filter through these functions, so the two cannot drift apart: the batched replay is bit-identical to the
per-sample filter by construction (test_batch_filter.py compares every figure exactly). The general matrix form,
:class:`~.paper_family.FusionFilter`, stays the reference that this closed form is tested against
(test_fast_filter.py: 1e-12 over thousands of random steps); it is written independently on purpose.

Why it is separable. Write the general state as x = [p v b] with each block (x, y, z). F, Q and the measurement
rows of eq. (9)-(11) are Kronecker products with I3 -- per axis F = [[1, dt, 0], [0, 1, 0], [0, 0, 1]],
Q = [[q dt^3/3, q dt^2/2, 0], [q dt^2/2, q dt, 0], [0, 0, q_b dt]], h_global = [1, -lag, 1], h_local =
[1, -lag, 0] (``paper_family.measurement_matrix``: -lag in the velocity block, lag = filter time - sample stamp;
without the bias state the last column is dropped). So if the covariance P has no entry coupling two different
axes, and R has none either, every step keeps that structure and the 9x9 (6x6) filter is three independent 3x3
(2x2) filters, one per axis, each with its own 3x3 covariance:

* prediction, gain and update act on each axis alone (S is block-diagonal over axes);
* NIS = y^T S^-1 y and the hop test's NIS_g are sums of per-axis terms;
* the hop inflation adds y_g,i^2 to the bias variance of axis i only (diagonal);
* the biased estimator M = diag(m_i) of eq. (7) is per state, so m_i uses axis i's own x_i and P_ii, and
  P = M P M^T scales entries without coupling axes.

The three covariances are not equal in general (M and the hop inflation differ per axis, R may be anisotropic),
so one is kept per axis. Whether the closed form applies (diagonal R, no cross-axis entry in P) is the caller's
decision (:mod:`.paper_fast`); these functions assume it.

The state: ``X`` the general state vector as a list [px py pz vx vy vz (bx by bz)], ``C`` one per-axis covariance
[pp, pv, pb, vv, vb, bb] per axis (pb = vb = bb = 0 without the bias state). :func:`predict_axes` writes ``X`` and
the slots of ``C`` in place and replaces the per-axis lists (never mutates them); :func:`init_axes` and
:func:`update_axes` return new lists and leave their input alone -- so a copy of the outer lists is a snapshot
(``ClosedFormFilter.snapshot``) and a refused update leaves the state as predicted.

A pair is updated through S = L D L^T (the sequential global-then-local form): it agrees with the general form's
LU solve ~100x more closely than the explicit 2x2 inverse did. The posterior covariance is P - U S^-1 U^T
(U = P H^T), which equals the general form's Joseph form for the optimal gain.

Why plain floats and plain functions: at 3x3, numpy's per-call overhead (~1 us per ufunc/matmul) dominates -- the
per-axis CBKF predict + global update took a median 14 us in Python floats and 96 us written with (3,)-arrays over
the axes -- and scalars instead of small lists in the update are a third less again. The form of a filter
(:class:`AxisForm`) is a tuple, unpacked once per call. For the same reason :func:`update_axes` is one pass per
axis: innovation, S, gain and posterior at once, speculatively as if there were no hop (a hop that inflates the bias
variance redoes the pass), and with ``dt`` the prediction in the same pass -- the batched replay's step;
:func:`predict_axes` is that pass without a sample, so the arithmetic stays one copy. Against the former two passes
with a tuple per axis between them and a separate predict loop, over the 13 352 steps of the four filters on
bags/paper/G-B-P (minimum of 30 runs, interleaved): the update alone 63 -> 50 ms (-20 %), predict + update
77 -> 57 ms (-25 %), the whole batched replay (:func:`~.paper_batch.run_closed_form`) 88 -> 65 ms; a per-sample
predict costs ~0.8 us more (the update's set-up), which its faster update makes up. Every float is the same. (The
axes are iterated over a tuple of their indices: ~5 % faster than ``range(3)`` and ``3 + a`` on CPython 3.11.)
"""

from __future__ import annotations

import math
from typing import NamedTuple

from fullperc_fusion.filters.paper_family import FilterParams

__all__ = ["AxisForm", "axis_form", "biased_factor", "init_axes", "initial_axes", "predict_axes", "update_axes"]


class AxisForm(NamedTuple):
    """One filter kind with its parameters, as the kernel reads them (:func:`axis_form`)."""

    has_bias: bool                 # ckf, cbkf: the state has the global source's bias b
    biased: bool                   # bkf, cbkf: the biased estimator M of eq. (7)
    prior: bool                    # eq. (14) on the predicted P (``eq14_covariance='prior'``), biased kinds only
    shrink_p: bool                 # M acts on p / v / b (``shrink_blocks``; b only with the bias state)
    shrink_v: bool
    shrink_b: bool
    accel_noise: float             # q_a
    bias_walk: float               # q_b
    global_var: tuple[float, float, float]   # the fixed noise per axis, global_std^2 / local_std^2
    local_var: tuple[float, float, float]
    init_pos_var: float            # prior variances of a (re-)initialisation
    init_vel_var: float
    init_bias_var: float           # 0 without the bias state
    hop_gate: float
    inflate: bool                  # a hop raises the bias variance (``hop_to_bias`` with the bias state)
    max_gap_s: float


def axis_form(kind: str, params: FilterParams) -> AxisForm:
    """The :class:`AxisForm` of ``kind`` (one of ``FILTER_KINDS``) with ``params`` (as FusionFilter reads them)."""
    has_bias = kind in ("ckf", "cbkf")
    biased = kind in ("bkf", "cbkf")
    blocks = set(params.shrink_blocks)
    return AxisForm(has_bias, biased, params.eq14_covariance == "prior" and biased, "p" in blocks, "v" in blocks,
                    "b" in blocks and has_bias, params.accel_noise, params.bias_walk, (params.global_std**2,) * 3,
                    (params.local_std**2,) * 3, params.init_pos_std**2, params.init_vel_std**2,
                    params.init_bias_std**2 if has_bias else 0.0, params.hop_gate, params.hop_to_bias and has_bias,
                    params.max_gap_s)


def biased_factor(x: float, var: float) -> float:
    """m = x^2 / (var + x^2) of eq. (7) for one state (the cases of ``paper_family.biased_factors``)."""
    if var <= 0:
        return 1.0
    x2 = x * x
    den = var + x2
    return x2 / den if den > 0 else 1.0


def initial_axes(form: AxisForm) -> tuple[list[float], list[list[float]]]:
    """(X, C) of a filter that has no state yet: x = 0, P = I (FusionFilter.reset)."""
    bb = 1.0 if form.has_bias else 0.0
    return [0.0] * (9 if form.has_bias else 6), [[1.0, 0.0, 0.0, 1.0, 0.0, bb] for _ in range(3)]


def predict_axes(form: AxisForm, X: list[float], C: list[list[float]], dt: float) -> None:
    """Eq. (9)-(10) per axis over ``dt`` [s], in place: p += dt v, P = F P F^T + Q -- :func:`update_axes`'s
    prediction without a sample (the batched replay has it predict and update in one pass)."""
    X[:], C[:] = update_axes(form, X, C, 0, None, None, None, None, None, None, False, dt)[0:2]


def init_axes(form: AxisForm, X: list[float], C: list[list[float]], dt: float | None, zg, zl
              ) -> tuple[list[float], list[list[float]]]:
    """(X, C) of a (re-)initialisation (FusionFilter's rule): p from the local sample ``zl``, else from the global
    one ``zg`` minus the bias; v = 0 with the prior variances. ``dt`` [s] since the state's stamp, None when there is
    no state yet: with a state the bias and its variance are kept (propagated over dt by the random walk), without
    one they start at 0 and ``init_bias_std^2``."""
    has_bias = form.has_bias
    keep = dt is not None and has_bias
    b = X[6:9] if keep else [0.0, 0.0, 0.0]
    bb = [c[5] + form.bias_walk * dt for c in C] if keep else [form.init_bias_var] * 3
    p = list(zl) if zl is not None else [zg[0] - b[0], zg[1] - b[1], zg[2] - b[2]]
    vp, vv = form.init_pos_var, form.init_vel_var
    return p + [0.0, 0.0, 0.0] + (b if has_bias else []), [[vp, 0.0, 0.0, vv, 0.0, bb[a]] for a in range(3)]


def update_axes(form: AxisForm, X: list[float], C: list[list[float]], t: int, tg: int | None, zg, rg,
                tl: int | None, zl, rl, full: bool = True, dt: float | None = None) -> tuple:
    """Eq. (11)-(14) per axis at filter time ``t`` [ns]: the global sample (stamp ``tg``, position ``zg``, variance
    per axis ``rg``) and/or the local one (``tl``, ``zl``, ``rl``); None where absent. With ``dt`` [s] the state is
    first predicted over it, eq. (9)-(10) (:func:`predict_axes` is this without a sample).

    Returns ``(X, C, hop, nis, nis_global, innovation, m)``: the new state (new lists), the hop flag, the NIS of the
    whole update and of the global rows, the innovation per axis (global rows if any, else local) and M's diagonal
    (None for the unbiased kinds). ``full=False`` skips what only a :class:`~.api.Step` reports -- NIS, innovation
    and M are then 0.0, None and None; the state, the hop flag and NIS_global (the hop test's) are the same -- for
    the batched replay, which reports none of them (they would add ~5 % to its time). ValueError for a sample older
    than ``max_gap_s``, FloatingPointError for a non-finite result (not for a prediction alone); the input state is
    left as it was either way.
    """
    (has_bias, biased, prior, sp, sv, sb, qa, q_b, _, _, _, _, _, gate, inflate_hops, max_gap) = form
    if dt is not None:   # the process noise of the prediction
        q_pp, q_pv, q_vv = qa * dt**3 / 3, qa * dt**2 / 2, qa * dt
        q_bb = q_b * dt if has_bias else 0.0
    has_g, has_l = zg is not None, zl is not None
    lg = ll = 0.0
    if has_g:
        lg = (t - tg) * 1e-9
        if lg > max_gap:
            raise ValueError(f"measurement {lg:.3f} s older than the filter time (max_gap_s {max_gap})")
    if has_l:
        ll = (t - tl) * 1e-9
        if ll > max_gap:
            raise ValueError(f"measurement {ll:.3f} s older than the filter time (max_gap_s {max_gap})")
    hb = 1.0 if has_bias else 0.0
    both = has_g and has_l
    nx = len(X)
    nis = 0.0
    innov = m = None
    if full:
        innov = [0.0, 0.0, 0.0]
        if biased:
            m = [1.0] * nx
    # One pass per axis: (the prediction,) the innovation, U = P h^T and S, and at once the gain and the update --
    # speculatively, as if there were no hop: the hop test needs the global NIS of all three axes. A hop that
    # inflates the bias variance (rare: a jump of the global source) redoes the pass with the inflated terms
    # (``inflating``); NIS, innovation and the hop test stay the first pass's, as the inflation comes after them.
    # ``probe`` is the hop test alone: if the speculative update divided by zero, only a hop's inflated terms can
    # make the update valid -- else that error is the result, as it was when the update came after the test.
    probe = inflating = False
    report = full   # the NIS and the innovation, from the first pass
    err = None
    while True:
        nis_g = total = 0.0
        Xn = [0.0] * nx
        Cn: list = [None, None, None]   # per axis, filled in order
        try:
            for a, va, ba in ((0, 3, 6), (1, 4, 7), (2, 5, 8)):   # axis a: the index of its p, v and b in X
                c0, c1, c2, c3, c4, c5 = C[a]
                p, v = X[a], X[va]
                if dt is not None:   # predict: p += dt v, P = F P F^T + Q
                    p = p + dt * v
                    pvdt = c1 + dt * c3
                    c0, c1, c2 = c0 + dt * c1 + dt * pvdt + q_pp, pvdt + q_pv, c2 + dt * c4
                    c3, c5 = c3 + q_vv, c5 + q_bb
                if has_g:   # the global row (u, s, y: its U, S and innovation), then the local one (ul, sll, yl)
                    b = X[ba] if has_bias else 0.0
                    u0, u1, u2 = c0 - lg * c1 + hb * c2, c1 - lg * c3 + hb * c4, c2 - lg * c4 + hb * c5
                    s = u0 - lg * u1 + hb * u2 + rg[a]
                    y = zg[a] - (p - lg * v + hb * b)
                    q = y * y / s
                    nis_g += q
                    if probe:
                        continue
                    if inflating:   # a hop: y^2 onto the bias variance, so onto u2 and s as well
                        d = y * y
                        c5, u2, s = c5 + d, u2 + d, s + d
                    elif report:
                        innov[a] = y
                        if not has_l:
                            nis += q
                    if has_l:
                        ul0, ul1, ul2 = c0 - ll * c1, c1 - ll * c3, c2 - ll * c4
                        sll = ul0 - ll * ul1 + rl[a]
                        yl = zl[a] - (p - ll * v)
                        sgl = ul0 - lg * ul1 + hb * ul2
                elif has_l:
                    u0, u1, u2 = c0 - ll * c1, c1 - ll * c3, c2 - ll * c4
                    s = u0 - ll * u1 + rl[a]
                    y = zl[a] - (p - ll * v)
                    if report:
                        innov[a] = y
                        nis += y * y / s
                else:   # no sample: the prediction is the result (predict_axes; no finiteness test, as before)
                    Xn[a], Xn[va] = p, v
                    if has_bias:
                        Xn[ba] = X[ba]
                    Cn[a] = [c0, c1, c2, c3, c4, c5]
                    continue
                # gain and update, eq. (12)-(13); the bias column only with the bias state (else it is all 0)
                if both:
                    # U S^-1 U^T and U S^-1 y through S = L D L^T, L = [[1, 0], [lgl, 1]]: W = U L^-T =
                    # [u, ul - lgl u], D = diag(s, d2); its NIS is y^T S^-1 y = y^2 / s + e^2 / d2
                    lgl = sgl / s
                    d2 = sll - lgl * sgl
                    e = yl - lgl * y
                    if report:
                        nis += q + e * e / d2
                    w0, w1 = ul0 - lgl * u0, ul1 - lgl * u1
                    kg0, kg1 = u0 / s, u1 / s
                    kl0, kl1 = w0 / d2, w1 / d2
                    dx0, dx1 = kg0 * y + kl0 * e, kg1 * y + kl1 * e
                    n0, n1, n3 = c0 - (kg0 * u0 + kl0 * w0), c1 - (kg0 * u1 + kl0 * w1), c3 - (kg1 * u1 + kl1 * w1)
                    if has_bias:
                        w2 = ul2 - lgl * u2
                        kg2, kl2 = u2 / s, w2 / d2
                        dx2 = kg2 * y + kl2 * e
                        n2, n4 = c2 - (kg0 * u2 + kl0 * w2), c4 - (kg1 * u2 + kl1 * w2)
                        n5 = c5 - (kg2 * u2 + kl2 * w2)
                else:
                    k0, k1 = u0 / s, u1 / s
                    dx0, dx1 = k0 * y, k1 * y
                    n0, n1, n3 = c0 - k0 * u0, c1 - k0 * u1, c3 - k1 * u1
                    if has_bias:
                        k2 = u2 / s
                        dx2 = k2 * y
                        n2, n4, n5 = c2 - k0 * u2, c4 - k1 * u2, c5 - k2 * u2
                xp, xv = p + dx0, v + dx1
                if has_bias:
                    xb = X[ba] + dx2
                if biased:
                    # eq. (14): x = M x'', P = M P M^T (on the posterior P, or the prior with eq14_covariance='prior')
                    mp = biased_factor(xp, n0) if sp else 1.0
                    mv = biased_factor(xv, n3) if sv else 1.0
                    if prior:
                        n0, n1, n3 = c0, c1, c3
                    n0, n1, n3 = n0 * (mp * mp), n1 * (mp * mv), n3 * (mv * mv)
                    xp, xv = mp * xp, mv * xv
                    if has_bias:
                        mb = biased_factor(xb, n5) if sb else 1.0
                        if prior:
                            n2, n4, n5 = c2, c4, c5
                        n2, n4, n5 = n2 * (mp * mb), n4 * (mv * mb), n5 * (mb * mb)
                        xb = mb * xb
                    if m is not None:
                        m[a], m[va] = mp, mv
                        if has_bias:
                            m[ba] = mb
                Xn[a], Xn[va] = xp, xv
                if has_bias:
                    Xn[ba] = xb
                    Cn[a] = [n0, n1, n2, n3, n4, n5]
                    total += xp + xv + xb + n0 + n1 + n2 + n3 + n4 + n5
                else:
                    Cn[a] = [n0, n1, 0.0, n3, 0.0, 0.0]
                    total += xp + xv + n0 + n1 + n3
        except ZeroDivisionError as exc:
            if full or probe or inflating or not (has_g and inflate_hops):   # (full: its NIS divides by the same)
                raise
            probe, err = True, exc
            continue
        hop = has_g and nis_g > gate
        if probe and not (hop and inflate_hops):
            raise err
        if inflating or not (hop and inflate_hops):
            break
        probe, inflating, report = False, True, False
    # a finite sum means every entry is finite (cheap test first; the exact one only if it is not)
    if not math.isfinite(total) and not (all(math.isfinite(v) for v in Xn)
                                         and all(math.isfinite(v) for c in Cn for v in c)):
        raise FloatingPointError("filter produced a non-finite state")
    return Xn, Cn, hop, nis, nis_g, innov, m
