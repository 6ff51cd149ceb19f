"""A pipeline's counters and the newest reason per kind of problem (what ``/diagnostics`` and the evaluator show)."""

from __future__ import annotations

from collections import Counter

# refusals of a sample whose stamp is good (the pose, its covariance, a jump): the stamp says when it was sent
POSE_KINDS = frozenset({"rejected_nonfinite", "rejected_nonunit", "rejected_pose", "rejected_cov", "rejected_jump"})


class Problems:
    """``counts`` (events and problems by kind), the newest reason per kind (``by_kind``) and overall (``last``,
    ``last_t_ns``, ``last_key``). A pipeline reports into its own; work whose diagnostics are not kept
    (arrival.py's side-by-side filters) reports into a throwaway one."""

    __slots__ = ("by_kind", "counts", "last", "last_key", "last_t_ns")

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.by_kind: dict[str, str] = {}
        self.last = self.last_key = ""
        self.last_t_ns: int | None = None

    def report(self, key: str, msg: str, t_ns: int | None) -> None:
        """Count a problem of kind ``key`` and make ``msg`` the newest one."""
        self.counts[key] += 1
        self.last, self.last_key = msg, key
        self.by_kind[key] = msg
        self.last_t_ns = t_ns

    def pose_refused(self, t_ns: int) -> int | None:
        """``t_ns`` if the newest problem refused the sample of that stamp for its pose (:data:`POSE_KINDS`: its
        stamp is good), else None."""
        return t_ns if self.last_t_ns == t_ns and self.last_key in POSE_KINDS else None
