"""The paper's KF / BKF / CKF / CBKF over a whole recording at once: one loop, no per-sample objects.

Why: offline evaluation (issue 16 item 6) runs the four filters over thousands of synchronised items. Through
:class:`~fast_filter.ClosedFormFilter` each item costs a :class:`~filter_api.Measurement` per source, a
:class:`~filter_api.Step`, numpy arrays for its fields and the filter protocol's calls -- several times the
arithmetic itself. :func:`run_closed_form` takes the items as plain lists (stamps and positions in ``base``) and
advances every requested filter in one Python loop on floats, writing the results into preallocated arrays.

Equality, not similarity: the arithmetic is :class:`~fast_filter.ClosedFormFilter`'s, operation for operation
and in the same order (predict, the time rule of :func:`~filter_api.predict_interval`, (re-)initialisation after a
gap, the stacked update through S = L D L^T, the hop inflation, the biased estimator), so the estimates are
bit-identical to the per-sample filters (test_batch_filter.py checks it against ``ClosedFormFilter`` and the
evaluator's test against the whole pipeline). Only what the closed form serves is supported: fixed isotropic
noise (no measurement covariance) -- anything else raises :class:`BatchUnsupported` and the caller runs the
per-sample filters instead, as it does when a step would raise there (time going backwards, a sample older than
``max_gap_s``, a non-finite state).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams
from fullperc_fusion.filters.paper_fast import biased_factor

__all__ = ["BatchOutput", "BatchUnsupported", "run_closed_form"]


class BatchUnsupported(Exception):
    """The batched filters cannot reproduce the per-sample result here; the message says why (caller falls back)."""


@dataclass
class BatchOutput:
    """One filter's output per item (every item gives one: the paper's filters output on each)."""

    p: np.ndarray          # (N, 3) position [m]
    bias: np.ndarray       # (N, 3) global-source bias [m] (zeros without a bias state)
    pos_var: np.ndarray    # (N, 3) variance of each position axis [m^2] (the diagonal of Step.pos_cov)
    hop: np.ndarray        # (N,) bool
    sources: np.ndarray    # (N,) int: SOURCE_GLOBAL | SOURCE_LOCAL bits
    reset: np.ndarray      # (N,) bool: the item (re-)initialised the state


class _State:
    """One filter's closed-form state (ClosedFormFilter's ``_X``, ``_C``, ``t_ns``, ``_pending_ns``)."""

    __slots__ = ("C", "X", "biased", "has_bias", "kind", "out", "pending", "prior", "shrink", "t")

    def __init__(self, kind: str, params: FilterParams, n_items: int) -> None:
        self.kind = kind
        self.has_bias = kind in ("ckf", "cbkf")
        self.biased = kind in ("bkf", "cbkf")
        blocks = set(params.shrink_blocks)
        self.shrink = ("p" in blocks, "v" in blocks, "b" in blocks and self.has_bias)
        self.prior = params.eq14_covariance == "prior" and self.biased
        self.X = [0.0] * (9 if self.has_bias else 6)
        self.C = [[1.0, 0.0, 0.0, 1.0, 0.0, 1.0 if self.has_bias else 0.0] for _ in range(3)]
        self.t: int | None = None
        self.pending: int | None = None
        self.out = BatchOutput(np.zeros((n_items, 3)), np.zeros((n_items, 3)), np.zeros((n_items, 3)),
                               np.zeros(n_items, bool), np.zeros(n_items, np.int64), np.zeros(n_items, bool))


def run_closed_form(kinds: tuple[str, ...] | list[str], params: FilterParams, t_item: list[int],
                    g_t: list[int | None], g_p: list[list[float] | None],
                    l_t: list[int | None], l_p: list[list[float] | None]) -> dict[str, BatchOutput]:
    """Every filter of ``kinds`` (each one of FILTER_KINDS) over the items, as the pipeline steps them.

    Item i has processing stamp ``t_item[i]`` (the newer of its samples) and a global sample (stamp ``g_t[i]``,
    position ``g_p[i]`` in base) and/or a local one (``l_t``, ``l_p``); None where absent. The pipeline calls
    ``predict(t_item)`` then ``update(global, local)`` on a fresh filter per kind: so does this, in closed form.
    """
    for k in kinds:
        if k not in FILTER_KINDS:
            raise BatchUnsupported(f"filter '{k}' has no batched form")
    n_items = len(t_item)
    states = [_State(k, params, n_items) for k in kinds]
    pr = params
    qa, qb, max_gap = pr.accel_noise, pr.bias_walk, pr.max_gap_s
    rg0, rl0 = pr.global_std**2, pr.local_std**2
    vp, vv0 = pr.init_pos_std**2, pr.init_vel_std**2
    bb_init = pr.init_bias_std**2
    gate, hop_to_bias = pr.hop_gate, pr.hop_to_bias
    for i in range(n_items):
        t_i = t_item[i]
        tg, tl = g_t[i], l_t[i]
        zg, zl = g_p[i], l_p[i]
        has_g, has_l = tg is not None, tl is not None
        src = (SOURCE_GLOBAL if has_g else 0) | (SOURCE_LOCAL if has_l else 0)
        for s in states:
            # ---- predict(t_i): filter_api.predict_interval, then ClosedFormFilter.predict
            now = s.pending if s.pending is not None else s.t
            if now is None:
                s.pending = t_i
            else:
                if t_i < now:
                    raise BatchUnsupported(f"filter {s.kind}: time went backwards at item {i}")
                if s.pending is not None:
                    s.pending = t_i
                else:
                    dt = (t_i - s.t) * 1e-9
                    if dt > max_gap:
                        s.pending = t_i
                    else:
                        q_pp, q_pv, q_vv = qa * dt**3 / 3, qa * dt**2 / 2, qa * dt
                        q_bb = qb * dt if s.has_bias else 0.0
                        X, C = s.X, s.C
                        for a in range(3):
                            X[a] = X[a] + dt * X[3 + a]
                            pp, pv, pb, vv, vb, bb = C[a]
                            pvdt = pv + dt * vv
                            C[a] = [pp + dt * pv + dt * pvdt + q_pp, pvdt + q_pv, pb + dt * vb, vv + q_vv, vb,
                                    bb + q_bb]
                        s.t = t_i
            # ---- update: the filter's time is t_i now (predicted or pending), so no second predict
            out = s.out
            out.sources[i] = src
            if s.pending is not None:
                _init_state(s, t_i, zg, zl, has_bias=s.has_bias, bias_walk=qb, vp=vp, vv=vv0, bb0=bb_init)
                X = s.X
                out.p[i] = X[0:3]
                if s.has_bias:
                    out.bias[i] = X[6:9]
                out.pos_var[i] = vp
                out.reset[i] = True
                continue
            lg = (t_i - tg) * 1e-9 if has_g else 0.0
            ll = (t_i - tl) * 1e-9 if has_l else 0.0
            if lg > max_gap or ll > max_gap:
                raise BatchUnsupported(f"filter {s.kind}: measurement older than max_gap_s at item {i}")
            hop = _update_axes(s, t_i, zg if has_g else None, zl if has_l else None, lg, ll, rg0, rl0, gate,
                               hop_to_bias)
            X = s.X
            out.p[i] = X[0:3]
            if s.has_bias:
                out.bias[i] = X[6:9]
            C = s.C
            out.pos_var[i] = (C[0][0], C[1][0], C[2][0])
            out.hop[i] = hop
    return {s.kind: s.out for s in states}


def _init_state(s: _State, t: int, zg, zl, *, has_bias: bool, bias_walk: float, vp: float, vv: float,
                bb0: float) -> None:
    """ClosedFormFilter._init_state: p from the local sample, else the global one minus the kept bias."""
    keep = s.t is not None and has_bias
    dt = (t - s.t) * 1e-9 if s.t is not None else 0.0
    b = s.X[6:9] if keep else [0.0, 0.0, 0.0]
    bb0 = bb0 if has_bias else 0.0
    bb = [c[5] + bias_walk * dt for c in s.C] if keep else [bb0] * 3
    p = list(zl) if zl is not None else [zg[a] - b[a] for a in range(3)]
    s.X = p + [0.0, 0.0, 0.0] + (list(b) if has_bias else [])
    s.C = [[vp, 0.0, 0.0, vv, 0.0, bb[a]] for a in range(3)]
    s.t = int(t)
    s.pending = None


def _update_axes(s: _State, t: int, zg, zl, lg: float, ll: float, rg: float, rl: float, gate: float,
                 hop_to_bias: bool) -> bool:
    """ClosedFormFilter._update_axes with fixed noise (R = std^2 I), on scalars instead of small lists (the lists
    were a third of the loop's time); returns the hop flag. Same operations in the same order (module docstring):
    change one only together with fast_filter.py."""
    hb = 1.0 if s.has_bias else 0.0
    X, C = s.X, s.C
    has_g, has_l = zg is not None, zl is not None
    # pass 1: innovations, U = P h^T, S per axis; the global NIS decides the hop before any gain
    ax = []
    nis_g = 0.0
    ug0 = ug1 = ug2 = sgg = yg = ul0 = ul1 = ul2 = sll = yl = sgl = 0.0
    for a in range(3):
        pp, pv, pb, vv, vb, bb = C[a]
        p, v = X[a], X[3 + a]
        b = X[6 + a] if hb else 0.0
        if has_g:
            ug0, ug1, ug2 = pp - lg * pv + hb * pb, pv - lg * vv + hb * vb, pb - lg * vb + hb * bb
            sgg = ug0 - lg * ug1 + hb * ug2 + rg
            yg = zg[a] - (p - lg * v + hb * b)
            nis_g += yg * yg / sgg
        if has_l:
            ul0, ul1, ul2 = pp - ll * pv, pv - ll * vv, pb - ll * vb
            sll = ul0 - ll * ul1 + rl
            yl = zl[a] - (p - ll * v)
            if has_g:
                sgl = ul0 - lg * ul1 + hb * ul2
        ax.append((ug0, ug1, ug2, sgg, yg, ul0, ul1, ul2, sll, yl, sgl))
    hop = has_g and nis_g > gate
    inflate = hop and s.has_bias and hop_to_bias
    prior, biased = s.prior, s.biased
    sp, sv, sb = s.shrink
    Xn = [0.0] * len(X)
    Cn = []
    total = 0.0
    for a in range(3):
        ug0, ug1, ug2, sgg, yg, ul0, ul1, ul2, sll, yl, sgl = ax[a]
        c0, c1, c2, c3, c4, c5 = C[a]
        if inflate:
            d = yg * yg
            c5 = c5 + d
            ug2 = ug2 + d
            sgg += d
        if has_g and has_l:
            # U S^-1 U^T and U S^-1 y through S = L D L^T: W = U L^-T = [ug, ul - lgl ug], D = diag(sgg, d2)
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
            if has_g:
                u0, u1, u2, sv_, y = ug0, ug1, ug2, sgg, yg
            else:
                u0, u1, u2, sv_, y = ul0, ul1, ul2, sll, yl
            k0, k1, k2 = u0 / sv_, u1 / sv_, u2 / sv_
            dx0, dx1, dx2 = k0 * y, k1 * y, k2 * y
            n0, n1, n2 = c0 - k0 * u0, c1 - k0 * u1, c2 - k0 * u2
            n3, n4, n5 = c3 - k1 * u1, c4 - k1 * u2, c5 - k2 * u2
        xp, xv = X[a] + dx0, X[3 + a] + dx1
        xb = X[6 + a] + dx2 if hb else 0.0
        if biased:
            mp = biased_factor(xp, n0) if sp else 1.0
            mv = biased_factor(xv, n3) if sv else 1.0
            mb = biased_factor(xb, n5) if sb else 1.0
            if prior:
                b0, b1, b2, b3, b4, b5 = c0, c1, c2, c3, c4, c5
            else:
                b0, b1, b2, b3, b4, b5 = n0, n1, n2, n3, n4, n5
            n0, n1, n2 = b0 * (mp * mp), b1 * (mp * mv), b2 * (mp * mb)
            n3, n4, n5 = b3 * (mv * mv), b4 * (mv * mb), b5 * (mb * mb)
            xp, xv, xb = mp * xp, mv * xv, mb * xb
        if not hb:
            n2 = n4 = n5 = 0.0
        Xn[a], Xn[3 + a] = xp, xv
        if hb:
            Xn[6 + a] = xb
        Cn.append([n0, n1, n2, n3, n4, n5])
        total += xp + xv + xb + n0 + n1 + n2 + n3 + n4 + n5
    # finite sum -> every entry finite (cheap test first; the exact one only if it is not)
    if not math.isfinite(total) and not (all(math.isfinite(v) for v in Xn)
                                         and all(math.isfinite(v) for c in Cn for v in c)):
        raise BatchUnsupported(f"filter {s.kind}: non-finite state")
    s.X, s.C, s.t = Xn, Cn, t
    return hop
