"""Fusion on arrival's bookkeeping (:mod:`.arrival`): the history of items fused and not final yet, and the
outputs not handed out yet."""

from __future__ import annotations

import bisect
from collections.abc import Container
from dataclasses import dataclass, field

from fullperc_fusion.pipeline.lane import LaneSnapshot
from fullperc_fusion.pipeline.link_views import View
from fullperc_fusion.pipeline.synchronizer import SyncItem
from fullperc_fusion.pipeline.target import FusedOutput


@dataclass(eq=False)
class Entry:
    """One item in the history: what was fused, the live lane before it, what it output and changed."""

    item: SyncItem
    te: int                                  # stamp of its first sample (the synchronizer's order)
    snap: LaneSnapshot                       # the live lane before the item (FilterLane.snapshot)
    outs: list[FusedOutput] = field(default_factory=list)
    delta: dict[str, int] = field(default_factory=dict)   # counters the processing incremented (a plain dict:
    #                                                       building a Counter per entry was ~6 % of the live path)
    view: View | None = None                 # static links it is resolved with; None: the current ones
    alive: bool = True                       # False once replaced by a rewind


class History:
    """The entries in the synchronizer's order (``te``); the first ``nres`` are resolved (their links fixed)."""

    __slots__ = ("entries", "nres", "tes")

    def __init__(self) -> None:
        self.entries: list[Entry] = []
        self.tes: list[int] = []     # entry.te, parallel to entries (bisect)
        self.nres = 0

    def __len__(self) -> int:
        return len(self.entries)

    def index(self, t_ns: int) -> int:
        """Index of the first entry whose first stamp is at or after ``t_ns``."""
        return bisect.bisect_left(self.tes, t_ns)

    def append(self, e: Entry) -> None:
        self.entries.append(e)
        self.tes.append(e.te)

    def cut(self, i: int) -> list[Entry]:
        """Remove the entries from index ``i`` on (a rewind) and return them."""
        gone = self.entries[i:]
        del self.entries[i:]
        del self.tes[i:]
        self.nres = min(self.nres, i)
        return gone

    def drop_front(self, n: int) -> None:
        """Remove the first ``n`` entries (they became final)."""
        del self.entries[:n]
        del self.tes[:n]
        self.nres = max(0, self.nres - n)


class Outbox:
    """What :meth:`~.arrival.ArrivalPipeline.poll` and ``take_final`` hand out next.

    ``fresh``: entries (re)processed since the last poll; ``carried``: live outputs of a timeline a restart ended,
    first in the next poll; ``committed``: side-by-side outputs of items that became final; ``final``: outputs of
    the items that left the history (take_final); ``published_ns``: stamp of the newest live output returned.
    """

    __slots__ = ("carried", "committed", "final", "fresh", "published_ns")

    def __init__(self) -> None:
        self.fresh: list[Entry] = []
        self.carried: list[FusedOutput] = []
        self.committed: list[FusedOutput] = []
        self.final: list[FusedOutput] = []
        self.published_ns: int | None = None

    def poll(self, side: Container[str]) -> list[FusedOutput]:
        """The carried outputs, then the live outputs (filters not in ``side``) of the fresh entries still in the
        history, in stamp order, each entry's only if its newest output is newer than the last one returned; then
        the committed side-by-side outputs."""
        out, self.carried = self.carried, []
        for e in sorted((e for e in self.fresh if e.alive and e.outs), key=lambda e: e.item.t_ns):
            live = [o for o in e.outs if o.filter not in side]
            # gate on the outputs' own stamps, not the item's: a pair re-run when the partner of a published sample
            # arrives has a newer item stamp, but if the chain cannot map the partner (links not known yet) its
            # output is the estimate already published, with the same stamp -- it must not go out twice
            t = max((o.t_ns for o in live), default=None)
            if t is not None and (self.published_ns is None or t > self.published_ns):
                out.extend(live)
                self.published_ns = t
        self.fresh = []
        out.extend(self.committed)
        self.committed = []
        return out

    def take_final(self) -> list[FusedOutput]:
        out, self.final = self.final, []
        return out
