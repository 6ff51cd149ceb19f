"""Fusion on arrival with rewind-and-replay: no reorder wait, and the same estimates as ordered processing.

Why: the ordered :class:`~pipeline.TargetPipeline` waits ``2·slop + reorder_delay`` (58 ms by default) before it
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
  history is where the replay starts: its snapshot is restored and the items from there on are processed with
  ``TargetPipeline._process_item`` -- the very function ordered processing uses. Usually only the new item is
  processed; a partner that completes a pair replays one or two items.
* Items leave the history once their first stamp is more than ``history`` older than the newest sample: their
  outputs are then final (:meth:`ArrivalPipeline.take_final`). A sample older than the last item that left
  (``late``) or with a stamp its stream already had (``duplicate``) is dropped, counted and described naming
  source and stamp, exactly like the ordered pipeline's late / duplicate samples.
* Static links: the ordered pipeline maps an item into ``base`` with the links in use when it processes it, i.e.
  when the newest stamp has passed ``t_first + 2·slop + reorder_delay``. The arrival pipeline remembers that
  moment per item (the links it was "resolved" with) and replays the unresolved items when the links change, so a
  link estimate finished mid-stream gives the same estimates as ordered processing. ``reorder_delay`` has no
  other role here.
* Counters that processing increments (``items``, ``waiting_for_links``, ...) are rolled back on a rewind, so a
  replay does not count twice. A TrackingQuality that arrives after its pose (``push_omc_quality``) replays the
  item when the primary filter uses the measurement models (``fullperc``).

Filters. Only the primary filter (``filters[0]``) is fused on arrival and replayed. The side-by-side filters (the
others, for comparison) are fused when an item leaves the history, in stamp order like ordered processing -- no
replay, so they cost what they cost in ordered processing (replaying every filter would nearly double the node's
CPU with the paper's four beside the primary) -- and their outputs are final, ``history`` behind.

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

Cost: a snapshot is a few list copies per filter (fast_filter.ClosedFormFilter.snapshot); a rewind restores one
and processes the replayed items again. Filters without ``snapshot`` / ``restore`` are copied with deepcopy.
"""

from __future__ import annotations

import bisect
import copy
from dataclasses import dataclass, field
from typing import Any

from fullperc_fusion.pipeline.ordered import FusedOutput, TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync, Sample, SyncItem

PROCESSING_MODES = ("arrival", "ordered")
LATE_SOURCE_SPAN_NS = 5_000_000_000   # [ns] of a late source's own (in-order) stamps before it restarts the timeline


@dataclass
class _Entry:
    """One item in the history: what was fused, the state before it, what it output and changed."""

    item: SyncItem
    te: int                                  # stamp of its first sample (the synchronizer's order)
    snap: tuple                              # pipeline state before the item (:meth:`ArrivalPipeline._snap`)
    outs: list[FusedOutput] = field(default_factory=list)
    delta: dict[str, int] = field(default_factory=dict)   # counters the processing incremented (a plain dict:
    #                                                       building a Counter per entry was ~6 % of the live path)
    view: Any = None                         # static links it is resolved with; None: the current ones
    alive: bool = True                       # False once replaced by a rewind


def _key(item: SyncItem) -> tuple[int | None, int | None, int]:
    return (None if item.glob is None else item.glob.t_ns, None if item.local is None else item.local.t_ns,
            item.source)


def _links_signature(links) -> tuple:
    return (id(links.T_omc_base), id(links.T_base_ots), id(links.T_rig_ots), links.generation)


def _stream(item: SyncItem) -> int:
    """The synchronizer stream of the item's local sample: 1 + its local source index."""
    return LOCAL + item.source


def _copy_links(links):
    v = copy.copy(links)
    v.estimates = dict(links.estimates)
    v.sources = dict(links.sources)
    return v


class ArrivalPipeline(TargetPipeline):
    """:class:`TargetPipeline` with processing on arrival; see the module docstring. Same input API."""

    def __init__(self, config: TargetConfig) -> None:
        super().__init__(config)
        self.history_ns = int(config.history_ns)
        self._entries: list[_Entry] = []
        self._tes: list[int] = []                 # entry.te, parallel to _entries (bisect)
        self._names = self.sync.names              # stream names: global, local, further local sources
        self._stamps: tuple[set[int], ...] = tuple(set() for _ in self._names)   # target stamps in the history
        self._last_committed: list[int | None] = [None] * len(self._names)
        self.horizon_ns: int | None = None        # processing stamp of the last item that left the history
        self.newest_ns: int | None = None         # newest target stamp accepted
        self._fresh: list[_Entry] = []            # (re)processed since the last poll
        self._published_ns: int | None = None
        self._carried: list[FusedOutput] = []     # live outputs of the timeline a restart ended, for the next poll
        self._final: list[FusedOutput] = []
        self._nres = 0                            # the first _nres entries are resolved (links fixed)
        self._late_run: int | None = None         # first stamp of a run of samples all behind the history
        self._own_newest: list[int | None] = [None] * len(self._names)   # newest stamp seen per stream
        self._view = None                         # snapshot of the current static links (shallow copy)
        self._sig = self._signature()
        self._new_view()
        self._resolve_ns = 2 * config.slop_ns + config.delay_ns
        # lanes: the primary filter (filters[0]) is fused on arrival; the side-by-side ones when an item leaves the
        # history (module docstring); self.filters is the live lane, _process_item runs whichever is set there
        names = list(self.filters)
        self._lane_final = {n: self.filters[n] for n in names[1:]}
        self.filters = {names[0]: self.filters[names[0]]}
        # model covariances (measurement_models) per lane: the live lane builds them only if its filter uses them
        self._models_live = getattr(self.filters[names[0]], "uses_models", False)
        self._lane_last: tuple = (None, None, None)   # last_local_ns, last_global_ns, last_item_ns of it
        self._committed: list[FusedOutput] = []   # side-by-side outputs not yet returned by poll

    # ---- input ------------------------------------------------------------------------------------------------
    def _chains(self) -> list:
        return [self.chain, *self.extra_chains]

    def push_omc(self, body: str, t_ns: int, pose, cov=None, now_ns: int | None = None, **kw) -> bool:
        ok = super().push_omc(body, t_ns, pose, cov, now_ns=now_ns, **kw)
        c = self.config.chain
        if ok and body != c.omc_target:
            self._after_link_sample([k for k, ch in enumerate(self._chains())
                                     if body == ch.cfg.omc_rig and ch.cfg.local_chain == "tracked"], t_ns)
        return ok

    def push_ots(self, tool: str, t_ns: int, pose, cov=None, now_ns: int | None = None, **kw) -> bool:
        ok = super().push_ots(tool, t_ns, pose, cov, now_ns=now_ns, **kw)
        c = self.config.chain
        if ok and tool == c.ots_base and tool != c.ots_target:
            self._after_link_sample([0] if c.local_chain == "direct" else [], t_ns)
        return ok

    def push_local(self, k: int, tool: str, t_ns: int, pose, cov=None, now_ns: int | None = None) -> bool:
        if k == 0:
            return self.push_ots(tool, t_ns, pose, cov, now_ns)
        ok = super().push_local(k, tool, t_ns, pose, cov, now_ns)
        c = self.extra_chains[k - 1].cfg
        if ok and tool == c.ots_base and tool != c.ots_target:
            self._after_link_sample([k] if c.local_chain == "direct" else [], t_ns)
        return ok

    def push_omc_quality(self, body: str, t_ns: int, quality: dict) -> None:
        """The quality of a sample already fused (it came after its pose): replay from its item, so the model
        covariance it gives is used as in ordered processing (only when the live filter uses the models)."""
        super().push_omc_quality(body, t_ns, quality)
        f = next(iter(self.filters.values()))
        if body != self.config.chain.omc_target or not getattr(f, "uses_models", False):
            return
        i = bisect.bisect_left(self._tes, int(t_ns) - self.config.slop_ns)
        while i < len(self._entries) and self._tes[i] <= t_ns:
            g = self._entries[i].item.glob
            if g is not None and g.t_ns == t_ns:
                self._replay_from(i)
                return
            i += 1

    def apply_calibration(self, cal, source: str) -> None:
        super().apply_calibration(cal, source)
        self._after_link_sample([], 0)

    def _enqueue(self, stream: int, what: str, t: int, payload) -> bool:
        if t in self._stamps[stream] or self._last_committed[stream] == t:
            self._problem("duplicate", f"{what}: duplicate stamp {t} ns; dropped", t)
            self.counts[f"{self._names[stream]}_duplicate"] += 1
            return False
        own = self._own_newest[stream]
        if own is None or t > own:
            self._own_newest[stream] = t
        if self.newest_ns is not None and t < self.newest_ns - self.history_ns:   # behind the history
            # Only a stream that went back against its own stamps says the stamps went back for good; a source
            # whose samples come late but in order (its driver starved on a busy machine: seen 1.3 s behind) is
            # dropped as late -- restarting for it put the output a second back in time. A run of a late source
            # alone restarts only after LATE_SOURCE_SPAN_NS of its stamps (its clock may have been reset while the
            # stream that ran ahead fell silent: the node must not stall).
            span = self.history_ns if own is not None and t < own else max(self.history_ns, LATE_SOURCE_SPAN_NS)
            if self._late_run is None:
                self._late_run = t
            elif t - self._late_run > span:
                self._restart_timeline(what, t)
        else:
            self._late_run = None
        if self.horizon_ns is not None and t < self.horizon_ns:
            self._problem("late", f"{what}: sample at {t} ns is older than the history ({self.history_ns * 1e-9:g} s): "
                                  f"{(self.newest_ns - t) * 1e-9:.3f} s behind the newest sample ({self.newest_ns} ns),"
                                  f" before the last item that left the history ({self.horizon_ns} ns); dropped", t)
            self.counts[f"{self._names[stream]}_late"] += 1
            return False
        self._stamps[stream].add(t)
        self.counts[f"{self._names[stream]}_in"] += 1
        if self.newest_ns is None or t > self.newest_ns:
            self.newest_ns = t
        k = bisect.bisect_left(self._tes, t - 2 * self.config.slop_ns)
        old = self._entries[k:]
        if len(self._names) == 2:   # global + one local source: the samples of the window per stream, directly
            streams: list[list[Sample]] = [[e.item.glob for e in old if e.item.glob is not None],
                                           [e.item.local for e in old if e.item.local is not None]]
        else:
            streams = [[] for _ in self._names]
            for e in old:
                if e.item.glob is not None:
                    streams[GLOBAL].append(e.item.glob)
                if e.item.local is not None:
                    streams[_stream(e.item)].append(e.item.local)
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
        return True

    def _restart_timeline(self, what: str, t: int) -> None:
        """Samples all behind the history, their stamps spanning more than ``history``: the stamps went back for
        good (a bag replayed again, a clock reset, or one stamp far ahead that no clock could check). The history
        becomes final, the filters start again, and the samples are fused and output from here on -- the node
        never stalls."""
        self._problem("timeline_restart", f"{what}: stamps went back to {t} ns, {(self.newest_ns - t) * 1e-9:.3f} s "
                                          f"before the newest ({self.newest_ns} ns), for more than the history; "
                                          "history ended, filters restarted", t)
        self._resolve_and_commit(everything=True)
        # the live outputs not yet polled belong to the old timeline: gated against it now and handed out first by
        # the next poll; left in _fresh, the hour-ahead one would go out after the new timeline's outputs of the
        # same poll and hold back every later output (stamps an hour older) for good
        self._carried = self.poll()
        self.horizon_ns = self.newest_ns = self._published_ns = self._late_run = None
        self._last_committed = [None] * len(self._names)
        self._own_newest = [None] * len(self._names)
        for f in (*self.filters.values(), *self._lane_final.values()):
            f.reset()

    def _signature(self) -> tuple:
        return tuple(_links_signature(ch.links) for ch in self._chains())

    def _after_link_sample(self, lookups: list[int], t: int) -> None:
        """A base / rig sample: replay what the ordered pipeline would map with new links or a nearer rig pose.
        ``lookups``: the local sources (index) whose chain looks this body up live (tracked rig, direct base)."""
        sig = self._signature()
        start = None
        if sig != self._sig:
            self._sig = sig
            self._new_view()
            start = next((i for i, e in enumerate(self._entries) if e.view is None), None)
        for k in lookups:   # tracked: nearest rig pose within rig_max_age; direct: the base tool of the same frame
            c = self._chains()[k].cfg
            age = c.rig_max_age_ns if c.local_chain == "tracked" else 0
            i = bisect.bisect_left(self._tes, t - age - self.config.slop_ns)
            while i < len(self._entries) and (start is None or i < start):
                it = self._entries[i].item
                if it.local is not None and it.source == k and abs(it.local.t_ns - t) <= age:
                    start = i
                    break
                i += 1
        if start is not None:
            self._replay_from(start)

    # ---- history ----------------------------------------------------------------------------------------------
    def _new_view(self) -> None:
        """The links in use now: the primary chain's, or with further local sources a tuple of every chain's."""
        v = _copy_links(self.chain.links)
        self._view = (v, *(_copy_links(ch.links) for ch in self.extra_chains)) if self.extra_chains else v

    def _set_links(self, view) -> tuple | object:
        """Use the links of ``view`` (:meth:`_new_view`); returns what was in use, for :meth:`_set_links` back."""
        chains = self._chains()
        was = tuple(ch.links for ch in chains) if self.extra_chains else self.chain.links
        for ch, links in zip(chains, view if self.extra_chains else (view,), strict=True):
            ch.links = links
        return was

    def _snap(self) -> tuple:
        snaps = tuple(f.snapshot() if hasattr(f, "snapshot") else copy.deepcopy(f) for f in self.filters.values())
        return snaps, self.last_local_ns, self.last_global_ns, dict(self.last_output), self.last_item_ns

    def _restore(self, snap: tuple) -> None:
        snaps, self.last_local_ns, self.last_global_ns, last, self.last_item_ns = snap
        self.last_output = dict(last)
        for (name, f), s in zip(list(self.filters.items()), snaps, strict=True):
            if hasattr(f, "restore"):
                f.restore(s)
            else:
                self.filters[name] = copy.deepcopy(s)

    def _rewind(self, i: int) -> None:
        """Drop the entries from index ``i`` on and restore the state before entry ``i``."""
        if i >= len(self._entries):
            return
        self._restore(self._entries[i].snap)
        for e in self._entries[i:]:
            self.counts.subtract(e.delta)
            e.alive = False
        self.counts["replayed_items"] += len(self._entries) - i
        self.counts["rewinds"] += 1
        del self._entries[i:]
        del self._tes[i:]
        self._nres = min(self._nres, i)

    def _replay_from(self, i: int) -> None:
        items = [e.item for e in self._entries[i:]]
        views = [e.view for e in self._entries[i:]]
        self._rewind(i)
        for it, v in zip(items, views, strict=True):
            self._process_entry(it, v)

    def _process_entry(self, item: SyncItem, view=None) -> None:
        te = min(s.t_ns for s in (item.glob, item.local) if s is not None)
        if view is None and te + self._resolve_ns <= self.newest_ns:
            view = self._view
        e = _Entry(item, te, self._snap(), view=view)
        before = dict(self.counts)   # a dict copy: Counter.copy / Counter - Counter were ~5 % of the input path
        links, models = None, self._models
        if view is not None and view is not self._view:
            links = self._set_links(view)     # the links ordered processing used for this item
        self._models = self._models_live
        try:
            e.outs = self._process_item(item)
        finally:
            self._models = models
            if links is not None:
                self._set_links(links)
        e.delta = {k: v - before.get(k, 0) for k, v in self.counts.items() if v > before.get(k, 0)}
        self._entries.append(e)
        self._tes.append(te)
        self._fresh.append(e)

    def _resolve_and_commit(self, everything: bool = False) -> None:
        i = self._nres   # entries before are resolved; resolve from there until the first that is not yet
        while i < len(self._entries):
            e = self._entries[i]
            if e.view is None:
                if not (everything or e.te + self._resolve_ns <= self.newest_ns):
                    break
                e.view = self._view
            i += 1
        self._nres = i
        n = 0
        while n < len(self._entries) and (everything or self._entries[n].te < self.newest_ns - self.history_ns):
            e = self._entries[n]
            if self._lane_final:
                side = self._side_by_side(e)
                e.outs = e.outs + side
                self._committed.extend(side)
            self._final.extend(e.outs)
            self.horizon_ns = e.item.t_ns if not e.item.source or self.horizon_ns is None \
                else max(self.horizon_ns, e.item.t_ns)   # a further source's lagged item: never back (synchronizer)
            for s, x in ((GLOBAL, e.item.glob), (_stream(e.item), e.item.local)):
                if x is not None:
                    self._stamps[s].discard(x.t_ns)
                    self._last_committed[s] = x.t_ns
            n += 1
        if n:
            del self._entries[:n]
            del self._tes[:n]
            self._nres = max(0, self._nres - n)

    def _side_by_side(self, e: _Entry) -> list[FusedOutput]:
        """The side-by-side filters on a final item, in stamp order as ordered processing does (their own
        last-sample stamps; counters and the live lane untouched)."""
        live = self.filters, self.last_local_ns, self.last_global_ns, self.last_item_ns, self._models
        counts, problem = self.counts.copy(), (self.last_problem, dict(self.problems), self.last_problem_t_ns)
        self.filters = self._lane_final
        self.last_local_ns, self.last_global_ns, self.last_item_ns = self._lane_last
        self._models = any(getattr(f, "uses_models", False) for f in self._lane_final.values())
        links = None if e.view is None else self._set_links(e.view)
        try:
            return self._process_item(e.item)
        finally:
            if links is not None:
                self._set_links(links)
            self._lane_last = self.last_local_ns, self.last_global_ns, self.last_item_ns
            self.filters, self.last_local_ns, self.last_global_ns, self.last_item_ns, self._models = live
            self.counts = counts
            self.last_problem, self.problems, self.last_problem_t_ns = problem

    # ---- output -----------------------------------------------------------------------------------------------
    def poll(self, now_ns: int | None = None) -> list[FusedOutput]:
        """The live outputs since the last poll (module docstring); ``now_ns`` is not needed (nothing waits)."""
        out, self._carried = self._carried, []
        for e in sorted((e for e in self._fresh if e.alive and e.outs), key=lambda e: e.item.t_ns):
            live = [o for o in e.outs if o.filter not in self._lane_final]
            # gate on the outputs' own stamps, not the item's: a pair re-run when the partner of a published sample
            # arrives has a newer item stamp, but if the chain cannot map the partner (links not known yet) its
            # output is the estimate already published, with the same stamp -- it must not go out twice
            t = max((o.t_ns for o in live), default=None)
            if t is not None and (self._published_ns is None or t > self._published_ns):
                out.extend(live)
                self._published_ns = t
        self._fresh = []
        out.extend(self._committed)
        self._committed = []
        return out

    def flush(self) -> list[FusedOutput]:
        """End of the history: every item in it becomes final (:meth:`take_final`); returns the live outputs."""
        self._resolve_and_commit(everything=True)
        return self.poll()

    def take_final(self) -> list[FusedOutput]:
        """Outputs of the items that left the history since the last call (= ordered processing), stamp order."""
        out, self._final = self._final, []
        return out

    @property
    def pending(self) -> int:
        """Items in the history (fused, not final yet)."""
        return len(self._entries)

    def stats(self) -> dict:
        d = super().stats()
        d["pending"] = self.pending
        d["processing"] = "arrival"
        d["history_s"] = self.history_ns * 1e-9
        for k in ("rewinds", "replayed_items"):
            d.setdefault(k, 0)
        return d


def make_pipeline(config: TargetConfig) -> TargetPipeline:
    """The pipeline ``config.processing`` asks for: :class:`ArrivalPipeline` or the ordered TargetPipeline."""
    return ArrivalPipeline(config) if config.processing == "arrival" else TargetPipeline(config)
