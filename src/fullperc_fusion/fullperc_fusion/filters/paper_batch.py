"""The paper's KF / BKF / CKF / CBKF over a whole recording at once: one loop, no per-sample objects.

Why: offline evaluation runs the four filters over thousands of synchronised items. Through
:class:`~.paper_fast.ClosedFormFilter` each item costs a :class:`~.api.Measurement` per source, a
:class:`~.api.Step`, numpy arrays for its fields and the filter protocol's calls -- several times the arithmetic
itself. :func:`run_closed_form` takes the items as plain lists (stamps and positions in ``base``) and advances every
requested filter in one Python loop, writing the results into preallocated arrays.

Equality, not similarity: each step is :mod:`.paper_kernel`'s -- the time rule of :func:`~.api.predict_interval`,
then the kernel's predict, (re-)initialisation or update, the very functions ``ClosedFormFilter`` calls -- so the
estimates are bit-identical to the per-sample filters by construction (test_batch_filter.py checks it against
``ClosedFormFilter``, the evaluator's test against the whole pipeline). Only what the closed form serves is
supported: fixed isotropic noise (no measurement covariance) -- anything else raises :class:`BatchUnsupported` and
the caller runs the per-sample filters instead, as it does when a step would raise there (time going backwards, a
sample older than ``max_gap_s``, a non-finite state).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, predict_interval
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams
from fullperc_fusion.filters.paper_kernel import AxisForm, axis_form, init_axes, initial_axes, predict_axes, update_axes

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

    __slots__ = ("C", "X", "form", "has_bias", "kind", "out", "pending", "t")

    def __init__(self, kind: str, params: FilterParams, n_items: int) -> None:
        self.kind = kind
        self.form: AxisForm = axis_form(kind, params)
        self.has_bias = self.form.has_bias
        self.X, self.C = initial_axes(self.form)
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
    max_gap = params.max_gap_s
    for i in range(n_items):
        t_i = t_item[i]
        tg, tl = g_t[i], l_t[i]
        zg, zl = g_p[i], l_p[i]
        src = (SOURCE_GLOBAL if tg is not None else 0) | (SOURCE_LOCAL if tl is not None else 0)
        for s in states:
            form, out = s.form, s.out
            out.sources[i] = src
            # predict(t_i) as ClosedFormFilter.predict; the filter's time is t_i after it, so update does not predict
            try:
                t, dt = predict_interval(t_i, s.t, s.pending, max_gap)
            except ValueError:
                raise BatchUnsupported(f"filter {s.kind}: time went backwards at item {i}") from None
            if dt is None:
                s.pending = t
            else:
                predict_axes(form, s.X, s.C, dt)
                s.t = t
            if s.pending is not None:   # (re-)initialisation, as ClosedFormFilter.update
                s.X, s.C = init_axes(form, s.X, s.C, (t - s.t) * 1e-9 if s.t is not None else None, zg, zl)
                s.t, s.pending = t, None
                X = s.X
                out.p[i] = X[0:3]
                if s.has_bias:
                    out.bias[i] = X[6:9]
                out.pos_var[i] = form.init_pos_var
                out.reset[i] = True
                continue
            try:
                s.X, s.C, out.hop[i], _, _, _, _ = update_axes(form, s.X, s.C, t, tg, zg, form.global_var, tl, zl,
                                                               form.local_var, False)
            except (ValueError, FloatingPointError) as e:
                raise BatchUnsupported(f"filter {s.kind} at item {i}: {e}") from None
            X, C = s.X, s.C
            out.p[i] = X[0:3]
            if s.has_bias:
                out.bias[i] = X[6:9]
            out.pos_var[i] = (C[0][0], C[1][0], C[2][0])
    return {s.kind: s.out for s in states}
