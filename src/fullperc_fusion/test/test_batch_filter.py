"""paper_batch.run_closed_form against the per-sample ClosedFormFilter (paper_fast), stepped as the pipeline steps it,
and the per-axis kernel both run on (paper_kernel).

Item streams with pairs (lagged older sample), global-only and local-only items, gaps longer than max_gap
(re-initialisation with the bias kept), hops of the global source (bias inflation) and the biased estimator:
every estimate, bias, position variance, hop flag and source bit must be bit-identical.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_fusion.filters import paper_batch, paper_fast, paper_kernel
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.paper_batch import BatchUnsupported, run_closed_form
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams
from fullperc_fusion.filters.paper_fast import ClosedFormFilter
from fullperc_fusion.filters.paper_kernel import axis_form, init_axes, update_axes


def _items(seed: int, n: int = 600):
    """A moving target seen by a biased, hopping global source and an occluded local one, with gaps."""
    rng = np.random.default_rng(seed)
    t, out = 1_000_000_000, []
    bias = np.array([0.003, -0.001, 0.002])
    for k in range(n):
        t += int(rng.integers(2_000_000, 12_000_000))
        if k in (150, 400):
            t += 700_000_000            # a gap longer than max_gap_s (0.5 s)
        if k == 250:
            bias = bias + np.array([0.004, 0.0, -0.003])   # a hop of the global source
        truth = np.array([0.3 + 0.05 * np.sin(t * 1e-9), 0.1 * np.cos(t * 1e-9), 0.4]) + 0.02 * (t * 1e-9)
        r = rng.random()
        has_g, has_l = r < 0.8, r > 0.6 or (k // 100) % 2 == 0 and r > 0.3
        if not (has_g or has_l):
            has_g = True
        lag = int(rng.integers(0, 3_000_000))
        tg = t - (lag if has_l and rng.random() < 0.5 else 0) if has_g else None
        tl = (t - (lag if tg == t else 0)) if has_l else None
        if has_g and has_l:
            t_item = max(tg, tl)
        else:
            t_item = tg if has_g else tl
        zg = (truth + bias + 3e-4 * rng.standard_normal(3)).tolist() if has_g else None
        zl = (truth + 1.5e-4 * rng.standard_normal(3)).tolist() if has_l else None
        out.append((t_item, tg, zg, tl, zl))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_batched_equals_closed_form_filter(seed):
    params = FilterParams()
    items = _items(seed)
    res = run_closed_form(FILTER_KINDS, params, [i[0] for i in items], [i[1] for i in items],
                          [i[2] for i in items], [i[3] for i in items], [i[4] for i in items])
    hops = resets = 0
    for kind in FILTER_KINDS:
        f = ClosedFormFilter(kind, params)
        r = res[kind]
        for n, (t_item, tg, zg, tl, zl) in enumerate(items):
            ms = []
            if tg is not None:
                ms.append(Measurement(tg, SOURCE_GLOBAL, np.array(zg)))
            if tl is not None:
                ms.append(Measurement(tl, SOURCE_LOCAL, np.array(zl)))
            f.predict(t_item)
            st = f.update(*ms)
            assert st.t_ns == t_item
            assert np.array_equal(r.p[n], st.p), (kind, n)
            assert np.array_equal(r.bias[n], st.b), (kind, n)
            assert np.array_equal(r.pos_var[n], np.diag(st.pos_cov)), (kind, n)
            assert r.hop[n] == st.hop and r.reset[n] == st.reset and r.sources[n] == st.sources, (kind, n)
            hops += int(st.hop)
            resets += int(st.reset)
    assert hops > 0 and resets >= 3 * len(FILTER_KINDS)   # the stream exercised hops and re-initialisations


def test_time_going_backwards_is_refused_not_guessed():
    with pytest.raises(BatchUnsupported, match="backwards"):
        run_closed_form(["cbkf"], FilterParams(), [2_000_000, 1_000_000], [2_000_000, 1_000_000],
                        [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [None, None], [None, None])


def test_unknown_kind_is_refused():
    with pytest.raises(BatchUnsupported, match="no batched form"):
        run_closed_form(["fullperc"], FilterParams(), [], [], [], [], [])


def test_both_forms_step_through_the_one_kernel():
    """The per-sample and the batched closed form call the same functions: no second copy of the arithmetic (the
    batched replay predicts inside update_axes; the per-sample predict_axes is update_axes without a sample)."""
    for name in ("axis_form", "initial_axes", "init_axes", "update_axes"):
        kernel_fn = getattr(paper_kernel, name)
        assert getattr(paper_batch, name) is kernel_fn and getattr(paper_fast, name) is kernel_fn, name
    assert paper_fast.predict_axes is paper_kernel.predict_axes


def test_the_first_failure_item_by_item_is_the_one_raised():
    """Each filter runs over the items in turn, but what is raised is what stepping them item by item meets first:
    the earliest item, and on it the first filter of ``kinds``."""
    items = _items(4, 200)
    t_item = [i[0] for i in items]
    t_item[120] = t_item[119] - 1
    t_item[60] = t_item[59] - 1
    for kinds in (["kf", "cbkf"], ["ckf", "bkf", "kf"]):
        with pytest.raises(BatchUnsupported, match=f"filter {kinds[0]}: time went backwards at item 60$"):
            run_closed_form(kinds, FilterParams(), t_item, [i[1] for i in items], [i[2] for i in items],
                            [i[3] for i in items], [i[4] for i in items])


def test_an_item_without_a_sample_is_refused():
    with pytest.raises(BatchUnsupported, match="item 1 has no sample"):
        run_closed_form(["kf"], FilterParams(), [1_000_000, 2_000_000], [1_000_000, None], [[0.0, 0.0, 0.0], None],
                        [None, None], [None, None])


def _state(rng, has_bias: bool):
    X = (0.3 + 0.1 * rng.standard_normal(9 if has_bias else 6)).tolist()
    C = []
    for _ in range(3):
        A = rng.standard_normal((3, 3)) * [[1e-3], [1e-2], [1e-3]]
        P = A @ A.T + 1e-8 * np.eye(3)
        if not has_bias:
            P[2, :] = P[:, 2] = 0.0
        C.append(P[np.triu_indices(3)].tolist())   # pp pv pb vv vb bb
    return X, C


def _kernel_samples(rng, X, k: int, t: int):
    """(tg, zg, tl, zl) near the state X: a pair, a global or a local sample by k % 3, stamps up to 4 ms before t."""
    zg = (np.array(X[0:3]) + 2e-3 * rng.standard_normal(3)).tolist() if k % 3 != 1 else None
    zl = (np.array(X[0:3]) + 1e-4 * rng.standard_normal(3)).tolist() if k % 3 != 0 else None
    return t - int(rng.integers(0, 4_000_000)), zg, t - int(rng.integers(0, 4_000_000)), zl


@pytest.mark.parametrize("kind", FILTER_KINDS)
def test_kernel_update_without_diagnostics_gives_the_same_state(kind):
    """``full=False`` (the batched replay) skips NIS, innovation and M only: state, hop flag and the hop test's
    NIS_global are bit-identical."""
    rng = np.random.default_rng(7)
    form = axis_form(kind, FilterParams(hop_gate=3.0))
    t = 10 * 10**9
    hops = 0
    for k in range(300):
        X, C = _state(rng, form.has_bias)
        tg, zg, tl, zl = _kernel_samples(rng, X, k, t)
        full = update_axes(form, X, C, t, tg, zg, form.global_var, tl, zl, form.local_var)
        lean = update_axes(form, X, C, t, tg, zg, form.global_var, tl, zl, form.local_var, False)
        assert full[0:3] == lean[0:3] and full[4] == lean[4]
        assert lean[3] == 0.0 and lean[5:] == (None, None) and full[3] > 0.0 and len(full[5]) == 3
        assert (full[6] is not None) == form.biased
        hops += full[2]
    assert 0 < hops < 300


def test_kernel_leaves_its_input_alone():
    """update_axes and init_axes return new lists: a refused or a successful step leaves the state it was given
    (the per-sample filter's snapshot copies only the outer lists; a refused update keeps the predicted state)."""
    rng = np.random.default_rng(8)
    form = axis_form("cbkf", FilterParams())
    X, C = _state(rng, True)
    X0, C0 = list(X), [list(c) for c in C]
    t = 10 * 10**9
    update_axes(form, X, C, t, t, [0.3, 0.3, 0.3], form.global_var, t - 10**6, [0.3, 0.3, 0.3], form.local_var)
    with pytest.raises(ValueError, match="older than the filter time"):
        update_axes(form, X, C, t, t - 10**9, [0.3, 0.3, 0.3], form.global_var, None, None, None)
    Xi, Ci = init_axes(form, X, C, 0.7, [0.5, 0.5, 0.5], None)
    assert X == X0 and C == C0
    # the re-initialisation keeps the bias and walks its variance over the gap; p is the global sample minus it
    assert Xi[6:9] == X[6:9] and Xi[0:3] == [0.5 - b for b in X[6:9]] and Xi[3:6] == [0.0] * 3
    assert [c[5] for c in Ci] == [c[5] + form.bias_walk * 0.7 for c in C]
