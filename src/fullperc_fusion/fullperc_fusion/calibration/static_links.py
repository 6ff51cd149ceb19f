"""The static links of a target's frame chain and their life cycle: configured, estimated, re-estimated, applied.

:class:`ChainConfig` says which device bodies make up one target's chain (``pipeline.frame_chain`` maps every
measurement into ``base`` with it) and how its static links are obtained; :class:`StaticLinks` owns those links
from the start of a run to every re-estimation. The bodies must be stationary while the links are being estimated
(the paper's initialization).

How the static links are estimated (``static_links``; a link given as a parameter is never estimated):
  * ``average``   the chordal mean of the first ``init_samples`` sightings of each body.
  * ``calibrate`` (default) the robust SE(3) mean of :mod:`fullperc_fusion.calibration.se3_stats`
                  (outliers rejected, refused when a body moved or too few sightings came) over
                  ``calibration_duration_s`` seconds of stamps, one
                  :class:`~fullperc_fusion.calibration.collector.Collector` for the global link and one for the local
                  link; a refused collection is logged (:attr:`StaticLinks.last_refusal`) and started again.
                  Bridge: a link that has no value yet (the start; not a re-estimation, whose previous link stays)
                  is served meanwhile by the ``average`` estimate (the first ``init_samples`` sightings, exactly as
                  in ``average`` mode), so fusion starts as early; each link switches to its calibrated estimate
                  when its collection completes (a refused one keeps the average and collects again).
                  ``StaticLinks.sources`` names the estimate in use.
  * a calibration file (``ChainConfig.calibration``) gives links at start; only the missing ones are estimated,
    and ``~/initialize`` re-estimates every one of them.
While a (re-)estimation runs the previous links stay in use; :meth:`StaticLinks.apply` swaps in a finished
calibration (``fusion_node``'s ``~/calibrate``) in one step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fullperc_common.transforms import inv_T, mean_T
from fullperc_fusion.calibration.collector import Collector
from fullperc_fusion.calibration.links import link_T_rig_ots
from fullperc_fusion.calibration.poses import pose_to_T
from fullperc_fusion.calibration.se3_stats import (
    Calibration,
    CalibrationBodies,
    CalibrationError,
    CalibrationSettings,
    LinkEstimate,
    mean_estimate,
)

__all__ = ["LOCAL_CHAINS", "STATIC_LINK_MODES", "ChainConfig", "StaticLinks", "links_needed"]

LOCAL_CHAINS = ("static", "tracked", "direct")
STATIC_LINK_MODES = ("average", "calibrate")
_BRIDGE = "until the robust mean"   # in ``sources`` of a link calibrate mode's bridge serves


@dataclass
class ChainConfig:
    """Which device bodies make up one target's chain (names as on the driver topics)."""

    omc_target: str = "tool"        # OMC rigid body of the target -> global measurement
    ots_target: str = "tool"        # OTS tool of the target -> local measurement
    omc_base: str = "base"          # OMC body of the global reference marker
    omc_rig: str = "ots_rig"        # OMC body rigidly attached to the OTS (paper's {Robot})
    ots_base: str = "base"          # OTS tool on the global reference marker (eq. 2)
    local_chain: str = "static"     # static | tracked | direct (module docstring)
    init_samples: int = 30          # samples of each body averaged per static link
    T_rig_ots: np.ndarray | None = None   # given hand-eye calibration (eq. 1), else estimated
    T_base_ots: np.ndarray | None = None  # given calibration of a stationary OTS, else estimated
    rig_max_age_ns: int = 20_000_000      # tracked mode: rig pose must be this close in time
    static_links: str = "calibrate"       # calibrate | average (module docstring)
    calibration_duration_s: float = 10.0  # calibrate mode: seconds of stamps per collection
    calibration_settings: CalibrationSettings = field(default_factory=CalibrationSettings)
    calibration: Calibration | None = None  # links from a calibration file (calibration_io.load_calibration)
    calibration_file: str = ""            # where ``calibration`` was read from (for messages)

    def __post_init__(self) -> None:
        if self.local_chain not in LOCAL_CHAINS:
            raise ValueError(f"local_chain '{self.local_chain}' is not one of {LOCAL_CHAINS}")
        if self.static_links not in STATIC_LINK_MODES:
            raise ValueError(f"static_links '{self.static_links}' is not one of {STATIC_LINK_MODES}")
        if int(self.init_samples) < 1:
            raise ValueError(f"init_samples must be >= 1, got {self.init_samples}")
        if not (np.isfinite(self.calibration_duration_s) and self.calibration_duration_s > 0):
            raise ValueError(f"calibration duration must be > 0 s, got {self.calibration_duration_s}")
        for name in ("T_rig_ots", "T_base_ots"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, pose_to_T(v))
                if self.calibration is not None and name in self.calibration.links:
                    where = self.calibration_file or self.calibration.source
                    raise ValueError(f"{name} is given both as a parameter and in the calibration file {where!r}; "
                                     "give it once (the calibrate executable's 'links' parameter selects the links "
                                     "it writes)")


def links_needed(cfg: ChainConfig) -> tuple[str, ...]:
    """The links a calibration of this chain estimates: T_omc_base, plus T_rig_ots (tracked) or T_base_ots
    (static, direct) unless that one is given as a parameter."""
    if cfg.local_chain == "tracked":
        return ("T_omc_base",) if cfg.T_rig_ots is not None else ("T_omc_base", "T_rig_ots")
    return ("T_omc_base",) if cfg.T_base_ots is not None else ("T_omc_base", "T_base_ots")


class StaticLinks:
    """Estimates the chain's static links from stationary sightings (mode ``cfg.static_links``, module docstring).

    ``T_omc_base`` is needed by the global path; the local link (``T_base_ots`` and, for ``tracked``,
    ``T_rig_ots``) becomes ready independently, so global fusion starts even while the OTS cannot see the base
    marker yet. While a re-estimation is running the previous links stay in use. ``estimates`` holds the links
    that carry a covariance (calibrate mode, a calibration file, :meth:`apply`, and the averages of
    average mode and of calibrate mode's bridge); ``sources`` says per link how it
    was obtained.
    """

    def __init__(self, cfg: ChainConfig) -> None:
        self.cfg = cfg
        self.T_omc_base: np.ndarray | None = None
        self.T_base_ots: np.ndarray | None = cfg.T_base_ots
        self.T_rig_ots: np.ndarray | None = cfg.T_rig_ots
        self.estimates: dict[str, LinkEstimate] = {}
        self.sources: dict[str, str] = {k: "parameter" for k in ("T_base_ots", "T_rig_ots")
                                        if getattr(cfg, k) is not None}
        self.generation = 0  # bumps each time a link is (re-)estimated
        self.refusals = 0    # calibrate mode: collections refused (body moved, too few sightings)
        self.last_refusal = ""
        self.mode = cfg.static_links
        self._collect: dict[str, list[np.ndarray]] | None = None
        self._cal: dict[str, Collector] = {}
        self._avg_global = self._avg_local = False   # links the average estimates (average mode, calibrate's bridge)
        if cfg.calibration is not None:
            self.apply(cfg.calibration, f"calibration file {cfg.calibration_file}".strip())
        self.start(initial=True)

    def start(self, mode: str | None = None, initial: bool = False) -> None:
        """(Re-)start estimating every link that is not a parameter, in ``mode`` (default ``cfg.static_links``);
        previous links remain valid until the new ones are computed. ``initial``: links of the calibration file
        are kept (construction)."""
        c = self.cfg
        self.mode = mode or c.static_links
        if self.mode not in STATIC_LINK_MODES:
            raise ValueError(f"static_links mode '{self.mode}' is not one of {STATIC_LINK_MODES}")
        from_file = set(c.calibration.links) if initial and c.calibration is not None else set()
        self._need_global = "T_omc_base" not in from_file
        local = "T_rig_ots" if c.local_chain == "tracked" else "T_base_ots"
        self._need_local = getattr(c, local) is None and local not in from_file
        if self.mode == "average":
            self._avg_global, self._avg_local = self._need_global, self._need_local
        else:   # the bridge: only links without a value (a re-estimation keeps the previous link meanwhile)
            self._avg_global = self._need_global and self.T_omc_base is None
            self._avg_local = self._need_local and getattr(self, local) is None
        bridge = self._avg_global or self._avg_local
        self._collect = {"omc_base": [], "omc_rig": [], "ots_base": []} if bridge else None
        self._cal = {}
        if self.mode == "calibrate":
            parts = (["global"] if self._need_global else []) + (self._local_parts() if self._need_local else [])
            self._cal = {p: self._collector(p) for p in parts}

    @property
    def collecting(self) -> bool:
        return self._need_global or self._need_local

    @property
    def global_ready(self) -> bool:
        return self.T_omc_base is not None

    @property
    def local_ready(self) -> bool:
        if self.cfg.local_chain == "tracked":
            return self.T_omc_base is not None and self.T_rig_ots is not None
        return self.T_base_ots is not None

    def progress(self) -> dict[str, int]:
        """Sightings collected so far per body ('omc_base', 'omc_rig', 'ots_base')."""
        if self.mode == "average":
            c = self._collect or {}
            return {k: len(v) for k, v in c.items()}
        keys = {("omc", self.cfg.omc_base): "omc_base", ("omc", self.cfg.omc_rig): "omc_rig",
                ("ots", self.cfg.ots_base): "ots_base"}
        out = {k: 0 for k in keys.values()}
        for part, col in self._cal.items():
            for key, n in col.counts().items():
                dev, body = key.split(":", 1)
                k = "omc_rig" if part == "rig" else keys.get((dev, body))
                if k is not None:
                    out[k] = max(out[k], n)
        return out

    def describe(self) -> str:
        """What is being waited for, for /diagnostics ('' when nothing is being estimated)."""
        if not self.collecting:
            return ""
        if self.mode == "average":
            return f"waiting for {self.cfg.init_samples} samples of each static body (have {self.progress()})"
        spans = [(col.last_ns - col.start_ns) / 1e9 for col in self._cal.values()
                 if col.start_ns is not None and col.last_ns is not None]
        text = (f"calibrating the static links over {self.cfg.calibration_duration_s:g} s of stamps "
                f"({max(spans, default=0.0):.1f} s collected, sightings {self.progress()})")
        if self._avg_global or self._avg_local or any(_BRIDGE in v for v in self.sources.values()):
            text += f"; meanwhile the average of the first {self.cfg.init_samples} samples"
        return text + (f"; {self.refusals} collection(s) refused, last: {self.last_refusal}" if self.refusals else "")

    def add(self, which: str, T: np.ndarray, t_ns: int | None = None) -> bool:
        """Feed one observation ('omc_base', 'omc_rig' or 'ots_base') stamped ``t_ns`` [ns] (needed in calibrate
        mode); True when a link was updated."""
        if not self.collecting:
            return False
        changed = False
        if self._collect is not None and (self._avg_global or self._avg_local):   # average mode or the bridge
            n = int(self.cfg.init_samples)
            buf = self._collect[which]
            if len(buf) < n:
                buf.append(T)
            changed = self._try_finish(n)
        if self.mode == "calibrate":
            if t_ns is None:
                raise ValueError("calibrate mode needs the stamp of every observation")
            c = self.cfg
            if which == "omc_base":   # (not a dict built per sighting)
                dev, body = "omc", c.omc_base
            elif which == "omc_rig":
                dev, body = "omc", c.omc_rig
            elif which == "ots_base":
                dev, body = "ots", c.ots_base
            else:
                raise KeyError(which)
            cols = self._cal.values()
            for col in cols:
                col.add(dev, body, t_ns, T)
            for col in cols:   # nothing to finish until a collection is complete: most sightings
                if col.complete:
                    changed = self._try_finish_calibrate() or changed
                    break
        return changed

    def apply(self, cal: Calibration, source: str) -> None:
        """Use the links of ``cal`` from now on (all in one step); stops estimating the links it provides."""
        for name, est in cal.links.items():
            setattr(self, name, est.T)
            self.estimates[name] = est
            self.sources[name] = source
        local = "T_rig_ots" if self.cfg.local_chain == "tracked" else "T_base_ots"
        if "T_omc_base" in cal.links:
            self._need_global = self._avg_global = False
            self._cal.pop("global", None)
        if local in cal.links:
            self._need_local = self._avg_local = False
            for p in ("eq2", "rig", "tracked"):
                self._cal.pop(p, None)
        self.generation += 1

    # ---- average mode (and calibrate mode's bridge) ------------------------------------------
    def _done_avg(self, part: str) -> None:
        """The average of ``part`` ('global' | 'local') is set: done in average mode; the bridge waits on."""
        setattr(self, f"_avg_{part}", False)
        if self.mode == "average":
            setattr(self, f"_need_{part}", False)

    def _set_average(self, name: str, source: str, samples: list[np.ndarray] | None = None) -> None:
        """Name the averaged link; ``samples``: the sightings it is the mean of, whose covariance of the mean
        (:func:`calibration.mean_estimate`) then goes into ``estimates`` (the model covariances of a local sample
        and ``pipeline``'s frame covariance use it)."""
        if self.mode == "calibrate":
            source += f", {_BRIDGE} over {self.cfg.calibration_duration_s:g} s is done"
        self._set_source(name, source)
        if samples is not None and len(samples) >= 2:
            self.estimates[name] = mean_estimate(samples, getattr(self, name), source=source)

    def _try_finish(self, n: int) -> bool:
        c = self._collect
        assert c is not None
        changed = False
        if self._avg_global and len(c["omc_base"]) >= n:
            self.T_omc_base = mean_T(c["omc_base"])
            self._set_average("T_omc_base", f"average of {n} samples", c["omc_base"])
            self._done_avg("global")
            changed = True
        if self._avg_local and not self._avg_global and self.T_omc_base is not None:
            T_omc_base = self.T_omc_base
            assert T_omc_base is not None
            given_rig = self.T_rig_ots   # static/direct: the hand-eye calibration (parameter or file), if any
            if self.cfg.local_chain == "tracked":
                # T_rig_ots = inv(T_omc_rig) T_omc_base inv(T_ots_base): both systems see the base marker.
                if len(c["omc_rig"]) >= n and len(c["ots_base"]) >= n:
                    T_base_ots = mean_T([inv_T(T) for T in c["ots_base"]])
                    self.T_rig_ots = inv_T(mean_T(c["omc_rig"])) @ T_omc_base @ T_base_ots
                    self.T_base_ots = T_base_ots
                    self._set_average("T_rig_ots", f"average of {n} samples (eq. 1)")
                    self._done_avg("local")
                    changed = True
            elif len(c["ots_base"]) >= n:
                # eq. (2) averaged: the OTS sees the base marker directly.
                inverted = [inv_T(T) for T in c["ots_base"]]
                self.T_base_ots = mean_T(inverted)
                self._set_average("T_base_ots", f"average of {n} samples (eq. 2)", inverted)
                self._done_avg("local")
                changed = True
            elif given_rig is not None and len(c["omc_rig"]) >= n:
                # eq. (1) averaged with the hand-eye calibration T_rig_ots.
                self.T_base_ots = inv_T(T_omc_base) @ mean_T(c["omc_rig"]) @ given_rig
                self._set_average("T_base_ots", f"average of {n} rig samples and T_rig_ots (eq. 1)")
                self._done_avg("local")
                changed = True
        if changed:
            self.generation += 1
        return changed

    def _set_source(self, name: str, source: str) -> None:
        self.sources[name] = source
        self.estimates.pop(name, None)

    # ---- calibrate mode ----------------------------------------------------------------------
    def _local_parts(self) -> list[str]:
        if self.cfg.local_chain == "tracked":
            return ["tracked"]
        return ["eq2"] + (["rig"] if self.T_rig_ots is not None else [])

    def _collector(self, part: str) -> Collector:
        c = self.cfg
        bodies = CalibrationBodies(c.omc_base, c.ots_base, c.omc_rig)
        links = {"global": ("T_omc_base",), "eq2": ("T_base_ots",), "tracked": ("T_rig_ots",),
                 "rig": ("T_omc_base",)}[part]
        if part == "rig":   # the robust mean of the rig's pose: a T_omc_base collector watching the rig body
            bodies = CalibrationBodies(c.omc_rig, c.ots_base, c.omc_rig)
        return Collector(links, bodies, c.calibration_duration_s, c.calibration_settings)

    def _finish(self, part: str) -> Calibration | None:
        try:
            return self._cal[part].finish(source=f"{self.mode} mode")
        except CalibrationError as e:
            self.refusals += 1
            self.last_refusal = str(e)
            self._cal[part] = self._collector(part)   # collect again from the next sighting on
            return None

    def _try_finish_calibrate(self) -> bool:
        c, changed = self.cfg, False
        dur = f"robust mean over {c.calibration_duration_s:g} s"
        g = self._cal.get("global")
        if g is not None and g.complete:
            cal = self._finish("global")
            if cal is not None:
                est = cal.links["T_omc_base"]
                self.T_omc_base, self.estimates["T_omc_base"] = est.T, est
                self.sources["T_omc_base"] = dur
                self._need_global = self._avg_global = False
                del self._cal["global"]
                changed = True
        for part in ("eq2", "rig", "tracked"):
            col = self._cal.get(part)
            if not self._need_local or col is None or not col.complete:
                continue
            if part != "eq2" and self._need_global:
                continue   # eq. 1 needs the T_omc_base the chain uses; wait for it (the collector keeps its window)
            cal = self._finish(part)
            if cal is None:
                continue
            if part == "eq2":
                est = cal.links["T_base_ots"]
                self.T_base_ots, self.estimates["T_base_ots"] = est.T, est
                self.sources["T_base_ots"] = f"{dur} (eq. 2)"
            elif part == "rig":
                assert self.T_omc_base is not None and self.T_rig_ots is not None
                self.T_base_ots = inv_T(self.T_omc_base) @ cal.links["T_omc_base"].T @ self.T_rig_ots
                self.estimates.pop("T_base_ots", None)
                self.sources["T_base_ots"] = f"{dur} of the rig and T_rig_ots (eq. 1)"
            else:
                X = self.estimates.get("T_omc_base") or cal.links["T_omc_base"]
                tr, Tr = col.samples("omc", c.omc_rig)
                to, To = col.samples("ots", c.ots_base)
                try:
                    est = link_T_rig_ots(tr, Tr, to, To, X, c.calibration_settings, Collector.label("omc", c.omc_rig),
                                         Collector.label("ots", c.ots_base))
                except CalibrationError as e:
                    self.refusals += 1
                    self.last_refusal = f"calibration refused: {e}"
                    self._cal[part] = self._collector(part)
                    continue
                self.T_rig_ots, self.estimates["T_rig_ots"] = est.T, est
                self.sources["T_rig_ots"] = f"{dur} (eq. 1)"
            self._need_local = self._avg_local = False
            for p in ("eq2", "rig", "tracked"):
                self._cal.pop(p, None)
            changed = True
            break
        if changed:
            self.generation += 1
        return changed
