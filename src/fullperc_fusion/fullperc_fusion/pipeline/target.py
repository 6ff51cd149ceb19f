"""What one target's pipeline is configured with and what it outputs: :class:`TargetConfig`, :class:`FusedOutput`.

Shared by the two processing modes (``ordered``: :class:`~.ordered.TargetPipeline`, ``arrival``:
:class:`~.arrival.ArrivalPipeline`) and by what builds them (``fusion_config``) or reads their outputs
(``fusion_node``, the evaluator). :mod:`.ordered` re-exports all of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fullperc_fusion.calibration.monitor import MonitorParams
from fullperc_fusion.filters.api import Step
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.measurement_models import OmcModelParams
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.filters.registry import FILTERS
from fullperc_fusion.margin.layout import Layout
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.param_table import NONNEGATIVE, POSITIVE, Param, one_of
from fullperc_fusion.pipeline.sources import SourceSet

FILTER_NAMES: tuple[str, ...] = tuple(FILTERS)   # ("cbkf", "ckf", "bkf", "kf", "omc", "fullperc"): filters.registry


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
    partner_wait_ns: int = 0        # arrival: longest wait of a sample for its partner (partner_hold.py); 0 = none
    orientation_std_local: float = 0.002   # [rad] reported in pose_cov when the OTS orientation is used
    orientation_std_global: float = 0.01   # [rad] when the OMC orientation is used
    monitor: MonitorParams = field(default_factory=MonitorParams)   # link monitoring (link_monitor)
    layout: Layout | None = None    # OR layout (omc frame) for the OMC model's view margin; None: margin unknown
    omc_model: OmcModelParams = field(default_factory=OmcModelParams)   # constants of the OMC model (noise_model_file)
    sources: SourceSet = field(default_factory=SourceSet)   # sources.py: global + first local (``chain``) + further
    # plausibility.py: a target sample further than max_jump + max_speed x dt from its source's last accepted one is
    # dropped (rejected_jump); the parameters plausibility.max_speed and plausibility.jump
    max_speed: float = 2.0          # [m/s] the fastest the target moves
    max_jump: float = 0.01          # [m] what a sample may be off besides (noise, the OMC's marker hops)

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
        if not 0 <= self.partner_wait_ns <= self.history_ns // 2:
            raise ValueError(f"target '{self.name}': partner_wait must be >= 0 and <= history / 2, got "
                             f"{self.partner_wait_ns * 1e-9} s")
        if not self.max_future_ns > 0:
            raise ValueError(f"target '{self.name}': max_future must be > 0, got {self.max_future_ns * 1e-9} s")
        for what, v in (("plausibility.max_speed", self.max_speed), ("plausibility.jump", self.max_jump)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"target '{self.name}': {what} must be finite and > 0, got {v}")


_T = TargetConfig()
TIMING_PARAMS: tuple[Param, ...] = (
    Param("slop", _T.slop_ns * 1e-9, "float", *NONNEGATIVE, "s",
          "pair OMC and OTS samples closer than this"),
    Param("reorder_delay", _T.delay_ns * 1e-9, "float", *NONNEGATIVE, "s",
          "wait for late / reordered samples before processing"),
    Param("clock", "stamps", "str", *one_of(("stamps", "host"), "stamps or host"), "",
          "what 'now' is for the synchronizer: the newest stamp, or the node clock"),
    Param("max_future", _T.max_future_ns * 1e-9, "float", *POSITIVE, "s",
          "a sample stamped more than this ahead of the node clock is rejected (named on /diagnostics)"),
    Param("idle_flush", 0.5, "float", *POSITIVE, "s",
          "without target samples for this long: process everything pending (arrival: the history becomes final)"),
    Param("processing", _T.processing, "str", *one_of(("arrival", "ordered"), "arrival or ordered"), "",
          "arrival: fuse each sample when it arrives, rewind and replay for late ones | ordered: wait slop + "
          "reorder_delay, then fuse in stamp order"),
    Param("history", _T.history_ns * 1e-9, "float", *POSITIVE, "s",
          "arrival: a sample up to this much older than the newest is still fused in order (rewind and replay); "
          "older: dropped, named on /diagnostics"),
    Param("partner_wait", 0.004, "float", *NONNEGATIVE, "s",
          "arrival: a sample whose approximate-time partner is due waits for it up to this long (host clock) "
          "instead of being fused and rewound when the partner comes; 0 = never wait"),
)
"""fusion_node's parameters of when a target's samples are paired and fused (rows of fusion_config.PARAMS)."""


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
    # the filter's step (read by :meth:`velocity` only): kept, not copied, so an output costs nothing more unless its
    # velocity is asked for (the fast filters assemble their full covariance on first access); not compared
    step: Step | None = field(default=None, repr=False, compare=False)

    def velocity(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(linear velocity [m/s] in ``base``, its 3x3 covariance) from the filter's constant-velocity state -- every
        filter's state holds v after p (``Step.v``, ``P[3:6, 3:6]``) --, or None for a filter without one (``omc``,
        the raw pass-through, whose step has v = 0 with a zero covariance: not an estimate)."""
        st = self.step
        if st is None or self.filter == "omc":
            return None
        return np.array(st.v, dtype=float), np.array(st.P[3:6, 3:6], dtype=float)


def rotation_stds(config: TargetConfig) -> tuple[float, float]:
    """(global, local) per-axis orientation std [rad] of a sample given a fixed covariance by its source (``noise_std``
    or ``noise_model: std``, :mod:`.sources`): the filter parameters' own orientation noise when they model the
    orientation (:class:`~fullperc_fusion.filters.fullperc_params.FullpercParams` ``rot_global_std`` /
    ``rot_local_std``), else the orientation std the outputs report (``orientation_std_global`` / ``_local``)."""
    p = config.params
    if isinstance(p, FullpercParams):
        return p.rot_global_std, p.rot_local_std
    return config.orientation_std_global, config.orientation_std_local
