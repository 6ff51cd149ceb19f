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

from array import array
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
    """One filter's closed-form state (ClosedFormFilter's ``_X``, ``_C``, ``t_ns``, ``_pending_ns``) and its outputs
    so far, appended per item to flat float / bool buffers (:meth:`output` makes the arrays once: writing a numpy
    row per item cost ~1 us each, three per item and filter)."""

    __slots__ = ("C", "X", "bias", "form", "has_bias", "hop", "kind", "p", "pending", "pos_var", "reset", "t")

    def __init__(self, kind: str, params: FilterParams) -> None:
        self.kind = kind
        self.form: AxisForm = axis_form(kind, params)
        self.has_bias = self.form.has_bias
        self.X, self.C = initial_axes(self.form)
        self.t: int | None = None
        self.pending: int | None = None
        self.p = array("d")         # x y z per item
        self.bias = array("d")      # per item, only with the bias state
        self.pos_var = array("d")   # per item, the variance of each position axis
        self.hop: list[bool] = []
        self.reset: list[bool] = []

    def output(self, sources: np.ndarray) -> BatchOutput:
        """The filter's :class:`BatchOutput` over every item so far (``sources``: the items' source bits)."""
        n = len(self.hop)

        def rows(buf: array) -> np.ndarray:
            return np.frombuffer(buf, dtype=float).reshape(n, 3).copy() if n else np.zeros((0, 3))

        return BatchOutput(rows(self.p), rows(self.bias) if self.has_bias else np.zeros((n, 3)), rows(self.pos_var),
                           np.array(self.hop, dtype=bool).reshape(n), sources.copy(),
                           np.array(self.reset, dtype=bool).reshape(n))


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
    states = [_State(k, params) for k in kinds]
    max_gap = params.max_gap_s
    sources = np.array([(SOURCE_GLOBAL if tg is not None else 0) | (SOURCE_LOCAL if tl is not None else 0)
                        for tg, tl in zip(g_t, l_t, strict=True)], dtype=np.int64).reshape(n_items)
    for i in range(n_items):
        t_i = t_item[i]
        tg, tl = g_t[i], l_t[i]
        zg, zl = g_p[i], l_p[i]
        for s in states:
            form = s.form
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
                s.p.extend(X[0:3])
                if s.has_bias:
                    s.bias.extend(X[6:9])
                v = form.init_pos_var
                s.pos_var.extend((v, v, v))
                s.hop.append(False)
                s.reset.append(True)
                continue
            try:
                X, C, hop, _, _, _, _ = update_axes(form, s.X, s.C, t, tg, zg, form.global_var, tl, zl,
                                                    form.local_var, False)
            except (ValueError, FloatingPointError) as e:
                raise BatchUnsupported(f"filter {s.kind} at item {i}: {e}") from None
            s.X, s.C = X, C
            s.p.extend(X[0:3])
            if s.has_bias:
                s.bias.extend(X[6:9])
            s.pos_var.extend((C[0][0], C[1][0], C[2][0]))
            s.hop.append(hop)
            s.reset.append(False)
    return {s.kind: s.output(sources) for s in states}
