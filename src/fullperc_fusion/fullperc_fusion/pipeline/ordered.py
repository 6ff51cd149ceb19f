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

Data flow: every pose is validated (:func:`frame_chain.pose_to_T`; NaN/inf, non-unit quaternions
and bad stamps are rejected, counted and described in :attr:`TargetPipeline.last_problem`, never
raised), and so is its covariance when one is given (:func:`filter_api.check_covariance`: non-finite,
non-symmetric or not positive definite -> ``rejected_cov``, the sample is dropped, never fused); base / rig
samples feed the static links of the :class:`~frame_chain.FrameChain`; target
samples go through the :class:`~synchronizer.ApproxSync` as raw device poses and are mapped into
``base`` only when they come out (so a base-marker sample of the same OTS frame that arrived a little
later can still be used for eq. 2); each item then becomes one :class:`~filter_api.Measurement` per
source and every configured filter (:mod:`filter_registry`) is predicted to the item and updated with them.

A device covariance is given in the device frame (``omc`` / ``ots``), ROS order [x y z, rx ry rz], the
rotation part about the device frame's axes (the :mod:`filter_api` convention with that frame as parent).
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
:class:`~link_monitor.LinkMonitor`: a bump of the Vega or of the reference marker sets ``link_bumped`` in every
output and, with ``monitor.recalibrate``, re-estimates the static links in calibrate mode (the old links stay in
use meanwhile). A refused calibrate-mode collection is counted as ``calibration_refused`` with its reason.

The paper's filters do not filter the orientation (the paper fuses position): their output's orientation is that
of the best source in the item -- the local (OTS) one when present, else the global one -- mapped into ``base``,
and ``orientation_source`` says which. The ``omc`` pass-through always carries the global one. A filter whose
Step carries ``q`` (``fullperc``) outputs its fused orientation and its own 6x6 pose covariance, with
``orientation_source`` = both bits.

Model covariances: a filter with ``uses_models`` (``fullperc``) is fed the same samples with the covariances of
:mod:`measurement_models` -- the OMC's from its TrackingQuality (``push_omc(quality=...)`` or
:meth:`TargetPipeline.push_omc_quality`, matched by stamp) and the view margin at the body in
``TargetConfig.layout``, the local one from the Vega's distance model plus the calibrated link through the lever
arm. The paper's filters get exactly the measurements they got before (``cov`` only when a device gave one).

Frame covariance: the pose covariance a ``uses_models`` filter reports is that of its estimate in the frame the
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
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from fullperc_common.transforms import T_to_pq, inv_T
from fullperc_fusion.calibration.monitor import LinkMonitor, MonitorParams
from fullperc_fusion.calibration.se3_stats import Calibration
from fullperc_fusion.filters.api import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    BadMeasurement,
    Measurement,
    Step,
    check_covariance,
)
from fullperc_fusion.filters.measurement_models import (
    OmcModelParams,
    link_covariance_at,
    local_covariance,
    omc_covariance,
    omc_systematic_var,
    rotate_cov,
)
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.filters.registry import FILTERS, make_filter
from fullperc_fusion.margin.layout import Layout
from fullperc_fusion.margin.view_margin import margin_at
from fullperc_fusion.pipeline.frame_chain import BadSample, ChainConfig, FrameChain, pose_to_T
from fullperc_fusion.pipeline.sources import SourceSet, fixed_cov, model_cov_std, renamed_calibration
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync, SyncItem

_QUALITY_KEEP_NS = 1_000_000_000   # OMC qualities older than this behind the fused sample are dropped
FILTER_NAMES: tuple[str, ...] = tuple(FILTERS)   # ("cbkf", "ckf", "bkf", "kf", "omc"): filter_registry.FILTERS


@dataclass
class TargetConfig:
    """Everything one target needs. ``filters[0]`` is the primary filter of the node."""

    name: str = "tool"
    chain: ChainConfig = field(default_factory=ChainConfig)
    filters: tuple[str, ...] = ("cbkf",)
    params: FilterParams = field(default_factory=FilterParams)
    slop_ns: int = 4_000_000        # pair samples closer than this (below half the OMC period at 120 Hz)
    delay_ns: int = 50_000_000      # reorder / transport delay the synchronizer waits for
    max_future_ns: int = 100_000_000   # a sample stamped further ahead of the caller's clock is rejected
    processing: str = "arrival"     # fusion_node: arrival (arrival.ArrivalPipeline) | ordered (this class)
    history_ns: int = 200_000_000   # arrival: how far back a late sample still rewinds and replays
    orientation_std_local: float = 0.002   # [rad] reported in pose_cov when the OTS orientation is used
    orientation_std_global: float = 0.01   # [rad] when the OMC orientation is used
    monitor: MonitorParams = field(default_factory=MonitorParams)   # link monitoring (link_monitor)
    layout: Layout | None = None    # OR layout (omc frame) for the OMC model's view margin; None: margin unknown
    omc_model: OmcModelParams = field(default_factory=OmcModelParams)   # constants of the OMC model (noise_model_file)
    sources: SourceSet = field(default_factory=SourceSet)   # sources.py: global + first local (``chain``) + further

    def __post_init__(self) -> None:
        self.filters = tuple(self.filters)
        if not self.filters:
            raise ValueError(f"target '{self.name}': at least one filter is needed")
        for f in self.filters:
            if f not in FILTERS:
                raise ValueError(f"target '{self.name}': filter '{f}' is not one of {tuple(FILTERS)}")
        if len(set(self.filters)) != len(self.filters):
            raise ValueError(f"target '{self.name}': duplicate filter in {self.filters}")
        self.params.validate()
        self.monitor.validate()
        if self.processing not in ("arrival", "ordered"):
            raise ValueError(f"target '{self.name}': processing must be arrival or ordered, got {self.processing!r}")
        if not self.history_ns > 0:
            raise ValueError(f"target '{self.name}': history must be > 0, got {self.history_ns * 1e-9} s")
        if not self.max_future_ns > 0:
            raise ValueError(f"target '{self.name}': max_future must be > 0, got {self.max_future_ns * 1e-9} s")


@dataclass
class FusedOutput:
    """One fused estimate of one target by one filter (all vectors in ``base``, SI units)."""

    target: str
    filter: str
    t_ns: int                      # acquisition stamp of the newest sample used
    p: np.ndarray                  # (3,) position [m]
    q: np.ndarray                  # (4,) orientation x y z w
    cov: np.ndarray                # (6, 6) pose covariance, ROS order (x y z rotX rotY rotZ)
    bias: np.ndarray               # (3,) estimated global-source bias [m] (zeros without a bias state)
    innovation: np.ndarray         # (3,) global innovation if a global sample was used, else local [m]
    nis: float
    hop: bool
    sources: int                   # SOURCE_GLOBAL | SOURCE_LOCAL bits
    orientation_source: int
    time_since_local: float        # [s] since the last local sample used; -1 if never
    reset: bool                    # the filter (re-)initialised on this item
    t_global: int | None = None    # stamps of the samples used
    t_local: int | None = None
    local_equation: str = ""       # 'eq1' | 'eq2' | 'static' for the local measurement used
    link_bumped: bool = False      # the link monitor sees the OTS's view of the base off its calibration


class TargetPipeline:
    """Frame chain -> synchronizer -> filters for one target; see the module docstring."""

    def __init__(self, config: TargetConfig) -> None:
        self.config = config
        self.chain = FrameChain(config.chain)
        self.sync = ApproxSync(config.slop_ns, config.delay_ns, names=config.sources.stream_names)
        src = config.sources
        # further local sources (sources.py): their own chains, fixed covariances per local source index
        self.extra_chains = [FrameChain(x.chain) for x in src.extras if x.chain is not None]
        rot = (getattr(config.params, "rot_global_std", config.orientation_std_global),
               getattr(config.params, "rot_local_std", config.orientation_std_local))
        self._fixed_global = fixed_cov(src.glob, rot[0])
        self._fixed_local = [fixed_cov(x, rot[1]) for x in src.locals]
        self.last_item_ns: int | None = None   # processing stamp of the last item (lagged further-source samples)
        self.filters = {name: make_filter(name, config.params) for name in config.filters}
        self.counts: Counter[str] = Counter()
        self.last_problem = ""          # the most recent reason something was rejected or skipped
        self.problems: dict[str, str] = {}   # the most recent reason per kind (key of ``counts``)
        self.last_problem_t_ns: int | None = None
        self.last_local_ns: int | None = None
        self.last_global_ns: int | None = None
        self.last_output: dict[str, FusedOutput] = {}
        c = config.chain
        self.monitor = LinkMonitor(config.monitor, "T_base_ots", f"OTS tool '{c.ots_base}'")
        self._monitor_src: np.ndarray | None = None   # the T_base_ots the monitor's reference was made from
        self._refusals_seen = 0
        # the model covariances (measurement_models) are built only when a filter uses them (fullperc)
        self._models = any(getattr(f, "uses_models", False) for f in self.filters.values())
        self._omc_quality: dict[int, dict] = {}   # stamp -> TrackingQuality of the OMC target body (fit_error ...)

    # ---- input ------------------------------------------------------------------------------
    def report_problem(self, key: str, msg: str, t_ns: int | None) -> None:
        """Count a problem of kind ``key`` (a key of :attr:`counts`) and make ``msg`` the newest one: the pipeline's
        own rejections, and a caller's (``fusion_node``'s publish errors) the same way."""
        self._problem(key, msg, t_ns)

    def _problem(self, key: str, msg: str, t_ns: int | None) -> None:
        self.counts[key] += 1
        self.last_problem = msg
        self.problems[key] = msg
        self.last_problem_t_ns = t_ns

    def _validate(self, what: str, t_ns, pose, cov=None,
                  now_ns: int | None = None) -> tuple[int, np.ndarray, np.ndarray | None] | None:
        try:
            t = int(t_ns)
        except (TypeError, ValueError, OverflowError):
            self._problem("rejected_stamp", f"{what}: invalid stamp {t_ns!r}", None)
            return None
        if t <= 0:
            self._problem("rejected_stamp", f"{what}: invalid stamp {t}", None)
            return None
        if now_ns is not None and t - now_ns > self.config.max_future_ns:
            self._problem("rejected_future", f"{what}: stamp {t} ns is {(t - now_ns) * 1e-9:.3f} s ahead of the "
                                             f"clock ({now_ns} ns; max_future {self.config.max_future_ns * 1e-9:g} s); "
                                             "dropped", t)
            return None
        try:
            T = pose_to_T(pose)
        except BadSample as e:
            why = str(e)
            key = "rejected_nonfinite" if "non-finite" in why else "rejected_nonunit" if "non-unit" in why \
                else "rejected_pose"
            self._problem(key, f"{what}: {why}", t)
            return None
        if cov is None:
            return t, T, None
        try:
            return t, T, check_covariance(cov)
        except BadMeasurement as e:
            self._problem("rejected_cov", f"{what}: {e}", t)
            return None

    def push_omc(self, body: str, t_ns: int, pose, cov=None, now_ns: int | None = None,
                 quality: dict | None = None) -> bool:
        """One OMC sample of ``body`` (pose of the body in ``omc``, optional 6x6 covariance in ``omc``).
        False if rejected or unused. ``now_ns``: the caller's clock, for the time guard (module docstring).
        ``quality``: the sample's TrackingQuality fields (:meth:`push_omc_quality`), for the OMC model."""
        c = self.config.chain
        if quality is not None:
            self.push_omc_quality(body, t_ns, quality)
        extra = [ch for ch in self.extra_chains if body in (ch.cfg.omc_base, ch.cfg.omc_rig)]
        if body not in (c.omc_target, c.omc_base, c.omc_rig) and not extra:
            return False
        v = self._validate(f"OMC body '{body}'", t_ns, pose, cov, now_ns)
        if v is None:
            return False
        t, T, C = v
        self.chain.observe_omc(body, t, T)
        for ch in extra:
            ch.observe_omc(body, t, T)
        if body in (c.omc_base, c.omc_rig):
            self._links_changed(t)
        if body == c.omc_target:
            return self._enqueue(GLOBAL, f"OMC body '{body}'", t, (T, C))
        return True

    def push_ots(self, tool: str, t_ns: int, pose, cov=None, now_ns: int | None = None) -> bool:
        """One OTS sample of ``tool`` (pose of the tool in ``ots``, optional 6x6 covariance in ``ots``).
        False if rejected or unused. ``now_ns``: the caller's clock, for the time guard (module docstring)."""
        c = self.config.chain
        if tool not in (c.ots_target, c.ots_base):
            return False
        v = self._validate(f"OTS tool '{tool}'", t_ns, pose, cov, now_ns)
        if v is None:
            return False
        t, T, C = v
        self.chain.observe_ots(tool, t, T)
        if tool == c.ots_base:
            self._links_changed(t)
            self._watch_link(t, T)
        if tool == c.ots_target:
            return self._enqueue(LOCAL, f"OTS tool '{tool}'", t, (T, C))
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
        v = self._validate(what, t_ns, pose, cov, now_ns)
        if v is None:
            return False
        t, T, C = v
        ch.observe_ots(tool, t, T)
        if tool == ch.cfg.ots_target:
            return self._enqueue(1 + k, what, t, (T, C))
        return True

    def push_omc_quality(self, body: str, t_ns: int, quality: dict) -> None:
        """The TrackingQuality of one OMC sample of ``body`` (``fit_error`` [m], ``markers_used``), before or after
        its pose: it is looked up by stamp when the sample is fused, for the OMC model covariance
        (:func:`measurement_models.omc_covariance`; only filters with ``uses_models``). Other bodies are ignored."""
        if body != self.config.chain.omc_target or not self._models:
            return
        try:
            self._omc_quality[int(t_ns)] = {k: float(v) for k, v in dict(quality).items()}
        except (TypeError, ValueError):
            return   # a malformed quality only means the model's defaults
        if len(self._omc_quality) > 512:   # a body whose poses never come (not tracked): keep the newest
            for k in sorted(self._omc_quality)[:256]:
                del self._omc_quality[k]

    def _enqueue(self, stream: int, what: str, t: int, payload: tuple[np.ndarray, np.ndarray | None]) -> bool:
        r = self.sync.push(stream, t, payload)
        if r == "late":
            self._problem("late", f"{what}: sample at {t} ns is older than the processed horizon "
                                  f"{self.sync.horizon_ns} ns (time went backwards or arrived too late); dropped", t)
        elif r == "duplicate":
            self._problem("duplicate", f"{what}: duplicate stamp {t} ns; dropped", t)
        return r == "ok"

    def request_initialize(self, mode: str | None = None) -> None:
        """Re-estimate the static links from the next samples (the old ones stay in use meanwhile); ``mode``
        average | calibrate, default the configured ``static_links``."""
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
            self._problem("calibration_refused", f"static links: {L.last_refusal}", t)

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

    # ---- output -----------------------------------------------------------------------------
    def poll(self, now_ns: int | None = None) -> list[FusedOutput]:
        """Process every synchronizer item that is final at ``now_ns`` (default: newest stamp seen)."""
        return self._process(self.sync.poll(now_ns))

    def flush(self) -> list[FusedOutput]:
        """Process everything pending (end of a recording)."""
        return self._process(self.sync.flush())

    def _process(self, items: list[SyncItem]) -> list[FusedOutput]:
        out: list[FusedOutput] = []
        for item in items:
            out.extend(self._process_item(item))
        return out

    def _process_item(self, item: SyncItem) -> list[FusedOutput]:
        Tg = Tl = None
        eq = ""
        if item.glob is not None:
            Tg = self.chain.global_T(item.glob.payload[0])
            if Tg is None:   # only possible before T_omc_base is known
                self.counts["waiting_for_links"] += 1
        chain = self.chain if item.source == 0 else self.extra_chains[item.source - 1]
        if item.local is not None:
            Tl, eq = chain.local_T(item.local.t_ns, item.local.payload[0])
            if Tl is None:
                if chain.links.local_ready:   # e.g. no rig pose near this stamp (tracked mode)
                    self._problem("local_skipped", f"local sample skipped: {chain.why_not}", item.local.t_ns)
                else:
                    self.counts["waiting_for_links"] += 1
        if Tg is None and Tl is None:
            return []
        try:
            mg = None if Tg is None else _measurement(SOURCE_GLOBAL, item.glob.t_ns, Tg, *item.glob.payload,
                                                      fixed=self._fixed_global)
            ml = None if Tl is None else _measurement(SOURCE_LOCAL, item.local.t_ns, Tl, *item.local.payload,
                                                      fixed=self._fixed_local[item.source])
            ms_model = self._model_measurements(item, mg, ml, Tg, Tl, eq, chain) if self._models else None
        except BadMeasurement as e:   # a valid device covariance that mapping into base made invalid
            self._problem("rejected_cov", f"item at {item.t_ns} ns: covariance in base: {e}", item.t_ns)
            return []
        ms = [m for m in (mg, ml) if m is not None]
        t_item = max(m.t_ns for m in ms)
        if item.source and self.last_item_ns is not None:   # lagged sample of a further source (synchronizer.py)
            t_item = max(t_item, self.last_item_ns)
        self.last_item_ns = t_item
        if self.extra_chains and ml is not None:
            self.counts[f"{self.config.sources.locals[item.source].name}_fused"] += 1
        tg = None if mg is None else mg.t_ns
        tl = None if ml is None else ml.t_ns
        if tl is not None:
            self.last_local_ns = tl
        if tg is not None:
            self.last_global_ns = tg
        outs = []
        frame = self._frame()
        for name, f in self.filters.items():
            if frame is not None and getattr(f, "uses_models", False) and hasattr(f, "express_in"):
                if f.express_in(frame, ml is not None and item.source == 0) is not None:
                    self.counts["frame_moves"] += 1
            try:
                f.predict(t_item)
                st: Step | None = f.update(*(ms_model if ms_model is not None and getattr(f, "uses_models", False)
                                             else ms))
            except (ValueError, FloatingPointError, np.linalg.LinAlgError) as e:
                self._problem("filter_error", f"filter {name}: {e}", item.t_ns)
                continue
            if st is None:
                continue
            if st.q is not None and st.pose_cov is not None:   # the filter fused the orientation (fullperc)
                q, cov, osrc = st.q, st.pose_cov, SOURCE_GLOBAL | SOURCE_LOCAL
                if frame is not None and getattr(f, "uses_models", False):
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
                self._problem("nonfinite_output", f"filter {name}: non-finite estimate; filter reset", st.t_ns)
                continue
            since = -1.0 if self.last_local_ns is None else (st.t_ns - self.last_local_ns) * 1e-9
            o = FusedOutput(
                target=self.config.name, filter=name, t_ns=st.t_ns, p=st.p, q=q, cov=cov,
                bias=st.b, innovation=st.innovation, nis=st.nis, hop=st.hop, sources=st.sources,
                orientation_source=osrc, time_since_local=since, reset=st.reset,
                t_global=tg if st.sources & SOURCE_GLOBAL else None,
                t_local=tl if st.sources & SOURCE_LOCAL else None,
                local_equation=eq if st.sources & SOURCE_LOCAL else "", link_bumped=self.monitor.bumped)
            self.last_output[name] = o
            outs.append(o)
        self.counts["items"] += 1
        return outs

    def _frame(self) -> np.ndarray | None:
        """The frame the local samples come in (the primary chain's static link), for ``express_in``."""
        return self.chain.links.T_base_ots if self.chain.cfg.local_chain == "static" else None

    def _with_frame_cov(self, cov: np.ndarray, p: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """``cov`` plus the covariance of the local chain's frame (:meth:`_frame`) at p (module docstring, "Frame
        covariance"); ``cov`` itself when the link has no covariance."""
        est = self.chain.links.estimates.get("T_base_ots")
        return cov if est is None else cov + link_covariance_at(est.cov, p - frame[:3, 3])

    def _model_measurements(self, item: SyncItem, mg: Measurement | None, ml: Measurement | None,
                            Tg: np.ndarray | None, Tl: np.ndarray | None, eq: str,
                            chain: FrameChain) -> list[Measurement]:
        """The item's measurements with the model covariances of :mod:`measurement_models` (``uses_models``).

        Global: a device covariance when one was pushed (already in base), else the OMC model (white part) from the
        sample's quality (:meth:`push_omc_quality`; defaults without) and the view margin at the body in the layout;
        ``extras`` carry the quality and ``sys_var``, the variance of the OMC's systematic position error here.
        Local: the device covariance or the Vega's distance model, mapped into base, plus the calibrated static
        link's covariance through the lever arm (``static`` chain with a T_base_ots that has one: calibrated, or the
        average that bridges until it is; else no link term).
        A source with ``noise_std`` or ``noise_model: std`` (sources.py) gets its diagonal instead of the model.
        """
        src, p = self.config.sources, self.config.params
        out = []
        if mg is not None:
            T_dev = item.glob.payload[0]
            qual = self._omc_quality.get(mg.t_ns) or {}   # kept: arrival.py may fuse this item again (replay)
            for k in [k for k in self._omc_quality if k < mg.t_ns - _QUALITY_KEEP_NS]:
                del self._omc_quality[k]
            C = mg.cov
            if C is None and src.glob.noise_model == "std":
                C = model_cov_std(src.glob, p.global_std, p.rot_global_std)
            margin = None
            if C is None:
                lay = self.config.layout
                margin = margin_at(lay, T_dev[:3, 3])[0] if lay is not None else None
            sys_var = omc_systematic_var(qual.get("fit_error"), margin, self.config.omc_model)
            if C is None:
                RA = Tg[:3, :3] @ T_dev[:3, :3].T
                C = rotate_cov(omc_covariance(qual.get("fit_error"), margin, self.config.omc_model, sys_var), RA)
            out.append(Measurement(mg.t_ns, SOURCE_GLOBAL, mg.p, mg.q, C, extras={**qual, "sys_var": sys_var[0]}))
        if ml is not None:
            T_dev, C_dev = item.local.payload[0], item.local.payload[1]
            spec = src.locals[item.source]
            if self._fixed_local[item.source] is not None or (spec.noise_model == "std" and C_dev is None):
                C = ml.cov if ml.cov is not None else model_cov_std(spec, p.local_std, p.rot_local_std)
            else:
                A = Tl @ inv_T(T_dev)   # T_base_tool = A T_ots_tool: the whole chain in front of the tool
                est = chain.links.estimates.get("T_base_ots") if eq == "static" else None
                C = local_covariance(A, T_dev, None if est is None else est.cov, device_cov=C_dev)
            out.append(Measurement(ml.t_ns, SOURCE_LOCAL, ml.p, ml.q, C))
        return out

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


def _measurement(source: int, t_ns: int, T_base: np.ndarray, T_dev: np.ndarray,
                 C_dev: np.ndarray | None, fixed: np.ndarray | None = None) -> Measurement:
    """The filter's measurement of one sample mapped into base; the covariance rotated by the chain's R_A.
    ``fixed``: the source's own diagonal covariance in base (``noise_std``, sources.py), used instead."""
    p, q = T_to_pq(T_base)
    C = fixed
    if C_dev is not None and fixed is None:
        RA = T_base[:3, :3] @ T_dev[:3, :3].T   # T_base = A T_dev -> R_A = R_base R_dev^T
        J = np.zeros((6, 6))
        J[0:3, 0:3] = J[3:6, 3:6] = RA
        C = J @ C_dev @ J.T
        C = 0.5 * (C + C.T)
    return Measurement(t_ns, source, p, q, C)
