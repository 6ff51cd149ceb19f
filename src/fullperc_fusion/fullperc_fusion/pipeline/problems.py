"""A pipeline's counters and the newest reason per kind of problem (what ``/diagnostics`` and the evaluator show)."""

from __future__ import annotations

from collections import Counter


class Problems:
    """``counts`` (events and problems by kind), the newest reason per kind (``by_kind``) and overall (``last``,
    ``last_t_ns``). A pipeline reports into its own; work whose diagnostics are not kept (arrival.py's side-by-side
    filters) reports into a throwaway one."""

    __slots__ = ("by_kind", "counts", "last", "last_t_ns")

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.by_kind: dict[str, str] = {}
        self.last = ""
        self.last_t_ns: int | None = None

    def report(self, key: str, msg: str, t_ns: int | None) -> None:
        """Count a problem of kind ``key`` and make ``msg`` the newest one."""
        self.counts[key] += 1
        self.last = msg
        self.by_kind[key] = msg
        self.last_t_ns = t_ns
