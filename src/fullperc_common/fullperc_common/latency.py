"""A latency histogram of fixed size: the per-stage figures of fusion_node's input wake-ups on /diagnostics.

Why: the node reported the largest callback delay of a period and nothing else, so a p99 tail (``make bench``
measured tails 4-30x the median) could not be told from one stall, and where the time went (waiting for the
executor, or fusing and publishing) was not visible at all. Each input wake-up now adds three durations -- from the
DDS reception of the sample that started it to the callback (``callback_delay``), from the callback's start until
everything it fused is published (``wakeup``: take, fuse, publish), and their sum (``received_to_published``) --,
and the status shows the median, p99 and maximum of each over the report's stretch.

How: counts in log-spaced bins, 10 µs to 10 s with 12 bins per decade (each bin's upper edge 21 % above its lower
one), plus one bin below and one above. A quantile is the upper edge of the bin it falls in, so a reported figure
is never below the true one and at most 21 % above it; the maximum is kept exactly. Adding is one bisect, merging
two stretches adds their counts: memory and cost do not grow with the rate or with reports that were not published.
"""

from __future__ import annotations

import bisect
import math

BINS_PER_DECADE = 12
LOW_NS, HIGH_NS = 10_000, 10_000_000_000   # 10 µs .. 10 s
_DECADES = round(math.log10(HIGH_NS / LOW_NS))
EDGES_NS: tuple[int, ...] = tuple(round(LOW_NS * 10 ** (k / BINS_PER_DECADE))
                                  for k in range(_DECADES * BINS_PER_DECADE + 1))


class LatencyHistogram:
    """Durations [ns] in the bins of :data:`EDGES_NS`: bin ``i`` counts ``EDGES_NS[i-1] < d <= EDGES_NS[i]`` (bin 0:
    ``d <= 10 µs``; the last: above 10 s)."""

    __slots__ = ("counts", "n", "max_ns")

    def __init__(self) -> None:
        self.counts = [0] * (len(EDGES_NS) + 1)
        self.n = 0
        self.max_ns: int | None = None

    def add(self, ns: int) -> None:
        """One duration; a negative one (clocks of two processes) counts as 0."""
        ns = max(0, int(ns))
        self.counts[bisect.bisect_left(EDGES_NS, ns)] += 1
        self.n += 1
        if self.max_ns is None or ns > self.max_ns:
            self.max_ns = ns

    def merged(self, other: LatencyHistogram) -> LatencyHistogram:
        """Both stretches as one (a new histogram)."""
        out = LatencyHistogram()
        out.counts = [a + b for a, b in zip(self.counts, other.counts, strict=True)]
        out.n = self.n + other.n
        out.max_ns = other.max_ns if self.max_ns is None else self.max_ns if other.max_ns is None else max(
            self.max_ns, other.max_ns)
        return out

    def quantile_ns(self, q: float) -> int | None:
        """The upper edge of the bin holding the ``q`` quantile (nearest rank: the ceil(q·n)-th smallest), capped at
        the exact maximum; None when empty."""
        if not self.n:
            return None
        rank = max(1, math.ceil(q * self.n))
        seen = 0
        for i, c in enumerate(self.counts):
            seen += c
            if seen >= rank:
                edge = EDGES_NS[i] if i < len(EDGES_NS) else self.max_ns
                return min(edge, self.max_ns)
        return self.max_ns   # not reached: the counts sum to n

    def figures_ms(self, name: str) -> dict[str, float | None]:
        """``{name}_p50_ms``, ``{name}_p99_ms``, ``{name}_max_ms`` (None when empty)."""
        def ms(v: int | None) -> float | None:
            return None if v is None else round(v * 1e-6, 3)

        return {f"{name}_p50_ms": ms(self.quantile_ns(0.5)), f"{name}_p99_ms": ms(self.quantile_ns(0.99)),
                f"{name}_max_ms": ms(self.max_ns)}
