"""Approximate-time pairing of (global, local) samples that never drops a lone sample.

message_filters' ApproximateTimeSynchronizer only ever emits complete sets, so while the OTS is
occluded the OMC stream would be thrown away -- exactly wrong for fusion. This synchronizer emits
*every* sample exactly once, in stamp order, either paired with the other stream's sample or alone:

* Two samples pair when their stamps differ by less than ``slop`` and each is the other's nearest
  candidate (with ``slop`` below half the faster stream's period the match is unique anyway).
* A sample is final once no partner and no closer competitor can still arrive: all samples stamped up
  to ``now - delay`` are assumed to have arrived (``delay`` is the bounded reorder / transport delay),
  and a competitor of a partner can be stamped up to 2·slop after the sample, so a sample at t is
  emitted when ``now >= t + 2·slop + delay``. Latency of the output is therefore 2·slop + delay.
* ``now`` is either given (host clock in a live node) or, by default, the *watermark* -- the newest
  stamp pushed so far on any stream -- which makes the output a pure function of the stamps (offline
  evaluation, replays). A silent stream never blocks the other: the watermark moves with the stream
  that is alive, and :meth:`flush` emits everything at the end.
* Items come out in non-decreasing processing stamp (the newer stamp of a pair).

Defined behaviour for bad timing (each counted in :attr:`counts`, tested in test_synchronizer.py); the duplicate
and late rules are :class:`~.stamp_rules.StampRules`' (:attr:`ApproxSync.rules`), the same code fusion on arrival
applies to its history:

* duplicate: a sample with the same stamp as a pending or already emitted sample of the *same* stream
  is dropped (``'duplicate'``); the first one wins. Equal stamps on the two streams simply pair.
* out of order: a sample older than others of its stream but newer than the processing horizon is
  sorted in and handled normally -- that is what the reorder delay is for.
* late: a sample stamped before the horizon (the stamp of the last emitted item) cannot be processed
  without rewinding the filter; it is dropped and counted (``'late'``). Raise ``delay`` if this
  happens in normal operation.
* overflow: more than ``max_pending`` samples waiting on one stream (e.g. ``now`` stuck far behind)
  forces the oldest out early -- still emitted, never dropped.

Further local sources (:mod:`sources`, ``names`` beyond global and local): each is one more stream whose samples
never pair -- every one is its own item (``SyncItem.source`` = its local source index), emitted by the same
earliest-head rule, so items still come out in the order of their first stamp. The pairing of the global and the
first local stream does not look at them, so it is exactly what it is without them. Such an item can be stamped
before the previous pair's processing stamp (it lies in that pair's slop window); the pipeline fuses it as a
lagged measurement at that stamp.
"""

from __future__ import annotations

import bisect
from collections import Counter
from dataclasses import dataclass
from typing import Any

from fullperc_fusion.filters.api import ROLE_LABELS, Role
from fullperc_fusion.pipeline.stamp_rules import OK, StampRules

GLOBAL = int(Role.GLOBAL)   # the stream index of a role (filters.api.Role)
LOCAL = int(Role.LOCAL)
_NAMES = ROLE_LABELS


@dataclass(frozen=True)
class Sample:
    t_ns: int
    payload: Any


@dataclass(frozen=True)
class SyncItem:
    """One unit of work for the filter: a global sample, a local sample, or a pair."""

    t_ns: int                    # processing stamp: the newer stamp of the item
    glob: Sample | None
    local: Sample | None
    source: int = 0              # local source of ``local``: 0 = the first (paired) one, k = stream 1 + k


class ApproxSync:
    """Pairs global and local samples within ``slop_ns``; see the module docstring for the rules."""

    def __init__(self, slop_ns: int = 4_000_000, delay_ns: int = 50_000_000, max_pending: int = 4096,
                 names: tuple[str, ...] = _NAMES) -> None:
        if slop_ns < 0 or delay_ns < 0 or max_pending < 1:
            raise ValueError("slop and delay must be >= 0 and max_pending >= 1")
        if len(names) < 2 or len(set(names)) != len(names):
            raise ValueError(f"stream names {names}: global, local and distinct further ones")
        self.slop = int(slop_ns)
        self.delay = int(delay_ns)
        self.max_pending = int(max_pending)
        self.names = tuple(names)
        self._t: tuple[list[int], ...] = tuple([] for _ in names)      # sorted stamps per stream
        self._p: tuple[list[Any], ...] = tuple([] for _ in names)      # payloads, parallel to _t
        self.rules = StampRules(self.names)   # duplicate / late (stamp_rules.py): pending, last emitted, horizon
        self.counts: Counter[str] = Counter()
        self._in_keys = tuple(f"{n}_in" for n in self.names)   # push's counter per stream (not built per sample)

    @property
    def pending(self) -> int:
        return sum(len(ts) for ts in self._t)

    @property
    def horizon_ns(self) -> int | None:
        """Processing stamp of the last emitted item."""
        return self.rules.horizon_ns

    @property
    def watermark_ns(self) -> int | None:
        """Newest stamp pushed."""
        return self.rules.newest_ns

    def push(self, stream: int, t_ns: int, payload: Any = None) -> str:
        """Queue one sample; returns 'ok', 'late' or 'duplicate' (the latter two are dropped)."""
        t_ns = int(t_ns)
        r = self.rules.check(stream, t_ns)
        if r != OK:
            self.counts[f"{self.names[stream]}_{r}"] += 1
            return r
        ts = self._t[stream]
        i = bisect.bisect_left(ts, t_ns)
        ts.insert(i, t_ns)
        self._p[stream].insert(i, payload)
        self.rules.admit(stream, t_ns)
        self.counts[self._in_keys[stream]] += 1
        return OK

    def poll(self, now_ns: int | None = None) -> list[SyncItem]:
        """Emit every item that is final at ``now_ns`` (default: the watermark)."""
        now = self.rules.newest_ns if now_ns is None else int(now_ns)   # the watermark
        if now is None:
            return []
        final_by = now - 2 * self.slop - self.delay   # now >= t + 2 slop + delay, on integers
        # _drain's first test (the earliest pending sample final, or its stream overflowing) done here: most polls
        # (one per target sample) emit nothing, and building the drain was most of their cost
        streams = self._t
        if len(streams) == 2:   # the same test on the two heads (on equal stamps the global one's)
            tg, tl = streams
            first = tg if tg and (not tl or tg[0] <= tl[0]) else tl
            if not first or (first[0] > final_by and len(first) <= self.max_pending):
                return []
            return self._drain_two(lambda t: t <= final_by)
        head = None
        for s, ts in enumerate(streams):
            if ts and (head is None or (ts[0], s) < head):
                head = (ts[0], s)
        if head is None or (head[0] > final_by and len(streams[head[1]]) <= self.max_pending):
            return []
        return self._drain(lambda t: t <= final_by)

    def flush(self) -> list[SyncItem]:
        """Emit everything pending (end of data, or a stream stop)."""
        return self._drain(lambda t: True)

    @classmethod
    def pair(cls, glob: list[Sample], local: list[Sample], slop_ns: int,
             extra: tuple[list[Sample], ...] | list[list[Sample]] = ()) -> list[SyncItem]:
        """The items the rules above make of a *complete* set of samples (each list sorted by stamp, no duplicate
        stamps within a stream; ``extra``: the further local sources' streams) -- what :meth:`flush` emits once
        every one of them has been pushed. Used by :mod:`arrival` to re-pair the samples after a late one; the
        same code as the live path, so both agree."""
        if not extra:   # the two paired streams (every target without further local sources): the short path
            return _pair_two(glob, local, int(slop_ns))
        streams = (glob, local, *extra)
        s = cls(slop_ns, 0, max_pending=max(1, *(len(x) for x in streams)),
                names=_NAMES + tuple(f"local{k}" for k in range(1, len(extra) + 1)))
        s._t = tuple([x.t_ns for x in xs] for xs in streams)
        s._p = tuple([x.payload for x in xs] for xs in streams)
        return s._drain(lambda t: True)

    def _pop(self, stream: int, i: int) -> Sample:
        t = self._t[stream].pop(i)
        return Sample(t, self._p[stream].pop(i))

    def _nearest(self, stream: int, t_ns: int) -> int | None:
        """Index of the pending sample of ``stream`` nearest to t_ns (earlier one on ties)."""
        ts = self._t[stream]
        if not ts:
            return None
        i = bisect.bisect_left(ts, t_ns)   # ts[i - 1] < t_ns <= ts[i]
        if i == 0:
            return 0
        if i == len(ts):
            return i - 1
        return i - 1 if t_ns - ts[i - 1] <= ts[i] - t_ns else i   # a tie: the earlier (smaller) stamp

    def _drain(self, final) -> list[SyncItem]:
        """Emit items while the earliest pending sample is final (``final(t)``) or its stream overflows."""
        if len(self._t) == 2:
            return self._drain_two(final)
        return self._drain_any(final)

    def _drain_any(self, final) -> list[SyncItem]:
        """:meth:`_drain` for any number of streams (the reference of :meth:`_drain_two`)."""
        out: list[SyncItem] = []
        while True:
            heads = [(ts[0], s) for s, ts in enumerate(self._t) if ts]
            if not heads:
                break
            t_e, s_e = min(heads)  # earliest; on equal stamps the global one first (it pairs anyway)
            overflow = len(self._t[s_e]) > self.max_pending
            if not (final(t_e) or overflow):
                break
            if overflow and not final(t_e):
                self.counts["forced_by_overflow"] += 1
            e = self._pop(s_e, 0)
            if s_e >= 2:   # a further local source: never paired (module docstring)
                item = SyncItem(e.t_ns, None, e, s_e - 1)
                self.rules.release(item)
                self.counts[f"{self.names[s_e]}_alone"] += 1
                out.append(item)
                continue
            other = 1 - s_e
            j = self._nearest(other, t_e)
            partner = None
            if j is not None and abs(self._t[other][j] - t_e) < self.slop:
                t_b = self._t[other][j]
                k = self._nearest(s_e, t_b)  # a closer competitor of e's own stream?
                if k is None or abs(self._t[s_e][k] - t_b) >= abs(t_b - t_e):
                    partner = self._pop(other, j)
            g, loc = (e, partner) if s_e == GLOBAL else (partner, e)
            item = SyncItem(max(x.t_ns for x in (g, loc) if x is not None), g, loc)
            self.rules.release(item)
            self.counts["pairs" if partner is not None else f"{_NAMES[s_e]}_alone"] += 1
            out.append(item)
        return out

    def _drain_two(self, final) -> list[SyncItem]:
        """:meth:`_drain_any` with the global and the first local stream only: the same rules, decisions, counts.

        Why: every target sample polls, and the general drain (a list of heads, a min over tuples, two nearest
        searches) cost as much as the rest of the synchronizer. With two streams the earliest head ``e`` is the
        minimum of all pending stamps, so the other stream's nearest candidate is its head (``_nearest`` of a
        stamp at or before every one of them); only the closer-competitor search is left. test_eval_hot_paths.py
        pins it to the general drain on random streams."""
        out: list[SyncItem] = []
        t_s, p_s = self._t, self._p
        counts, release, max_pending, slop = self.counts, self.rules.release, self.max_pending, self.slop
        while True:
            tg, tl = t_s
            if tg and (not tl or tg[0] <= tl[0]):   # min of (stamp, stream): on equal stamps the global one
                s_e = GLOBAL
            elif tl:
                s_e = LOCAL
            else:
                break
            own = t_s[s_e]
            t_e = own[0]
            overflow = len(own) > max_pending
            is_final = final(t_e)
            if not (is_final or overflow):
                break
            if overflow and not is_final:
                counts["forced_by_overflow"] += 1
            other = 1 - s_e
            own.pop(0)
            e = Sample(t_e, p_s[s_e].pop(0))
            oth = t_s[other]
            partner = None
            if oth and oth[0] - t_e < slop:   # oth[0] >= t_e: the nearest, at |oth[0] - t_e|
                t_b = oth[0]
                k = self._nearest(s_e, t_b)   # a closer competitor of e's own stream?
                if k is None or abs(own[k] - t_b) >= t_b - t_e:
                    oth.pop(0)
                    partner = Sample(t_b, p_s[other].pop(0))
            if partner is None:
                item = SyncItem(t_e, e, None) if s_e == GLOBAL else SyncItem(t_e, None, e)
                key = _ALONE[s_e]
            else:
                t_i = max(t_e, t_b)
                item = SyncItem(t_i, e, partner) if s_e == GLOBAL else SyncItem(t_i, partner, e)
                key = "pairs"
            release(item)
            counts[key] += 1
            out.append(item)
        return out


_ALONE = tuple(f"{n}_alone" for n in _NAMES[:2])   # _drain's counter of an unpaired global / local sample


def _pair_two(glob: list[Sample], local: list[Sample], slop: int) -> list[SyncItem]:
    """:meth:`ApproxSync.pair` of two streams: the rules of ``_drain`` with a read position per stream.

    Why not ``_drain``: fusion on arrival pairs a window of the history again for every sample it takes in, and
    building a synchronizer per sample (its stamp rules, counters, list pops) was a third of the node's input path
    at 1 kHz + 1 kHz. The rules collapse here because the earliest head ``e`` is the global minimum: every pending
    sample of the other stream is at or after it, so its nearest candidate is the other stream's head, and a closer
    competitor of ``e``'s own stream is the pending one nearest that head. test_synchronizer.py pins the equality
    with ``_drain`` on random streams.
    """
    streams = (glob, local)
    ts = ([x.t_ns for x in glob], [x.t_ns for x in local])
    pos = [0, 0]
    n = (len(glob), len(local))
    out: list[SyncItem] = []
    while pos[0] < n[0] or pos[1] < n[1]:
        # earliest head; on equal stamps the global one first (it pairs anyway)
        s_e = GLOBAL if pos[1] >= n[1] or (pos[0] < n[0] and ts[0][pos[0]] <= ts[1][pos[1]]) else LOCAL
        o = 1 - s_e
        e = streams[s_e][pos[s_e]]
        pos[s_e] += 1
        partner = None
        if pos[o] < n[o]:
            t_b = ts[o][pos[o]]
            d = t_b - e.t_ns   # >= 0: e is the earliest pending sample
            if d < slop:
                own, lo = ts[s_e], pos[s_e]
                i = bisect.bisect_left(own, t_b, lo)
                closer = (i < n[s_e] and own[i] - t_b < d) or (i - 1 >= lo and t_b - own[i - 1] < d)
                if not closer:
                    partner = streams[o][pos[o]]
                    pos[o] += 1
        g, loc = (e, partner) if s_e == GLOBAL else (partner, e)
        out.append(SyncItem(e.t_ns if partner is None else max(e.t_ns, partner.t_ns), g, loc))
    return out
