"""The paper's KF / BKF / CKF / CBKF over a whole recording at once: a loop per filter, no per-sample objects.

Why: offline evaluation runs the four filters over thousands of synchronised items. Through
:class:`~.paper_fast.ClosedFormFilter` each item costs a :class:`~.api.Measurement` per source, a
:class:`~.api.Step`, numpy arrays for its fields and the filter protocol's calls -- several times the arithmetic
itself. :func:`run_closed_form` takes the items as plain lists (stamps and positions in ``base``) and advances each
requested filter over them in one Python loop, appending the results to flat buffers.

Equality, not similarity: each step is :mod:`.paper_kernel`'s -- the time rule of :func:`~.api.predict_interval`,
then the kernel's (re-)initialisation, or its update with the prediction in the same pass (``update_axes(...,
dt)``: the arithmetic ``ClosedFormFilter``'s predict_axes then update_axes run, in one call) -- so the estimates are
bit-identical to the per-sample filters by construction (test_batch_filter.py checks it against
``ClosedFormFilter``, the evaluator's test against the whole pipeline). Only what the closed form serves is
supported: fixed isotropic noise (no measurement covariance) -- anything else raises :class:`BatchUnsupported` and
the caller runs the per-sample filters instead, as it does when a step would raise there (time going backwards, a
sample older than ``max_gap_s``, a non-finite state) and for an item without any sample.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass

import numpy as np

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams
from fullperc_fusion.filters.paper_kernel import AxisForm, axis_form, init_axes, initial_axes, update_axes

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
    """One filter's outputs so far, appended per item to flat buffers (:meth:`output` makes the arrays once: writing
    a numpy row per item cost ~1 us each, three per item and filter): its whole state vector ``x`` (position and
    bias are slices of it: one append instead of two slices and two), the position variances, the hop flags and the
    indices of the (re-)initialisations. The state itself is stepped in :func:`_run`'s locals. (Keeping the state
    lists themselves and converting them at the end was slower: the conversion, and the garbage collector walking
    ~20 live lists per item.)"""

    __slots__ = ("form", "has_bias", "hop", "kind", "pos_var", "resets", "x")

    def __init__(self, kind: str, params: FilterParams) -> None:
        self.kind = kind
        self.form: AxisForm = axis_form(kind, params)
        self.has_bias = self.form.has_bias
        self.x = array("d")         # per item, the state vector [p v (b)] after it
        self.pos_var = array("d")   # per item, the variance of each position axis
        self.hop: list[bool] = []
        self.resets: list[int] = []

    def output(self, sources: np.ndarray) -> BatchOutput:
        """The filter's :class:`BatchOutput` over every item so far (``sources``: the items' source bits)."""
        n = len(self.hop)
        x = np.frombuffer(self.x, dtype=float).reshape(n, 9 if self.has_bias else 6) if n else np.zeros((0, 9))
        reset = np.zeros(n, dtype=bool)
        reset[self.resets] = True
        return BatchOutput(x[:, 0:3].copy(), x[:, 6:9].copy() if self.has_bias else np.zeros((n, 3)),
                           np.frombuffer(self.pos_var, dtype=float).reshape(n, 3).copy() if n else np.zeros((0, 3)),
                           np.array(self.hop, dtype=bool).reshape(n), sources.copy(), reset)


def run_closed_form(kinds: tuple[str, ...] | list[str], params: FilterParams, t_item: list[int],
                    g_t: list[int | None], g_p: list[list[float] | None],
                    l_t: list[int | None], l_p: list[list[float] | None]) -> dict[str, BatchOutput]:
    """Every filter of ``kinds`` (each one of FILTER_KINDS) over the items, as the pipeline steps them.

    Item i has processing stamp ``t_item[i]`` (the newer of its samples) and a global sample (stamp ``g_t[i]``,
    position ``g_p[i]`` in base) and/or a local one (``l_t``, ``l_p``); None where absent. The pipeline calls
    ``predict(t_item)`` then ``update(global, local)`` on a fresh filter per kind: so does this, in closed form.

    The filters do not interact, so each runs over all items in turn (:func:`_run`, its state in locals: faster
    than stepping every filter per item). What fails is what stepping them item by item would meet first: the
    earliest item, and on it the first filter of ``kinds``.
    """
    for k in kinds:
        if k not in FILTER_KINDS:
            raise BatchUnsupported(f"filter '{k}' has no batched form")
    n_items = len(t_item)
    states = [_State(k, params) for k in kinds]
    sources = np.array([(SOURCE_GLOBAL if tg is not None else 0) | (SOURCE_LOCAL if tl is not None else 0)
                        for tg, tl in zip(g_t, l_t, strict=True)], dtype=np.int64).reshape(n_items)
    if not sources.all():   # the pipeline makes none; update_axes would take it for a prediction alone
        raise BatchUnsupported(f"item {int(np.argmin(sources))} has no sample")
    items = list(zip([int(t) for t in t_item], g_t, g_p, l_t, l_p, strict=True))   # int(): as predict_interval
    failure = None
    for s in states:   # a later filter need only run up to an earlier one's failure, which comes first on a tie
        failed = _run(s, items, params.max_gap_s)
        if failed is not None:
            items, failure = items[:failed[0]], failed[1]
    if failure is not None:
        raise failure
    return {s.kind: s.output(sources) for s in states}


def _run(s: _State, items: list[tuple[int, int | None, list[float] | None, int | None, list[float] | None]],
         max_gap: float) -> tuple[int, Exception] | None:
    """Filter ``s`` over ``items`` (:func:`run_closed_form`'s, zipped), from no state; None, or the item where it
    failed and the exception that stepping it there raises (BatchUnsupported for what the per-sample filter
    refuses).

    Per item ClosedFormFilter's predict(t) then update: the time rule of :func:`~.api.predict_interval`, written
    out (the call was ~3 % of the replay; test_batch_filter.py holds the two to each other) -- no pending stamp
    here: a (re-)initialisation takes it at once --, then the kernel's predict and update in one call, or its
    (re-)initialisation when there is nothing to predict from."""
    form, kind = s.form, s.kind
    X, C = initial_axes(form)
    t_s: int | None = None   # the state's stamp
    rg, rl = form.global_var, form.local_var
    v = form.init_pos_var
    init_var = (v, v, v)
    put_x, put_var, put_hop, put_reset = s.x.extend, s.pos_var.extend, s.hop.append, s.resets.append
    i = 0
    try:
        for i, (t, tg, zg, tl, zl) in enumerate(items):
            dt = None
            if t_s is not None:
                if t < t_s:
                    return i, BatchUnsupported(f"filter {kind}: time went backwards at item {i}")
                dt = (t - t_s) * 1e-9
                if not dt > max_gap:
                    t_s = t
                    try:   # predict over dt and update, in one pass
                        X, C, hop, _, _, _, _ = update_axes(form, X, C, t, tg, zg, rg, tl, zl, rl, False, dt)
                    except (ValueError, FloatingPointError) as e:
                        return i, BatchUnsupported(f"filter {kind} at item {i}: {e}")
                    put_x(X)
                    put_var((C[0][0], C[1][0], C[2][0]))
                    put_hop(hop)
                    continue
            # (re-)initialisation: no state yet (dt None), or a gap longer than max_gap_s (the bias is kept)
            X, C = init_axes(form, X, C, dt, zg, zl)
            t_s = t
            put_x(X)
            put_var(init_var)
            put_hop(False)
            put_reset(i)
    except Exception as e:   # noqa: BLE001 -- not ours to judge: raised as stepping item by item would raise it
        return i, e
    return None
