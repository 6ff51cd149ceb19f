"""latency.LatencyHistogram: quantiles never below the true value and at most one bin (21 %) above, the maximum exact,
merging equal to adding everything to one histogram."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fullperc_common.latency import EDGES_NS, LatencyHistogram


def _true_quantile(d: np.ndarray, q: float) -> int:
    """Nearest rank: the ceil(q·n)-th smallest."""
    return int(np.sort(d)[max(1, math.ceil(q * d.size)) - 1])


def test_edges_are_twelve_per_decade_from_10_us_to_10_s():
    assert EDGES_NS[0] == 10_000 and EDGES_NS[-1] == 10_000_000_000 and len(EDGES_NS) == 6 * 12 + 1
    ratios = np.array(EDGES_NS[1:]) / np.array(EDGES_NS[:-1])
    assert np.allclose(ratios, 10 ** (1 / 12), rtol=1e-3)   # 1.212: a quantile is at most 21 % high


@pytest.mark.parametrize("seed", range(5))
def test_quantiles_bound_the_true_ones_within_a_bin(seed):
    rng = np.random.default_rng(seed)
    d = np.exp(rng.normal(np.log(1.5e6), 1.2, 3000)).astype(np.int64)   # lognormal around 1.5 ms, a heavy tail
    h = LatencyHistogram()
    for x in d.tolist():
        h.add(x)
    assert h.n == d.size and h.max_ns == d.max()
    for q in (0.5, 0.9, 0.99, 1.0):
        true = _true_quantile(d, q)
        got = h.quantile_ns(q)
        assert true <= got <= max(true * 10 ** (1 / 12) + 1, 10_000), (q, true, got)
    assert h.quantile_ns(1.0) == d.max()


def test_below_the_first_and_above_the_last_edge():
    h = LatencyHistogram()
    h.add(-5)          # clocks of two processes: counted as 0
    h.add(3_000)
    assert h.quantile_ns(0.5) == 3_000   # the bin's edge (10 us) capped by the exact maximum
    h.add(30_000_000_000)   # 30 s: the overflow bin reports the maximum
    assert h.quantile_ns(1.0) == 30_000_000_000 and h.counts[-1] == 1 and h.counts[0] == 2


def test_merged_equals_one_histogram_of_everything():
    rng = np.random.default_rng(7)
    a, b, both = LatencyHistogram(), LatencyHistogram(), LatencyHistogram()
    for i, x in enumerate(rng.integers(1_000, 5_000_000_000, 500).tolist()):
        (a if i % 3 else b).add(x)
        both.add(x)
    m = a.merged(b)
    assert m.counts == both.counts and m.n == both.n and m.max_ns == both.max_ns
    assert a.merged(LatencyHistogram()).counts == a.counts and LatencyHistogram().merged(a).max_ns == a.max_ns


def test_empty_histogram_reports_nothing():
    h = LatencyHistogram()
    assert h.quantile_ns(0.99) is None
    assert h.figures_ms("wakeup") == {"wakeup_p50_ms": None, "wakeup_p99_ms": None, "wakeup_max_ms": None}
