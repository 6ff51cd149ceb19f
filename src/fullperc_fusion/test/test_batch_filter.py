"""batch_filter.run_closed_form against the per-sample ClosedFormFilter, stepped as the pipeline steps it.

Item streams with pairs (lagged older sample), global-only and local-only items, gaps longer than max_gap
(re-initialisation with the bias kept), hops of the global source (bias inflation) and the biased estimator:
every estimate, bias, position variance, hop flag and source bit must be bit-identical.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.paper_batch import BatchUnsupported, run_closed_form
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams
from fullperc_fusion.filters.paper_fast import ClosedFormFilter


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
