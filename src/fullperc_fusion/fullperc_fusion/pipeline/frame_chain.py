"""Frame chain of the paper's eq. (1) and (2): every measurement of a target expressed in ``base``.

Notation as in ``fullperc_common.transforms``: ``T_a_b`` maps points from frame b into frame a.

* Global (OMC) measurement:   T_base_tool = inv(T_omc_base) · T_omc_tool
* Local (OTS) measurement, eq. (1):
      T_base_tool = inv(T_omc_base) · T_omc_rig · T_rig_ots · T_ots_tool
  where ``rig`` is the OMC body rigidly attached to the OTS (the paper's {Robot}); or eq. (2), when the
  OTS sees the base marker in the same frame:  T_base_tool = inv(T_ots_base) · T_ots_tool.

Static links are not measured live, because every live factor adds its own noise and hops to the
measurement: the base marker is fixed, so T_omc_base is the average of the OMC's base observations at
initialization; T_rig_ots (eq. 1; hand-eye calibration in the paper) is given or estimated from
simultaneous observations of the base marker by both systems; with a stationary OTS (a Vega on a
stand), the whole local prefix collapses to one static T_base_ots. Averages of rotations use
``mean_T`` (the chordal L2 mean), never a component-wise average of matrix entries or quaternions.

The bodies must be stationary while the links are being estimated (the paper's initialization:
"both positioning systems could see the target and the marker representing the global coordinate
system"); :class:`StaticLinks` can be re-estimated on request (``fusion_node``'s ``~/initialize``).

How the static links are estimated (``static_links``; a link given as a parameter is never estimated):
  * ``average``   the chordal mean of the first ``init_samples`` sightings of each body.
  * ``calibrate`` (default) the robust SE(3) mean of :mod:`fullperc_fusion.calibration.se3_stats`
                  (outliers rejected, refused when a body moved or too few sightings came) over
                  ``calibration_duration_s`` seconds of stamps, one
                  :class:`~fullperc_fusion.calibration.se3_stats.Collector` for the global link and one for the local
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

Local chain modes (``local_chain``):
  * ``static``  (default) T_base_ots fixed: given, or from eq. (2) averages (OTS sees base), or eq. (1)
                averages with a given T_rig_ots. Right for an OTS on a stand.
  * ``tracked`` eq. (1) with the live OMC pose of the rig (nearest in time) and a static T_rig_ots.
                Right for an OTS on a moving arm.
  * ``direct``  eq. (2) live whenever the OTS saw the base marker in the same frame, else ``static``.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fullperc_common.transforms import inv_T, mean_T
from fullperc_fusion.calibration.poses import BadSample, pose_to_T
from fullperc_fusion.calibration.se3_stats import (
    Calibration,
    CalibrationBodies,
    CalibrationError,
    CalibrationSettings,
    Collector,
    LinkEstimate,
    link_T_rig_ots,
    mean_estimate,
)

__all__ = ["LOCAL_CHAINS", "STATIC_LINK_MODES", "BadSample", "ChainConfig", "FrameChain", "StaticLinks",
           "links_needed", "pose_to_T"]

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
            dev, body = {"omc_base": ("omc", c.omc_base), "omc_rig": ("omc", c.omc_rig),
                         "ots_base": ("ots", c.ots_base)}[which]
            for col in self._cal.values():
                col.add(dev, body, t_ns, T)
            changed = self._try_finish_calibrate() or changed
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


class _Recent:
    """Last few stamped poses of one body, for nearest-in-time lookup."""

    def __init__(self, maxlen: int = 256) -> None:
        self.t: deque[int] = deque(maxlen=maxlen)
        self.T: deque[np.ndarray] = deque(maxlen=maxlen)

    def add(self, t_ns: int, T: np.ndarray) -> None:
        if self.t and t_ns < self.t[-1]:
            ts = list(self.t)
            i = bisect.bisect_right(ts, t_ns)
            if i == 0 and len(self.t) == self.t.maxlen:
                return  # older than everything kept
            Ts = list(self.T)
            ts.insert(i, t_ns)
            Ts.insert(i, T)
            self.t.clear()
            self.T.clear()
            self.t.extend(ts)
            self.T.extend(Ts)
            return
        self.t.append(t_ns)
        self.T.append(T)

    def nearest(self, t_ns: int, max_age_ns: int) -> np.ndarray | None:
        if not self.t:
            return None
        ts = self.t   # bisect on the deque itself: copying 256 stamps to a list per lookup cost more than the rest
        i = bisect.bisect_left(ts, t_ns)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(ts) and abs(ts[j] - t_ns) <= max_age_ns and (
                    best is None or abs(ts[j] - t_ns) < abs(ts[best] - t_ns)):
                best = j
        return None if best is None else self.T[best]


class FrameChain:
    """Turns raw device poses of one target into global and local measurements in ``base``.

    Feed every device pose through :meth:`observe_omc` / :meth:`observe_ots` (they collect the
    initialization averages and the live rig / base poses the chain needs), then call
    :meth:`global_T` / :meth:`local_T` for target samples. Both return None with a reason in
    :attr:`why_not` when the measurement cannot be formed yet.
    """

    def __init__(self, cfg: ChainConfig) -> None:
        self.cfg = cfg
        self.links = StaticLinks(cfg)
        self._rig = _Recent()
        self._ots_base = _Recent()
        self.why_not = ""
        self._inv_src: np.ndarray | None = None   # the T_omc_base whose inverse is cached (kept: no id reuse)
        self._inv: np.ndarray | None = None

    def _inv_omc_base(self, T_omc_base: np.ndarray) -> np.ndarray:
        """inv(T_omc_base), computed once per link estimate instead of once per sample (issue 16: per-sample
        cost). Links are replaced, never modified in place (StaticLinks sets new arrays; arrival.py's link views
        rely on the same), so the identity of the array names its value."""
        if T_omc_base is not self._inv_src:
            self._inv_src, self._inv = T_omc_base, inv_T(T_omc_base)
        return self._inv

    def reinitialize(self, mode: str | None = None) -> None:
        """Re-estimate the static links (``mode``: average | calibrate, default the configured one)."""
        self.links.start(mode)

    def observe_omc(self, body: str, t_ns: int, T: np.ndarray) -> None:
        if body == self.cfg.omc_base:
            self.links.add("omc_base", T, t_ns)
        if body == self.cfg.omc_rig:
            self.links.add("omc_rig", T, t_ns)
            self._rig.add(t_ns, T)

    def observe_ots(self, tool: str, t_ns: int, T: np.ndarray) -> None:
        if tool == self.cfg.ots_base:
            self.links.add("ots_base", T, t_ns)
            self._ots_base.add(t_ns, T)

    def global_T(self, T_omc_tool: np.ndarray) -> np.ndarray | None:
        """inv(T_omc_base) · T_omc_tool, or None before T_omc_base is known."""
        if self.links.T_omc_base is None:
            self.why_not = "global link T_omc_base not initialised yet"
            return None
        return self._inv_omc_base(self.links.T_omc_base) @ T_omc_tool

    def local_T(self, t_ns: int, T_ots_tool: np.ndarray) -> tuple[np.ndarray | None, str]:
        """Local measurement in base and the equation used ('eq1', 'eq2', 'static'), or (None, '')."""
        L = self.links
        mode = self.cfg.local_chain
        if mode == "direct":
            T_ots_base = self._ots_base.nearest(t_ns, 0)  # same OTS frame: identical stamp
            if T_ots_base is not None:
                return inv_T(T_ots_base) @ T_ots_tool, "eq2"
        if mode == "tracked":
            if L.T_omc_base is None or L.T_rig_ots is None:
                self.why_not = "local link T_rig_ots not initialised yet"
                return None, ""
            T_omc_rig = self._rig.nearest(t_ns, self.cfg.rig_max_age_ns)
            if T_omc_rig is None:
                self.why_not = f"no OMC pose of '{self.cfg.omc_rig}' within {self.cfg.rig_max_age_ns / 1e6:g} ms"
                return None, ""
            return self._inv_omc_base(L.T_omc_base) @ T_omc_rig @ L.T_rig_ots @ T_ots_tool, "eq1"
        if L.T_base_ots is None:
            self.why_not = "local link T_base_ots not initialised yet"
            return None, ""
        return L.T_base_ots @ T_ots_tool, "static"
