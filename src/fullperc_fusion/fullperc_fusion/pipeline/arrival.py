"""Fusion on arrival with rewind-and-replay: no reorder wait, and the same estimates as ordered processing.

Why: the ordered :class:`~.ordered.TargetPipeline` waits ``2·slop + reorder_delay`` (58 ms by default) before it
fuses a sample, because a partner or an older sample may still arrive. A tool moving at 0.1 m/s is millimetres
away from such a pose. :class:`ArrivalPipeline` fuses every sample the moment it arrives (predict to its stamp,
update, output) and keeps a bounded history -- ``history`` (default 0.2 s) of items, each with the snapshot of
every filter before it -- so a sample that arrives late (out of order, or the approximate-time partner of a sample
already fused) rewinds the filters to the state before the first item it changes and replays from there. This is
what robot_localization's history does, for the same reason.

How (every rule is the synchronizer's, :class:`~synchronizer.ApproxSync`, so pairs are the same as ordered):

* A new target sample at t can only change the pairing of items whose first sample is stamped at or after
  ``t - 2·slop`` (the pairing of a sample looks at stamps up to 2·slop after it, see synchronizer.py). Those items'
  samples plus the new one are paired again with :meth:`ApproxSync.pair`; the first item that differs from the
  history is where the replay starts: the live lane is restored whole from that entry's snapshot
  (:meth:`~.lane.FilterLane.restore`) and the items from there on are processed with
  ``TargetPipeline._process_item`` -- the very function ordered processing uses. Usually only the new item is
  processed; a partner that completes a pair replays one or two items -- unless the first sample of the pair
  waited for it (``partner_wait``, :mod:`.partner_hold`): a sample whose partner is due is held up to that long
  and then fused with it in one re-pairing (:meth:`ArrivalPipeline._fuse`), so the pair is fused once.
* Items leave the history once their first stamp is more than ``history`` older than the newest sample: their
  outputs are then final (:meth:`ArrivalPipeline.take_final`). A sample older than the last item that left
  (``late``) or with a stamp its stream already had (``duplicate``) is dropped, counted and described naming
  source and stamp: the rules of :mod:`.stamp_rules`, which the ordered pipeline's synchronizer applies too, here
  with the history, so stamps that went back for good restart the timeline instead of stalling.
* Static links: the ordered pipeline maps an item into ``base`` with the links in use when it processes it, i.e.
  when the newest stamp has passed ``t_first + 2·slop + reorder_delay``. The arrival pipeline remembers that
  moment per item (the links it was "resolved" with) and replays the unresolved items when the links change, so a
  link estimate finished mid-stream gives the same estimates as ordered processing. ``reorder_delay`` has no
  other role here.
* Counters that processing increments (``items``, ``waiting_for_links``, ...) are rolled back on a rewind, so a
  replay does not count twice. A TrackingQuality that arrives after its pose (``push_omc_quality``) replays the
  item when the primary filter uses the measurement models (``fullperc``).

Filters: two lanes (:class:`~.lane.FilterLane`). Only the primary filter (``filters[0]``, the live lane ``lane``)
is fused on arrival and replayed. The side-by-side filters (the others, for comparison; the lane ``side``) are
fused when an item leaves the history, in stamp order like ordered processing -- no replay, so they cost what they
cost in ordered processing (replaying every filter would nearly double the node's CPU with the paper's four beside
the primary) -- and their outputs are final, ``history`` behind; their counters and problems are not kept. With
``defer_side`` (fusion_node) that work waits until :meth:`ArrivalPipeline.side_outputs` asks for it -- the node does,
an item at a time, once the wake-up's live outputs are published and while no input waits --, or until a fusion
finds it more than ``side_lag`` (``min(history, SIDE_LAG_MAX_NS)``) behind the history, whichever comes first. So
a sample's live output waits for at most one item's side-by-side work, not for every due item's (with every filter
side by side that work is as much CPU as the live path: ``bench/bench_e2e_latency.py``), and a node short of CPU
still does it, ``side_lag`` late. The results are the same bit for bit (``test_arrival_defer.py``); only when they
are computed moves: what the work reads besides the item and its own lane -- the links the item was resolved with
(its view), the rig and base poses (:class:`~.frame_chain.FrameChain`'s last 256 per body) and the OMC qualities
(kept 1 s) -- is still there ``history + side_lag`` later.

Outputs. :meth:`poll` returns, in stamp order, the primary filter's outputs of every item (re)processed since the
last poll whose stamp is newer than the last one returned: the live estimate, stamps strictly increasing (what
fusion_node publishes on pose, pose_cov, status and /tf); then the side-by-side filters' outputs of the items that
left the history meanwhile. A correction of an item already returned is not returned again; it is part of the
next item's estimate. :meth:`take_final` returns the outputs of
the items that left the history: these equal ordered processing of the same samples (test_arrival.py) whenever
every sample arrived within ``history`` -- the offline evaluator's result (evaluation/replay.py runs the ordered
pipeline). :meth:`flush` (end of data, idle) ends the history: everything in it becomes final.

Further local sources (:mod:`sources`): one more stream each, never paired (synchronizer.py); the re-pairing
window, the duplicate / late rules and the link views cover their samples and chains the same way, so the final
estimates equal ordered processing with them too (test_arrival.py).

Cost: a snapshot is a few list copies per filter (paper_fast.ClosedFormFilter.snapshot; every filter has one, the
Filter protocol) and a copy of the lane's state; a rewind restores one and processes the replayed items again.
"""

from __future__ import annotations

import bisect

from fullperc_fusion.pipeline.history import Entry, History, Outbox
from fullperc_fusion.pipeline.lane import FilterLane
from fullperc_fusion.pipeline.link_views import LinkViews, View
from fullperc_fusion.pipeline.ordered import FusedOutput, TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.partner_hold import PartnerHold
from fullperc_fusion.pipeline.problems import Problems
from fullperc_fusion.pipeline.stamp_rules import DUPLICATE, LATE, LATE_SOURCE_SPAN_NS, OK, RESTART, StampRules
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync, Sample, SyncItem

__all__ = ["LATE_SOURCE_SPAN_NS", "PROCESSING_MODES", "ArrivalPipeline", "make_pipeline"]

PROCESSING_MODES = ("arrival", "ordered")
SIDE_LAG_MAX_NS = 100_000_000   # deferred side-by-side work falls at most this far behind the history (docstring)


def _key(item: SyncItem) -> tuple[int | None, int | None, int]:
    return (None if item.glob is None else item.glob.t_ns, None if item.local is None else item.local.t_ns,
            item.source)


def _stream(item: SyncItem) -> int:
    """The synchronizer stream of the item's local sample: 1 + its local source index."""
    return LOCAL + item.source


class ArrivalPipeline(TargetPipeline):
    """:class:`TargetPipeline` with processing on arrival; see the module docstring. Same input API."""

    CONSTANT = (*TargetPipeline.CONSTANT, "_resolve_ns", "_side_lag_ns", "defer_side")   # defer_side: set once
    LANES = ("lane", "side")   # the live lane (rewound: each history entry holds its snapshot) and the side-by-side
    # the rewind's own bookkeeping, kept by it: the stamp rules (the samples taken stay taken; a rewind pairs them
    # again), the history, the outputs not handed out yet, the views of the static links
    # hold: samples not fused yet; _side_due: items out of the history whose side-by-side work waits (defer_side)
    KEPT = (*TargetPipeline.KEPT, "rules", "history", "outbox", "views", "hold", "_side_due")

    def __init__(self, config: TargetConfig) -> None:
        super().__init__(config)
        # lanes: the primary filter (filters[0]) is fused on arrival; the side-by-side ones when an item leaves the
        # history (module docstring)
        first, *others = config.filters
        made = self.lane.filters
        self.side = FilterLane({n: made[n] for n in others})
        self.lane = FilterLane({first: made[first]})
        self.rules = StampRules(self.sync.names, config.history_ns)
        self.history = History()
        self.outbox = Outbox()
        self.views = LinkViews([self.chain, *self.extra_chains])
        self.hold = PartnerHold(config.slop_ns, config.partner_wait_ns)
        self._resolve_ns = 2 * config.slop_ns + config.delay_ns
        self.defer_side = False   # fusion_node: the side-by-side lane's work waits for side_outputs (docstring)
        self._side_lag_ns = min(config.history_ns, SIDE_LAG_MAX_NS)
        self._side_due: list[Entry] = []

    def lanes(self) -> tuple[FilterLane, ...]:
        return self.lane, self.side

    @property
    def last_output(self) -> dict[str, FusedOutput]:
        """The newest output of each filter: the primary's live one, the side-by-side filters' final ones."""
        return {**self.lane.state.last_output, **self.side.state.last_output}

    # ---- input ------------------------------------------------------------------------------------------------
    def observe_omc(self, body: str, t_ns: int, T) -> None:
        super().observe_omc(body, t_ns, T)
        if body != self.config.chain.omc_target:
            self._after_link_sample([k for k, ch in enumerate(self.views.chains)
                                     if body == ch.cfg.omc_rig and ch.cfg.local_chain == "tracked"], t_ns)

    def observe_ots(self, tool: str, t_ns: int, T) -> None:
        super().observe_ots(tool, t_ns, T)
        c = self.config.chain
        if tool == c.ots_base and tool != c.ots_target:
            self._after_link_sample([0] if c.local_chain == "direct" else [], t_ns)

    def observe_local(self, k: int, tool: str, t_ns: int, T) -> None:
        super().observe_local(k, tool, t_ns, T)   # k == 0: observe_ots above
        c = self.extra_chains[k - 1].cfg if k else None
        if c is not None and tool == c.ots_base and tool != c.ots_target:
            self._after_link_sample([k] if c.local_chain == "direct" else [], t_ns)

    def push_omc_quality(self, body: str, t_ns: int, quality: dict) -> None:
        """The quality of a sample already fused (it came after its pose): replay from its item, so the model
        covariance it gives is used as in ordered processing (only when the live lane uses the models)."""
        super().push_omc_quality(body, t_ns, quality)
        if body != self.config.chain.omc_target or not self.lane.models:
            return
        h = self.history
        i = h.index(int(t_ns) - self.config.slop_ns)
        while i < len(h) and h.tes[i] <= t_ns:
            g = h.entries[i].item.glob
            if g is not None and g.t_ns == t_ns:
                self._replay_from(i)
                return
            i += 1

    def apply_calibration(self, cal, source: str) -> None:
        super().apply_calibration(cal, source)
        self._after_link_sample([], 0)

    def enqueue(self, stream: int, t_ns: int, payload, what: str) -> str:
        """:meth:`TargetPipeline.enqueue` on arrival: the sample is paired with the history's samples near it and
        fused at once, rewinding to the first item it changes (module docstring)."""
        t, rules = t_ns, self.rules
        r = rules.check(stream, t)
        if r in (DUPLICATE, LATE):
            self.diag.report(r, rules.message(r, what, t), t)
            self.counts[f"{rules.names[stream]}_{r}"] += 1
            return r
        if r == RESTART:
            self._restart_timeline(what, t)
        rules.admit(stream, t)
        self.counts[f"{rules.names[stream]}_in"] += 1
        batch = self.hold.offer(stream, t, payload)   # empty: it waits for its partner (partner_hold.py)
        if batch:
            self._fuse(batch)
        return OK

    def _fuse(self, batch: list[tuple[int, int, object]]) -> None:
        """Fuse the samples ``(stream, t, payload)`` of ``batch``, admitted by the stamp rules: paired again with
        the history's samples near them, in one re-pairing, and fused from the first item they change on. Deferred
        side-by-side work more than ``side_lag`` behind the history comes first (module docstring)."""
        self._commit_due(self.rules.newest_ns - self.rules.history_ns - self._side_lag_ns)
        h = self.history
        k = h.index(min(t for _, t, _ in batch) - 2 * self.config.slop_ns)
        old, names = h.entries[k:], self.rules.names
        if len(names) == 2:   # global + one local source: the samples of the window per stream, directly
            streams: list[list[Sample]] = [[e.item.glob for e in old if e.item.glob is not None],
                                           [e.item.local for e in old if e.item.local is not None]]
        else:
            streams = [[] for _ in names]
            for e in old:
                if e.item.glob is not None:
                    streams[GLOBAL].append(e.item.glob)
                if e.item.local is not None:
                    streams[_stream(e.item)].append(e.item.local)
        for stream, t, payload in batch:
            bisect.insort(streams[stream], Sample(t, payload), key=lambda s: s.t_ns)
        items = ApproxSync.pair(streams[GLOBAL], streams[LOCAL], self.config.slop_ns, streams[2:])
        j = 0
        while j < len(old) and j < len(items) and _key(old[j].item) == _key(items[j]):
            j += 1
        views = {_key(e.item): e.view for e in old[j:] if e.view is not None}   # an unchanged item keeps its links
        self._rewind(k + j)
        for it in items[j:]:
            self._process_entry(it, views.get(_key(it)))
        self._resolve_and_commit()

    def _release(self, everything: bool = False) -> None:
        """Fuse the samples whose wait for a partner is over (``everything``: every waiting one)."""
        batch = self.hold.due(everything)
        if batch:
            self._fuse(batch)

    def _restart_timeline(self, what: str, t: int) -> None:
        """Samples all behind the history, their stamps spanning more than ``history`` (:mod:`.stamp_rules`): the
        history becomes final, the filters start again, and the samples are fused and output from here on -- the
        node never stalls."""
        self.diag.report("timeline_restart", self.rules.message(RESTART, what, t), t)
        self._release(everything=True)   # what waits belongs to the old timeline
        self.hold.restart()
        self._resolve_and_commit(everything=True)
        self._commit_due()   # the old timeline's side-by-side work, before the reset
        # the live outputs not yet polled belong to the old timeline: gated against it now and handed out first by
        # the next poll; left in fresh, the hour-ahead one would go out after the new timeline's outputs of the
        # same poll and hold back every later output (stamps an hour older) for good
        self.outbox.carried = self.poll()
        self.outbox.published_ns = None
        self.rules.restart()
        self.plausibility.restart()   # the new timeline's first sample of each source is accepted as its first
        self.lane.reset()
        self.side.reset()

    def _after_link_sample(self, lookups: list[int], t: int) -> None:
        """A base / rig sample: replay what the ordered pipeline would map with new links or a nearer rig pose.
        ``lookups``: the local sources (index) whose chain looks this body up live (tracked rig, direct base)."""
        h = self.history
        start = None
        if self.views.refresh():
            start = next((i for i, e in enumerate(h.entries) if e.view is None), None)
        for k in lookups:   # tracked: nearest rig pose within rig_max_age; direct: the base tool of the same frame
            c = self.views.chains[k].cfg
            age = c.rig_max_age_ns if c.local_chain == "tracked" else 0
            i = h.index(t - age - self.config.slop_ns)
            while i < len(h) and (start is None or i < start):
                it = h.entries[i].item
                if it.local is not None and it.source == k and abs(it.local.t_ns - t) <= age:
                    start = i
                    break
                i += 1
        if start is not None:
            self._replay_from(start)

    # ---- history ----------------------------------------------------------------------------------------------
    def _rewind(self, i: int) -> None:
        """Drop the entries from index ``i`` on and restore the live lane as it was before entry ``i``."""
        if i >= len(self.history):
            return
        self.lane.restore(self.history.entries[i].snap)
        gone = self.history.cut(i)
        for e in gone:
            self.counts.subtract(e.delta)
            e.alive = False
        self.counts["replayed_items"] += len(gone)
        self.counts["rewinds"] += 1

    def _replay_from(self, i: int) -> None:
        redo = [(e.item, e.view) for e in self.history.entries[i:]]
        self._rewind(i)
        for it, v in redo:
            self._process_entry(it, v)

    def _process_entry(self, item: SyncItem, view: View | None = None) -> None:
        te = min(s.t_ns for s in (item.glob, item.local) if s is not None)
        if view is None and te + self._resolve_ns <= self.rules.newest_ns:
            view = self.views.current
        e = Entry(item, te, self.lane.snapshot(), view=view)
        before = dict(self.counts)   # a dict copy: Counter.copy / Counter - Counter were ~5 % of the input path
        was = self.views.apply(view) if view is not None and view is not self.views.current else None
        try:
            e.outs = self._process_item(item, self.lane, self.diag)
        finally:
            if was is not None:
                self.views.apply(was)
        e.delta = {k: v - before.get(k, 0) for k, v in self.counts.items() if v > before.get(k, 0)}
        self.history.append(e)
        self.outbox.fresh.append(e)

    def _resolve_and_commit(self, everything: bool = False) -> None:
        h, newest = self.history, self.rules.newest_ns
        i = h.nres   # entries before are resolved; resolve from there until the first that is not yet
        while i < len(h):
            e = h.entries[i]
            if e.view is None:
                if not (everything or e.te + self._resolve_ns <= newest):
                    break
                e.view = self.views.current
            i += 1
        h.nres = i
        n = 0
        while n < len(h) and (everything or h.entries[n].te < newest - self.rules.history_ns):
            e = h.entries[n]
            if self.defer_side and self.side.filters:
                if e.view is None:   # the links it would have been fused with now
                    e.view = self.views.current
                self._side_due.append(e)
            else:
                self._commit(e)
            self.rules.release(e.item)
            n += 1
        if n:
            h.drop_front(n)

    def _commit(self, e: Entry) -> None:
        """An item that left the history: the side-by-side lane on it; its outputs final."""
        if self.side.filters:
            side = self._side_by_side(e)
            e.outs = e.outs + side
            self.outbox.committed.extend(side)
        self.outbox.final.extend(e.outs)

    def side_outputs(self, most: int | None = None) -> list[FusedOutput]:
        """With ``defer_side``: the side-by-side lane on the items that left the history and wait for it (at most
        ``most`` of them, the oldest), in stamp order, and its outputs -- with those a fusion did meanwhile (what
        :meth:`poll` would have returned with the live ones). Their final outputs are :meth:`take_final`'s from then
        on. Without: the side-by-side outputs committed since the last poll (the work was done as the items left)."""
        self._commit_due(most=most)
        out, self.outbox.committed = self.outbox.committed, []
        return out

    @property
    def side_backlog(self) -> int:
        """Items whose deferred side-by-side work waits for :meth:`side_outputs`."""
        return len(self._side_due)

    def _commit_due(self, before_ns: int | None = None, most: int | None = None) -> None:
        """The deferred side-by-side work of the items stamped before ``before_ns`` (None: every one), at most
        ``most``, oldest first."""
        due = self._side_due
        n = len(due)
        if before_ns is not None:
            n = 0
            while n < len(due) and due[n].te < before_ns:
                n += 1
        if most is not None:
            n = min(n, most)
        if n:
            todo, self._side_due = due[:n], due[n:]
            for e in todo:
                self._commit(e)

    def _side_by_side(self, e: Entry) -> list[FusedOutput]:
        """The side-by-side lane on a final item, in stamp order as ordered processing does, mapped with the links
        the item was resolved with; its counters and problems are not kept (a throwaway :class:`Problems`)."""
        was = None if e.view is None else self.views.apply(e.view)
        try:
            return self._process_item(e.item, self.side, Problems())
        finally:
            if was is not None:
                self.views.apply(was)

    # ---- output -----------------------------------------------------------------------------------------------
    def poll(self, now_ns: int | None = None) -> list[FusedOutput]:
        """The live outputs since the last poll (module docstring), after fusing the samples whose wait for a
        partner is over by the host clock (partner_hold.py); ``now_ns`` is not needed."""
        self._release()
        return self.outbox.poll(self.side.filters)

    @property
    def waiting(self) -> int:
        """Samples waiting for their partner (partner_hold.py): the node's timer polls while there are any."""
        return len(self.hold)

    def flush(self) -> list[FusedOutput]:
        """End of the history: every item in it, and every sample waiting for its partner, becomes final
        (:meth:`take_final`); returns the live outputs."""
        self._release(everything=True)
        self._resolve_and_commit(everything=True)
        self._commit_due()
        return self.poll()

    def take_final(self) -> list[FusedOutput]:
        """Outputs of the items that left the history since the last call (= ordered processing), stamp order."""
        return self.outbox.take_final()

    @property
    def pending(self) -> int:
        """Items in the history (fused, not final yet or their side-by-side work deferred) and samples waiting for
        their partner."""
        return len(self.history) + len(self.hold) + len(self._side_due)

    def stats(self) -> dict:
        d = super().stats()
        d["pending"] = self.pending
        d["processing"] = "arrival"
        d["history_s"] = self.rules.history_ns * 1e-9
        for k in ("rewinds", "replayed_items"):
            d.setdefault(k, 0)
        d["partner_waits"] = self.hold.waited
        return d


def make_pipeline(config: TargetConfig) -> TargetPipeline:
    """The pipeline ``config.processing`` asks for: :class:`ArrivalPipeline` or the ordered TargetPipeline."""
    return ArrivalPipeline(config) if config.processing == "arrival" else TargetPipeline(config)
