"""Per-target fusion pipeline: raw device poses in, fused poses out. ROS-free.

This class is *ordered* processing: every sample waits ``2·slop + delay`` in the synchronizer, then items are
fused in stamp order. The offline evaluator runs it; ``fusion_node`` runs :class:`arrival.ArrivalPipeline` by
default (``processing: arrival``), the same processing without the wait, whose final estimates equal this class's
(arrival.py); with ``processing: ordered`` the node runs this class, so a bag replayed through it gives exactly
what the node published::

    pipe = TargetPipeline(TargetConfig(name="tool", filters=("cbkf", "kf")))
    for each device sample, in arrival order:
        pipe.push_omc(body, t_ns, T_omc_body)      # 4x4 array or (p, q_xyzw); metres, stamps int ns
        pipe.push_ots(tool, t_ns, T_ots_tool, cov) # optional 6x6 pose covariance (see below)
        for out in pipe.poll():                    # or poll(now_ns) with a live host clock
            ...                                    # FusedOutput: one per filter per processed item
    outputs = pipe.flush()                         # end of data

Data flow: every pose is validated (:func:`.plausibility.validate`: NaN/inf, non-unit quaternions
and bad stamps are rejected, counted and described in :attr:`TargetPipeline.last_problem`, never
raised), and so is its covariance when one is given (:func:`~fullperc_fusion.filters.api.check_covariance`: non-finite,
non-symmetric or not positive definite -> ``rejected_cov``, the sample is dropped, never fused); base / rig
samples feed the static links of the :class:`~frame_chain.FrameChain`; a target sample further from its source's last
accepted one than the target can move is dropped as ``rejected_jump`` (:class:`.plausibility.Plausibility`); target
samples go through the :class:`~synchronizer.ApproxSync` as raw device poses and are mapped into
``base`` only when they come out (so a base-marker sample of the same OTS frame that arrived a little
later can still be used for eq. 2); each item then becomes one :class:`~fullperc_fusion.filters.api.Measurement`
per source (:mod:`.measure`) and every configured filter (:mod:`~fullperc_fusion.filters.registry`) is predicted to
the item and updated with them.

A device covariance is given in the device frame (``omc`` / ``ots``), ROS order [x y z, rx ry rz], the
rotation part about the device frame's axes (the :mod:`~fullperc_fusion.filters.api` convention with that frame
as parent).
It is mapped into ``base`` with the rotation R_A of the chain, T_base_tool = A T_dev_tool:
C_base = J C J^T, J = diag(R_A, R_A) (the links are taken as exact here). Without one the filters use their
fixed noise, as the paper does. The output's orientation covariance is the rotation block of the
orientation source's measurement when it has one, else ``orientation_std_*``.

Time guard: a sample stamped more than ``max_future_ns`` ahead of ``now_ns`` -- the clock the caller passes to
``push_*`` (fusion_node: its node clock, which follows /clock under ``use_sim_time``) -- is rejected
(``rejected_future``, message naming source, stamp and how far ahead) before it reaches the chain or the
synchronizer: one such stamp would otherwise move the synchronizer's watermark and horizon ahead and every later
sample would be "late". Without ``now_ns`` (offline replay of a bag, the evaluator) nothing is checked.

Once the local link is set (``static`` / ``direct`` chains), the OTS's sightings of the base marker also feed a
:class:`~fullperc_fusion.calibration.monitor.LinkMonitor`: a bump of the Vega or of the reference marker sets
``link_bumped`` in every output and, with ``monitor.recalibrate``, re-estimates the static links in calibrate mode
(the old links stay in use meanwhile). A refused calibrate-mode collection is counted as ``calibration_refused``
with its reason.

The paper's filters do not filter the orientation (the paper fuses position): their output's orientation is that
of the best source in the item -- the local (OTS) one when present, else the global one -- mapped into ``base``,
and ``orientation_source`` says which. The ``omc`` pass-through always carries the global one. A filter that
declares ``orientation`` and whose Step carries ``q`` (``fullperc``) outputs its fused orientation and its own 6x6
pose covariance, with ``orientation_source`` = both bits.

Model covariances: a filter that declares ``models`` (its registry entry's
:class:`~fullperc_fusion.filters.api.Capabilities`; ``fullperc``) is fed the same samples with the covariances of
:mod:`measurement_models` -- the OMC's from its TrackingQuality (``push_omc(quality=...)`` or
:meth:`TargetPipeline.push_omc_quality`, matched by stamp) and the view margin at the body in
``TargetConfig.layout``, the local one from the Vega's distance model plus the calibrated link through the lever
arm. The paper's filters get exactly the measurements they got before (``cov`` only when a device gave one).

Frame covariance: the pose covariance a ``models`` filter reports is that of its estimate in the frame the
local chain defines (CBKF's premise, kept by ``fullperc``: the local source is unbiased, the global one carries the
bias). That frame is only as good as the static link T_base_ots it comes through, and no sample tells the filter
the link's own error (every local sample carries the same one). So the output's covariance is

    C_out = P_pose + J(l) C_link J(l)^T,   l = p - p_base_ots   (:func:`measurement_models.link_covariance_at`)

with C_link the covariance of the link in use (a calibrated link, or the average that bridges until it is done:
:func:`calibration.mean_estimate`), for the first local source's ``static`` chain; none for ``tracked`` and
``direct`` chains and for a link given as a parameter (no covariance). The estimate itself is unchanged. Why: on
the twin's ``paper`` bags the raw Vega chain's error has a per-run mean of up to 0.45 mm (the 30-sample bridge link
of a run that starts in BVV) and the filter, averaging hundreds of Vega samples, reported 0.035 mm per axis: 88 % of
its outputs were inside their 95 % bound on that profile's ten seeds, 93 % with the link's covariance
(docs/fullperc_filter.md "The link's covariance and the bridge link").

State (:mod:`.lane`): what fusing an item changes lives in the pipeline's :class:`~.lane.FilterLane` (the filters
and what the pipeline keeps of their run), which fusion on arrival snapshots and restores whole; every other
attribute is declared in :attr:`TargetPipeline.CONSTANT` or :attr:`TargetPipeline.KEPT` (test_pipeline_state.py
holds ``vars(pipe)`` to these names).

Stages (public, for a caller that runs some of them itself -- the batched evaluator, which validates, maps and
filters a whole bag on arrays): ``push_*`` = validation + :meth:`~TargetPipeline.observe_omc` /
:meth:`~TargetPipeline.observe_ots` / :meth:`~TargetPipeline.observe_local` (what a valid pose does to the links
and the link monitor) + :meth:`~TargetPipeline.admit` (a target sample: plausibility, then
:meth:`~TargetPipeline.enqueue` into the synchronizer under the stamp rules, :mod:`.stamp_rules`);
:meth:`~TargetPipeline.poll` = fusing :meth:`~TargetPipeline.poll_items`.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from fullperc_common.transforms import inv_T
from fullperc_fusion.calibration.monitor import LinkMonitor
from fullperc_fusion.calibration.se3_stats import Calibration
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, BadMeasurement, Filter, Step
from fullperc_fusion.filters.measurement_models import link_covariance_at
from fullperc_fusion.filters.registry import make_filter
from fullperc_fusion.pipeline.frame_chain import FrameChain
from fullperc_fusion.pipeline.lane import FilterLane, caps_of
from fullperc_fusion.pipeline.measure import OmcQualities, measurement, model_measurements
from fullperc_fusion.pipeline.plausibility import Plausibility, validate
from fullperc_fusion.pipeline.problems import Problems
from fullperc_fusion.pipeline.sources import fixed_cov, renamed_calibration
from fullperc_fusion.pipeline.stamp_rules import OK
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync, SyncItem
from fullperc_fusion.pipeline.target import FILTER_NAMES, FusedOutput, TargetConfig, rotation_stds

__all__ = ["FILTER_NAMES", "FusedOutput", "TargetConfig", "TargetPipeline"]


class TargetPipeline:
    """Frame chain -> synchronizer -> filters for one target; see the module docstring."""

    # Every attribute of an instance, by what a rewind (arrival.py) does with it; test_pipeline_state.py holds
    # vars(pipe) to exactly these names, so a new attribute has to be placed in one of them (or in the lane).
    CONSTANT: tuple[str, ...] = ("config", "_fixed_global", "_fixed_local", "_rot_stds")   # set here, never changed
    LANES: tuple[str, ...] = ("lane",)   # FilterLane: everything fusing an item changes; a rewind restores it whole
    # state a rewind keeps, the input side: the chains (static links: a replayed item is mapped with the links it
    # was resolved with, arrival.py), the synchronizer, the link monitor and what it was last set from, the OMC
    # qualities (an item fused again needs its quality again), the diagnostics (counters a rewind rolls back by
    # what the rewound items added, arrival.py; reasons are not undone), the accepted samples plausibility compares
    # with (a sample is judged once, on arrival, before the synchronizer: a rewind never judges it again)
    KEPT: tuple[str, ...] = ("chain", "extra_chains", "sync", "monitor", "_monitor_src", "_refusals_seen",
                             "omc_quality", "diag", "plausibility")

    def __init__(self, config: TargetConfig) -> None:
        self.config = config
        self.chain = FrameChain(config.chain)
        self.sync = ApproxSync(config.slop_ns, config.delay_ns, names=config.sources.stream_names)
        src = config.sources
        # further local sources (sources.py): their own chains, fixed covariances per local source index
        self.extra_chains = [FrameChain(x.chain) for x in src.extras if x.chain is not None]
        self._rot_stds = rotation_stds(config)
        self._fixed_global = fixed_cov(src.glob, self._rot_stds[0])
        self._fixed_local = [fixed_cov(x, self._rot_stds[1]) for x in src.locals]
        self.lane = FilterLane({name: make_filter(name, config.params) for name in config.filters})
        self.diag = Problems()
        c = config.chain
        self.monitor = LinkMonitor(config.monitor, "T_base_ots", f"OTS tool '{c.ots_base}'")
        self._monitor_src: np.ndarray | None = None   # the T_base_ots the monitor's reference was made from
        self._refusals_seen = 0
        self.omc_quality = OmcQualities()   # TrackingQuality of the OMC target body by stamp (models lanes only)
        self.plausibility = Plausibility(len(self.sync.names), config.max_speed, config.max_jump,
                                         max(config.history_ns, 2 * config.slop_ns + config.delay_ns))

    # ---- what callers read -----------------------------------------------------------------------------------
    @property
    def filters(self) -> dict[str, Filter]:
        """Name -> filter of the lane fused as items are processed (ordered: every configured filter; arrival: the
        primary). The lane's own dict: an observer added here (the evaluator's taps) is fed like a filter."""
        return self.lane.filters

    @property
    def last_output(self) -> dict[str, FusedOutput]:
        """The newest output of each filter."""
        return self.lane.state.last_output

    @property
    def counts(self) -> Counter[str]:
        """Events and problems by kind: ``items``, ``late``, ``rejected_cov`` ..."""
        return self.diag.counts

    @property
    def problems(self) -> dict[str, str]:
        """The newest reason per kind of problem (a key of :attr:`counts`)."""
        return self.diag.by_kind

    @property
    def last_problem(self) -> str:
        """The most recent reason something was rejected or skipped."""
        return self.diag.last

    @property
    def last_problem_t_ns(self) -> int | None:
        return self.diag.last_t_ns

    def lanes(self) -> tuple[FilterLane, ...]:
        """Every filter lane of this pipeline (module docstring of :mod:`.lane`)."""
        return (self.lane,)

    # ---- input ------------------------------------------------------------------------------
    def report_problem(self, key: str, msg: str, t_ns: int | None) -> None:
        """Count a problem of kind ``key`` (a key of :attr:`counts`) and make ``msg`` the newest one: the pipeline's
        own rejections, and a caller's (``fusion_node``'s publish errors) the same way."""
        self.diag.report(key, msg, t_ns)

    def push_omc(self, body: str, t_ns: int, pose, cov=None, now_ns: int | None = None,
                 quality: dict | None = None) -> bool:
        """One OMC sample of ``body`` (pose of the body in ``omc``, optional 6x6 covariance in ``omc``).
        False if rejected or unused. ``now_ns``: the caller's clock, for the time guard (module docstring).
        ``quality``: the sample's TrackingQuality fields (:meth:`push_omc_quality`), for the OMC model."""
        c = self.config.chain
        if quality is not None:
            self.push_omc_quality(body, t_ns, quality)
        if body not in (c.omc_target, c.omc_base, c.omc_rig) and \
                not any(body in (ch.cfg.omc_base, ch.cfg.omc_rig) for ch in self.extra_chains):
            return False
        v = validate(f"OMC body '{body}'", t_ns, pose, cov, now_ns, self.config.max_future_ns, self.diag)
        if v is None:
            return False
        t, T, C = v
        self.observe_omc(body, t, T)
        if body == c.omc_target:
            return self.admit(GLOBAL, t, T, C, f"OMC body '{body}'")
        return True

    def push_ots(self, tool: str, t_ns: int, pose, cov=None, now_ns: int | None = None) -> bool:
        """One OTS sample of ``tool`` (pose of the tool in ``ots``, optional 6x6 covariance in ``ots``).
        False if rejected or unused. ``now_ns``: the caller's clock, for the time guard (module docstring)."""
        c = self.config.chain
        if tool not in (c.ots_target, c.ots_base):
            return False
        v = validate(f"OTS tool '{tool}'", t_ns, pose, cov, now_ns, self.config.max_future_ns, self.diag)
        if v is None:
            return False
        t, T, C = v
        self.observe_ots(tool, t, T)
        if tool == c.ots_target:
            return self.admit(LOCAL, t, T, C, f"OTS tool '{tool}'")
        return True

    def push_local(self, k: int, tool: str, t_ns: int, pose, cov=None, now_ns: int | None = None) -> bool:
        """One sample of local source ``k`` (0: the first, :meth:`push_ots`; k >= 1: a further one, its own chain
        and synchronizer stream, never paired; sources.py). False if rejected or unused."""
        if k == 0:
            return self.push_ots(tool, t_ns, pose, cov, now_ns)
        ch = self.extra_chains[k - 1]
        if tool not in (ch.cfg.ots_target, ch.cfg.ots_base):
            return False
        what = f"{self.config.sources.locals[k].name} tool '{tool}'"
        v = validate(what, t_ns, pose, cov, now_ns, self.config.max_future_ns, self.diag)
        if v is None:
            return False
        t, T, C = v
        self.observe_local(k, tool, t, T)
        if tool == ch.cfg.ots_target:
            return self.admit(1 + k, t, T, C, what)
        return True

    def push_omc_quality(self, body: str, t_ns: int, quality: dict) -> None:
        """The TrackingQuality of one OMC sample of ``body`` (``fit_error`` [m], ``markers_used``), before or after
        its pose: it is looked up by stamp when the sample is fused, for the OMC model covariance
        (:func:`~fullperc_fusion.filters.measurement_models.omc_covariance`; only for filters that declare
        ``models``). Other bodies are ignored."""
        if body == self.config.chain.omc_target and any(lane.models for lane in self.lanes()):
            self.omc_quality.add(t_ns, quality)

    # ---- stages of push_* (module docstring, "Stages") ---------------------------------------------------------
    def observe_omc(self, body: str, t_ns: int, T: np.ndarray) -> None:
        """What a valid OMC pose of ``body`` (``T``: 4x4 in ``omc``, already through :func:`pose_to_T`) does to the
        static links of every chain that uses it; a refused link calibration is counted (``calibration_refused``)."""
        c = self.config.chain
        self.chain.observe_omc(body, t_ns, T)
        for ch in self.extra_chains:
            if body in (ch.cfg.omc_base, ch.cfg.omc_rig):
                ch.observe_omc(body, t_ns, T)
        if body in (c.omc_base, c.omc_rig):
            self._links_changed(t_ns)

    def observe_ots(self, tool: str, t_ns: int, T: np.ndarray) -> None:
        """What a valid OTS pose of ``tool`` (4x4 in ``ots``) does to the primary chain's links and, for the base
        tool, to the link monitor (``link_bumped_checks``, ``recalibrations``)."""
        self.chain.observe_ots(tool, t_ns, T)
        if tool == self.config.chain.ots_base:
            self._links_changed(t_ns)
            self._watch_link(t_ns, T)

    def observe_local(self, k: int, tool: str, t_ns: int, T: np.ndarray) -> None:
        """:meth:`observe_ots` for local source ``k`` (0: the first; k >= 1: its own chain)."""
        if k == 0:
            self.observe_ots(tool, t_ns, T)
        else:
            self.extra_chains[k - 1].observe_ots(tool, t_ns, T)

    def admit(self, stream: int, t: int, T: np.ndarray, C: np.ndarray | None, what: str, payload=None) -> bool:
        """A valid target sample of ``stream``: dropped as ``rejected_jump`` if implausible (:mod:`.plausibility`),
        else handed to :meth:`enqueue` (payload ``(T, C)``, or ``payload``: the batched evaluator's sample index);
        once taken, the source's later samples are compared with it. True if taken."""
        why = self.plausibility.check(stream, t, T, what)
        if why is not None:
            self.diag.report("rejected_jump", why, t)
            return False
        if self.enqueue(stream, t, (T, C) if payload is None else payload, what) != OK:
            return False
        self.plausibility.accept(stream, t, T)
        return True

    def enqueue(self, stream: int, t_ns: int, payload, what: str) -> str:
        """A valid target sample of synchronizer ``stream`` (0 global, 1 + k local source k) at ``t_ns``: 'ok', or
        'late' / 'duplicate' (:mod:`.stamp_rules`), then dropped, counted and described naming ``what`` (source
        and body). ``payload``: ``(T_dev, C_dev)``, the device pose and covariance, for :meth:`poll` to fuse; a
        caller that takes the items itself (:meth:`poll_items`) may pass anything."""
        r = self.sync.push(stream, t_ns, payload)
        if r != OK:
            self.diag.report(r, self.sync.rules.message(r, what, t_ns), t_ns)
        return r

    def request_initialize(self, mode: str | None = None) -> None:
        """Re-estimate the static links from the next samples (the old ones stay in use meanwhile); ``mode``
        average | calibrate, default the configured ``static_links``. Plausibility starts again (the setup may have
        changed: the next sample of each source is accepted as its first)."""
        self.plausibility.restart()
        self.chain.reinitialize(mode)
        for ch in self.extra_chains:
            ch.reinitialize(mode)

    def apply_calibration(self, cal: Calibration, source: str) -> None:
        """Use the links of a finished calibration from now on (``fusion_node``'s ``~/calibrate``)."""
        self.chain.links.apply(cal, source)
        for x, ch in zip(self.config.sources.extras, self.extra_chains, strict=True):
            own = renamed_calibration(cal, x.name)   # T_omc_base, and T_base_<name> / T_rig_<name> if it has them
            if own is not None and own.links:
                ch.links.apply(own, source)

    # ---- static links: refusals and the link monitor -------------------------------------------
    def _links_changed(self, t: int) -> None:
        L = self.chain.links
        if L.refusals > self._refusals_seen:
            self._refusals_seen = L.refusals
            self.diag.report("calibration_refused", f"static links: {L.last_refusal}", t)

    def _watch_link(self, t: int, T_ots_base: np.ndarray) -> None:
        """Feed the monitor one OTS sighting of the base marker (reference: the T_base_ots in use)."""
        L = self.chain.links
        if L.T_base_ots is not self._monitor_src:
            self._monitor_src = L.T_base_ots
            watch = L.T_base_ots is not None and self.config.chain.local_chain != "tracked"
            self.monitor.set_reference(inv_T(L.T_base_ots) if watch else None)
        chk = self.monitor.add(t, T_ots_base)
        if chk is not None and chk.bumped:
            self.counts["link_bumped_checks"] += 1
            if self.config.monitor.recalibrate and not L.collecting:
                self.chain.reinitialize("calibrate")
                self.counts["recalibrations"] += 1

    def defer_link_checks(self) -> None:
        """The batched evaluator's: the monitor's checks are computed together by :meth:`resolve_link_checks`
        (LinkMonitor.defer), a bumped one then counted; no re-calibration (that evaluator runs none)."""
        self.monitor.defer()

    def resolve_link_checks(self) -> None:
        """The deferred checks, computed; each bumped one counted as :meth:`_watch_link` counts it."""
        for c in self.monitor.resolve():
            if c.bumped:
                self.counts["link_bumped_checks"] += 1

    # ---- output -----------------------------------------------------------------------------
    def side_outputs(self, most: int | None = None) -> list[FusedOutput]:
        """Deferred side-by-side outputs (:meth:`.arrival.ArrivalPipeline.side_outputs`): none in ordered processing."""
        return []

    def poll(self, now_ns: int | None = None) -> list[FusedOutput]:
        """Process every synchronizer item that is final at ``now_ns`` (default: newest stamp seen)."""
        return self._process(self.poll_items(now_ns))

    def flush(self) -> list[FusedOutput]:
        """Process everything pending (end of a recording)."""
        return self._process(self.flush_items())

    def poll_items(self, now_ns: int | None = None) -> list[SyncItem]:
        """The synchronizer items final at ``now_ns`` (:meth:`poll` without fusing them), in processing order."""
        return self.sync.poll(now_ns)

    def flush_items(self) -> list[SyncItem]:
        """Every pending synchronizer item (:meth:`flush` without fusing them)."""
        return self.sync.flush()

    def _process(self, items: list[SyncItem]) -> list[FusedOutput]:
        out: list[FusedOutput] = []
        for item in items:
            out.extend(self._process_item(item, self.lane, self.diag))
        return out

    def _process_item(self, item: SyncItem, lane: FilterLane, diag: Problems) -> list[FusedOutput]:
        """Map ``item`` into base with the chains' links in use and fuse it on ``lane``; counters and problems go
        to ``diag``. The one implementation of fusing an item, for both processing modes."""
        counts = diag.counts
        Tg = Tl = None
        eq = ""
        if item.glob is not None:
            Tg = self.chain.global_T(item.glob.payload[0])
            if Tg is None:   # only possible before T_omc_base is known
                counts["waiting_for_links"] += 1
        chain = self.chain if item.source == 0 else self.extra_chains[item.source - 1]
        if item.local is not None:
            Tl, eq = chain.local_T(item.local.t_ns, item.local.payload[0])
            if Tl is None:
                if chain.links.local_ready:   # e.g. no rig pose near this stamp (tracked mode)
                    diag.report("local_skipped", f"local sample skipped: {chain.why_not}", item.local.t_ns)
                else:
                    counts["waiting_for_links"] += 1
        if Tg is None and Tl is None:
            return []
        try:
            mg = None if Tg is None else measurement(SOURCE_GLOBAL, item.glob.t_ns, Tg, *item.glob.payload,
                                                     fixed=self._fixed_global)
            ml = None if Tl is None else measurement(SOURCE_LOCAL, item.local.t_ns, Tl, *item.local.payload,
                                                     fixed=self._fixed_local[item.source])
            ms_model = None
            if lane.models:
                qual = {} if mg is None else self.omc_quality.at(mg.t_ns)
                ms_model = model_measurements(self.config, self._rot_stds, self._fixed_local, item, mg, ml, Tg, Tl,
                                              eq, chain, qual)
        except BadMeasurement as e:   # a valid device covariance that mapping into base made invalid
            diag.report("rejected_cov", f"item at {item.t_ns} ns: covariance in base: {e}", item.t_ns)
            return []
        ms = [m for m in (mg, ml) if m is not None]
        state = lane.state
        t_item = max(m.t_ns for m in ms)
        if item.source and state.last_item_ns is not None:   # lagged sample of a further source (synchronizer.py)
            t_item = max(t_item, state.last_item_ns)
        state.last_item_ns = t_item
        if self.extra_chains and ml is not None:
            counts[f"{self.config.sources.locals[item.source].name}_fused"] += 1
        tg = None if mg is None else mg.t_ns
        tl = None if ml is None else ml.t_ns
        if tl is not None:
            state.last_local_ns = tl
        outs = []
        frame = self._frame()
        for name, f in lane.filters.items():
            caps = caps_of(name)
            if frame is not None and caps.models:   # it follows the local chain's frame (lane.py)
                if f.express_in(frame, ml is not None and item.source == 0) is not None:
                    counts["frame_moves"] += 1
            try:
                f.predict(t_item)
                st: Step | None = f.update(*(ms_model if caps.models else ms))
            except (ValueError, FloatingPointError, np.linalg.LinAlgError) as e:
                diag.report("filter_error", f"filter {name}: {e}", item.t_ns)
                continue
            if st is None:
                continue
            if caps.orientation and st.q is not None and st.pose_cov is not None:   # fused orientation (fullperc)
                q, cov, osrc = st.q, st.pose_cov, SOURCE_GLOBAL | SOURCE_LOCAL
                if frame is not None and caps.models:
                    cov = self._with_frame_cov(cov, st.p, frame)
            else:
                if name == "omc" or ml is None:
                    mq, osrc, ostd = mg, SOURCE_GLOBAL, self.config.orientation_std_global
                else:
                    mq, osrc, ostd = ml, SOURCE_LOCAL, self.config.orientation_std_local
                cov = np.zeros((6, 6))
                cov[0:3, 0:3] = st.pos_cov
                cov[3:6, 3:6] = np.eye(3) * ostd**2 if mq.cov is None else mq.cov[3:6, 3:6]
                q = mq.q
            # ndarray.all(): the same test as np.all without its Python dispatch layer (~1 us each, per output)
            if not (np.isfinite(st.p).all() and np.isfinite(cov).all() and np.isfinite(q).all()):
                f.reset()
                diag.report("nonfinite_output", f"filter {name}: non-finite estimate; filter reset", st.t_ns)
                continue
            since = -1.0 if state.last_local_ns is None else (st.t_ns - state.last_local_ns) * 1e-9
            o = FusedOutput(
                target=self.config.name, filter=name, t_ns=st.t_ns, p=st.p, q=q, cov=cov,
                bias=st.b, innovation=st.innovation, nis=st.nis, hop=st.hop, sources=st.sources,
                orientation_source=osrc, time_since_local=since, reset=st.reset,
                t_global=tg if st.sources & SOURCE_GLOBAL else None,
                t_local=tl if st.sources & SOURCE_LOCAL else None,
                local_equation=eq if st.sources & SOURCE_LOCAL else "", link_bumped=self.monitor.bumped, step=st)
            state.last_output[name] = o
            outs.append(o)
        counts["items"] += 1
        return outs

    def _frame(self) -> np.ndarray | None:
        """The frame the local samples come in (the primary chain's static link), for ``express_in``."""
        return self.chain.links.T_base_ots if self.chain.cfg.local_chain == "static" else None

    def _with_frame_cov(self, cov: np.ndarray, p: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """``cov`` plus the covariance of the local chain's frame (:meth:`_frame`) at p (module docstring, "Frame
        covariance"); ``cov`` itself when the link has no covariance."""
        est = self.chain.links.estimates.get("T_base_ots")
        return cov if est is None else cov + link_covariance_at(est.cov, p - frame[:3, 3])

    # ---- state for diagnostics ----------------------------------------------------------------
    def stats(self) -> dict:
        L = self.chain.links
        d = {
            "global_link": "ready" if L.global_ready else "waiting",
            "local_link": "ready" if L.local_ready else "waiting",
            "collecting": L.collecting,
            "init_progress": L.progress(),
            "pending": self.sync.pending,
            "static_links": L.mode,
            "links_source": "; ".join(f"{k}: {v}" for k, v in L.sources.items()),
            "link_bumped": self.monitor.bumped,
        }
        chk = self.monitor.last
        if chk is not None:
            d.update(link_dtrans_mm=round(chk.dtrans_m * 1e3, 3), link_drot_mrad=round(chk.drot_rad * 1e3, 3))
        for x, ch in zip(self.config.sources.extras, self.extra_chains, strict=True):
            d[f"{x.name}_link"] = "ready" if ch.links.local_ready else "waiting"
            d[f"{x.name}_links_source"] = "; ".join(f"{k}: {v}" for k, v in ch.links.sources.items())
        d.update({f"sync_{k}": v for k, v in self.sync.counts.items()})
        d.update(dict(self.counts))
        return d
