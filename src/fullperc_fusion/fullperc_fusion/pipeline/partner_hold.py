"""Hold-for-partner: fusion on arrival waits briefly for a partner that is due, instead of fusing and rewinding.

Why: fusion on arrival (:mod:`.arrival`) fuses every sample the moment it arrives. With the OMC at 240 Hz and the
OTS at 400 Hz nearly every OMC sample is the approximate-time partner of an OTS sample fused a moment before, so
nearly every pair was fused twice: the OTS sample alone, then -- on the partner's arrival -- the rewind to before it
and the pair (``bench/bench_node_cost.py`` counted ~3,980 rewinds per 3,990 items), and both outputs were
published. The replay and the extra message are a large part of the node's CPU per target (docs/performance.md).
A partner stamped within ``slop`` usually arrives within a millisecond or two: waiting for it costs that much
latency on the first sample of a pair and nothing on the pair's output (its stamp is the partner's), and saves a
rewind, a replay and a message.

Which sample waits (:meth:`PartnerHold.wants`; the streams' periods are the medians of their last few stamp
intervals): a sample at ``t`` of one of the two paired streams waits when the other stream's next sample is due
(its newest stamp plus its period: ``t_p``) and would pair with it -- ``|t_p - t| < slop``, nearer than the other
stream's sample already here, and nearer to ``t_p`` than this stream's previous sample and its predicted next one
(the synchronizer pairs mutual nearest samples, synchronizer.py). A stream that missed its predicted sample
(``t_p + slop < t``: occluded, or stopped) is not waited for.

When it stops waiting (:meth:`PartnerHold.offer`, :meth:`PartnerHold.due`): as soon as the other stream delivers
any sample (the partner, or one that shows the partner will not come), a newer sample of its own stream arrives
(at most one waits per stream), or ``wait_ns`` of the host clock have passed since it arrived (the node's timer
and every input check this); and at a flush or a timeline restart. A sample that waited is then fused exactly as
if it had just arrived, together with the samples released with it in one re-pairing, so a pair is fused once.
Nothing else changes: the stamp rules admitted it on arrival, and the rewind still corrects any pairing the
prediction got wrong, so once an item leaves the history the estimates equal ordered processing whatever waited
(test_partner_hold.py holds arrival with waiting to ordered processing under jitter, reordering and gaps).

Further local sources (:mod:`.sources`) never pair: their samples never wait and do not release one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL

__all__ = ["Held", "PartnerHold"]

GAPS = 5   # stamp intervals per stream whose median is its period: a dropped or reordered sample does not move it


class Held(NamedTuple):
    stream: int
    t_ns: int
    payload: Any
    deadline_ns: int   # host clock (``PartnerHold.clock``) after which it stops waiting


class PartnerHold:
    """The samples waiting for their partner and what predicts the partners; see the module docstring.
    ``wait_ns`` = 0: nothing ever waits (:meth:`offer` hands every sample straight back)."""

    __slots__ = ("clock", "gaps", "held", "newest", "slop_ns", "wait_ns", "waited")

    def __init__(self, slop_ns: int, wait_ns: int, clock: Callable[[], int] = time.monotonic_ns) -> None:
        if wait_ns < 0:
            raise ValueError(f"partner_wait must be >= 0, got {wait_ns * 1e-9} s")
        self.slop_ns, self.wait_ns, self.clock = int(slop_ns), int(wait_ns), clock
        self.newest: list[int | None] = [None, None]     # per paired stream: its newest stamp admitted
        self.gaps: list[list[int]] = [[], []]            # its last GAPS positive stamp intervals
        self.held: list[Held] = []
        self.waited = 0                                  # samples that waited (for /diagnostics)

    def __len__(self) -> int:
        return len(self.held)

    def period(self, stream: int) -> int | None:
        g = self.gaps[stream]
        return sorted(g)[len(g) // 2] if len(g) >= 2 else None

    def wants(self, stream: int, t: int) -> bool:
        """Whether a sample at ``t`` of ``stream`` (0 global, 1 the first local source) should wait for the other
        stream's next sample (module docstring). Call before :meth:`_note` records it."""
        other = 1 - stream
        last_o, per_o, per_s = self.newest[other], self.period(other), self.period(stream)
        last_s = self.newest[stream]
        if last_o is None or per_o is None or per_s is None or last_s is None or last_o >= t or t <= last_s:
            return False
        t_p = last_o + per_o
        d = abs(t_p - t)
        return (t_p + self.slop_ns >= t and d < self.slop_ns and d < t - last_o
                and d <= abs(t + per_s - t_p) and d < abs(t_p - last_s))

    def _note(self, stream: int, t: int) -> None:
        last = self.newest[stream]
        if last is None or t > last:
            if last is not None:
                g = self.gaps[stream]
                g.append(t - last)
                if len(g) > GAPS:
                    del g[0]
            self.newest[stream] = t

    def offer(self, stream: int, t: int, payload: Any) -> list[tuple[int, int, Any]]:
        """A sample the stamp rules admitted: the samples to fuse now, ``(stream, t, payload)`` -- the ones it
        releases and, unless it waits itself, the sample. Samples of further local sources pass straight through."""
        if stream not in (GLOBAL, LOCAL) or self.wait_ns == 0:
            return [*self.due(), (stream, t, payload)] if self.held else [(stream, t, payload)]
        # whatever waits is released: its own stream moved on, or the other one delivered (at most one waits)
        out = [(h.stream, h.t_ns, h.payload) for h in self.held]
        self.held = []
        wait = self.wants(stream, t)
        self._note(stream, t)
        if wait:
            self.held.append(Held(stream, t, payload, self.clock() + self.wait_ns))
            self.waited += 1
        else:
            out.append((stream, t, payload))
        return out

    def restart(self) -> None:
        """A new timeline (the stamps went back for good): the old one predicts nothing. Nothing may be waiting."""
        assert not self.held, "release the waiting samples (due(everything=True)) before a restart"
        self.newest, self.gaps = [None, None], [[], []]

    def due(self, everything: bool = False) -> list[tuple[int, int, Any]]:
        """The waiting samples whose time is up (``everything``: all of them), removed from the hold."""
        if not self.held:
            return []
        now = None if everything else self.clock()
        out = [(h.stream, h.t_ns, h.payload) for h in self.held if now is None or h.deadline_ns <= now]
        if out:
            self.held = [h for h in self.held if not (now is None or h.deadline_ns <= now)]
        return out
