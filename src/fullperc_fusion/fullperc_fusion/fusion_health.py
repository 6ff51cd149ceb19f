"""Alarms of one fused target for /diagnostics: a jumping or mis-compensated global source, a rejected source.

ROS-free and clock-free: every call takes ``now`` [s] on one monotonic clock chosen by the caller
(``fusion_node`` passes ``time.monotonic()`` at the moment it handles the data), so the rules are unit-tested
with made-up times. ``fusion_node`` feeds it what it already has: every input sample of a target's sources
that the pipeline refused (:meth:`TargetHealth.rejected`) and every output of the primary filter
(:meth:`TargetHealth.output`, the data of FusionStatus), and publishes :meth:`TargetHealth.alarms`.

Why: a 1 m jump of the OMC was followed by the filter, raised 172 hop flags and drove the CBKF bias to 1.0 m,
and /diagnostics said nothing -- hops and the bias were only in FusionStatus. A single hop is normal (the set of
cameras that see the target changed; hop_to_bias moves the step into b) and stays in FusionStatus only.

The rules (thresholds are :class:`HealthParams`, node parameters ``alarm.*`` in config/fusion.yaml):

* **hop rate** (WARN, global source): more than ``hop_max`` outputs flagged as a hop within the last
  ``hop_window_s`` seconds (the count is over the window ending at the newest hop: ``t_hop > now - window``).
* **compensation** (WARN, global source): the norm of the estimated bias b of the global source,
  |b| = sqrt(bx^2 + by^2 + bz^2) of the newest primary output, is above ``bias_max_m``. The bias models the OMC's
  systematic error (millimetres: calibration, distortion); a larger one is a jump the filter absorbed, a moved
  base marker or a wrong static link. Filters without a bias state (kf, bkf, omc) report b = 0.
* **all rejected** (ERROR, per source): a *run* of rejections starts at the first rejected sample of a source
  and ends when a sample of that source that was accepted *after* the run started is used by the primary filter
  (its bit is set in an output). It is an alarm while the run has lasted ``reject_timeout_s`` and the newest
  rejection is less than ``reject_timeout_s`` old (the source is still sending; a source that went silent is
  reported as silent by the node, not here). A run lasts the longer of ``now - first_rejection`` and the span of
  its samples' stamps (those the caller passes: not of samples refused for their stamp): a node that fell behind
  takes seconds of a source's refused samples in one burst, and by its clock alone that run would never last the
  timeout (a CI run on a busy machine: no ERROR for 2.5 s of NaN poses). "Rejected" = refused at the input
  (non-finite, non-unit quaternion, bad stamp, late, duplicate) or skipped by the chain (local_skipped);
  "accepted" = taken by the pipeline at the input. Outputs of samples accepted before the run (they come out up
  to ``reorder_delay`` or ``idle_flush`` later) do not end it; samples waiting for the static links neither start
  nor end one.
* **stamp offset** (WARN, local source): the OMC's and the Vega's stamps of one instant disagree. Every
  ``offset_period_s`` of stamps the last ``offset_window_s`` of the target's accepted samples of each source go to
  :func:`~fullperc_fusion.calibration.time_offset.align_tracks` (the speed of the target seen by each device,
  cross-correlated: frame-free, so no link is needed); an offset ``|d| > offset_warn_s`` (half of ``slop``: pairs
  then form with the wrong partner, and a moving target is ``speed x d`` off) that is also more than 3 sigma is a
  WARN naming it and ``time_align`` (docs/time_alignment.md). Windows without enough motion are skipped. Started
  from :meth:`TargetHealth.alarms` (the diagnostics timer), never on the input path: one estimate costs ~20-35 ms,
  in fusion_node on a worker thread (``background``; its result at the next call).
* every alarm stays raised ``hold_s`` seconds after its condition last held (a burst between two /diagnostics
  publications is not lost; as the node's other problems, ``problem_hold``), with "(cleared N s ago)". The
  conditions are evaluated at every input and again at every :meth:`TargetHealth.alarms` call; the bias rule
  holds as long as the newest output's bias does (the filter keeps b when the data stop; nothing but the data
  resets it).

Levels are the diagnostic_msgs values (OK 0, WARN 1, ERROR 2); messages name the target and the source.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from fullperc_common.background import Job
from fullperc_fusion.filters.api import Role

OK, WARN, ERROR = 0, 1, 2
GLOBAL, LOCAL = Role.GLOBAL.label, Role.LOCAL.label   # the per-source keys (filters.api.Role)
_BITS = {r.label: r.bit for r in Role}   # fullperc_msgs/FusionStatus SOURCE_GLOBAL / SOURCE_LOCAL


@dataclass(frozen=True)
class HealthParams:
    """Alarm thresholds; see the module docstring for the rules."""

    hop_window_s: float = 2.0     # [s] window of the hop count
    hop_max: int = 5              # [hops] more than this many within the window -> WARN
    bias_max_m: float = 0.02      # [m] |b| above this -> WARN
    reject_timeout_s: float = 1.0  # [s] every sample rejected for this long -> ERROR
    hold_s: float = 10.0          # [s] an alarm stays raised this long after its condition last held
    offset_warn_s: float = 0.002  # [s] |stamp offset| OMC vs OTS above this -> WARN (fusion_node: slop / 2)
    offset_window_s: float = 10.0  # [s] of samples per stamp-offset estimate
    offset_period_s: float = 10.0  # [s] of stamps between two estimates

    def validate(self) -> HealthParams:
        for name in ("hop_window_s", "bias_max_m", "reject_timeout_s", "hold_s", "offset_warn_s", "offset_window_s",
                     "offset_period_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"health parameter {name} must be finite and > 0, got {v!r}")
        if isinstance(self.hop_max, bool) or not isinstance(self.hop_max, int) or self.hop_max < 1:
            raise ValueError(f"health parameter hop_max must be an integer >= 1, got {self.hop_max!r}")
        return self


@dataclass(frozen=True)
class Alarm:
    level: int          # WARN or ERROR
    rule: str           # 'hop_rate' | 'bias' | 'rejected' | 'stamp_offset'
    source: str         # GLOBAL | LOCAL
    message: str        # names the target and the source


class _Held:
    """Condition -> alarm with a hold: remembers when the condition last held and what it said then."""

    __slots__ = ("last_true", "message")

    def __init__(self) -> None:
        self.last_true: float | None = None
        self.message = ""

    def mark(self, now: float, message: str) -> None:
        self.last_true = now
        self.message = message

    def active(self, now: float, hold: float) -> str | None:
        if self.last_true is None or now - self.last_true > hold:
            return None
        age = now - self.last_true
        return self.message if age <= 0 else f"{self.message} (cleared {age:.1f} s ago)"


class StampOffsetWatch:
    """The stamp offset of the local source against the global one from the target's accepted samples (the rule
    "stamp offset" of the module docstring): a ring of (stamp, position) per source, an estimate every ``period_s``
    of stamps."""

    MIN_STEP_NS = 4_000_000   # a sample closer than this to the ring's newest is skipped: <= 250 Hz per source,
    # so one estimate costs ~25 ms whatever the devices' rates (1 kHz streams: 54 ms without it)

    def __init__(self, window_s: float, period_s: float, background: bool = False) -> None:
        # imported here, at the node's start, not at the first estimate: an import on the worker thread takes the
        # GIL in turns with the input thread (measured: a 1 kHz loop 20-28 ms late at the first estimate, against
        # 1-12 ms with the import done before). time_offset needs neither scipy.signal nor scipy.stats, so this
        # costs fusion_node ~0.1 s of CPU (fusion_health is imported by offline tools too)
        from fullperc_fusion.calibration import time_offset

        self._align, self._error = time_offset.align_tracks, time_offset.AlignmentError
        self.window_ns, self.period_ns = int(window_s * 1e9), int(period_s * 1e9)
        self.rings: dict[str, deque] = {GLOBAL: deque(), LOCAL: deque()}
        self.newest_ns: int | None = None
        self.due_ns: int | None = None
        self.last = None          # the newest Alignment (time_offset), None before one succeeded
        self._job = Job(self._fit, background)   # fusion_node: on the worker thread (fullperc_common.background)

    def add(self, source: str, t_ns: int, p) -> None:
        ring = self.rings[source]
        if ring and t_ns - ring[-1][0] < self.MIN_STEP_NS:
            if ring[-1][0] - t_ns <= self.window_ns:   # a late or too close sample: the ring keeps stamp order
                return
            for r in self.rings.values():           # stamps went back for good (a restarted timeline): anew
                r.clear()
            self.newest_ns = self.due_ns = None
        ring.append((t_ns, p))
        self.newest_ns = t_ns if self.newest_ns is None else max(self.newest_ns, t_ns)
        if self.due_ns is None:
            self.due_ns = t_ns + self.period_ns
        while ring and ring[0][0] < self.newest_ns - self.window_ns:
            ring.popleft()

    def estimate(self):
        """A new :class:`~fullperc_fusion.calibration.time_offset.Alignment` when one is due and the window allows
        one (enough motion seen by both), else None; in the background, one call after the one that started it."""
        if not self._job.running:
            if self.newest_ns is None or self.due_ns is None or self.newest_ns < self.due_ns:
                return None
            self.due_ns = self.newest_ns + self.period_ns
            g, loc = self.rings[GLOBAL], self.rings[LOCAL]
            if len(g) < 20 or len(loc) < 20:
                return None
            t0 = g[0][0]
            self._job.start(np.array([t - t0 for t, _ in g]) * 1e-9, np.array([p for _, p in g], float),
                            np.array([t - t0 for t, _ in loc]) * 1e-9, np.array([p for _, p in loc], float))
            if self._job.background:
                return None   # its result at a later call, never at the one that started it
        done, a = self._job.poll()
        if done and a is not None:
            self.last = a
        return a

    def _fit(self, tg, pg, tl, pl):
        try:
            return self._align(tg, pg, tl, pl, max_lag_s=0.2)
        except (self._error, ValueError):
            return None


class TargetHealth:
    """The alarm state of one target; ``sources`` names the two sources, e.g. {"global": "OMC body 'tool'"}."""

    def __init__(self, target: str, sources: dict[str, str], params: HealthParams | None = None,
                 background: bool = False) -> None:
        self.target = target
        self.names = {GLOBAL: sources.get(GLOBAL, "global source"), LOCAL: sources.get(LOCAL, "local source")}
        self.params = (params or HealthParams()).validate()
        self._hops: deque[float] = deque()
        self.hops_total = 0
        self.bias_norm_m = 0.0
        self._bias = np.zeros(3)
        self._run_first: dict[str, float | None] = {GLOBAL: None, LOCAL: None}
        self._run_last: dict[str, float | None] = {GLOBAL: None, LOCAL: None}
        self._run_count = {GLOBAL: 0, LOCAL: 0}
        self._run_reason = {GLOBAL: "", LOCAL: ""}
        self._run_stamps: dict[str, list[int]] = {GLOBAL: [], LOCAL: []}   # the run's [oldest, newest] stamp
        self._last_accept: dict[str, float | None] = {GLOBAL: None, LOCAL: None}
        self._held = {("hop_rate", GLOBAL): _Held(), ("bias", GLOBAL): _Held(),
                      ("rejected", GLOBAL): _Held(), ("rejected", LOCAL): _Held(), ("stamp_offset", LOCAL): _Held()}
        self.offset = StampOffsetWatch(self.params.offset_window_s, self.params.offset_period_s, background)

    # ---- input --------------------------------------------------------------------------------------------
    def accepted(self, source: str, now: float, t_ns: int | None = None, p=None) -> None:
        """A sample of ``source`` was taken by the pipeline at ``now``; with its stamp and position (the device's
        frame) it also goes to the stamp-offset watch."""
        self._last_accept[source] = now
        if t_ns is not None and p is not None:
            self.offset.add(source, t_ns, p)

    def rejected(self, source: str, now: float, reason: str = "", n: int = 1, t_ns: int | None = None) -> None:
        """``n`` samples of ``source`` were refused at ``now`` (``reason``: the pipeline's description); ``t_ns``:
        the sample's stamp, when it is one to go by (module docstring, "all rejected")."""
        if n <= 0:
            return
        span = self._run_stamps[source]
        if self._run_first[source] is None:
            self._run_first[source] = now
            self._run_count[source] = 0
            span.clear()
        if t_ns is not None:
            span[:] = [min(span[0], t_ns), max(span[1], t_ns)] if span else [t_ns, t_ns]
        self._run_last[source] = now
        self._run_count[source] += n
        if reason:
            self._run_reason[source] = reason
        self._check_rejected(source, now)

    def output(self, now: float, sources: int, hop: bool, bias) -> None:
        """One output of the primary filter: its source bits, hop flag and bias estimate [m] (FusionStatus)."""
        for s, bit in _BITS.items():
            first, acc = self._run_first[s], self._last_accept[s]
            if sources & bit and first is not None and acc is not None and acc >= first:
                self._run_first[s] = self._run_last[s] = None
                self._run_count[s] = 0
        b = np.asarray(bias, dtype=float).reshape(3)
        self._bias = b
        self.bias_norm_m = float(np.linalg.norm(b)) if np.all(np.isfinite(b)) else math.inf
        if hop:
            self.hops_total += 1
            self._hops.append(now)
        self._check_bias_and_hops(now)

    # ---- output -------------------------------------------------------------------------------------------
    def alarms(self, now: float) -> list[Alarm]:
        """The raised alarms at ``now``, most severe first."""
        self._check_bias_and_hops(now)
        for s in (GLOBAL, LOCAL):
            self._check_rejected(s, now)
        self._check_offset(now)
        out = []
        for (rule, source), h in self._held.items():
            msg = h.active(now, self.params.hold_s)
            if msg is not None:
                out.append(Alarm(ERROR if rule == "rejected" else WARN, rule, source, msg))
        return sorted(out, key=lambda a: -a.level)

    def values(self, now: float) -> dict:
        """Key values for the diagnostic status."""
        self._prune(now)
        v = {"hops_in_window": len(self._hops), "hops_total": self.hops_total,
             "bias_norm_mm": round(1e3 * self.bias_norm_m, 3)}
        if (a := self.offset.last) is not None:
            v["stamp_offset_ms"] = round(1e3 * a.offset_s, 3)
            v["stamp_offset_sigma_ms"] = round(1e3 * a.offset_sigma_s, 3)
        for s in (GLOBAL, LOCAL):
            v[f"{s}_rejected_run_s"] = round(self._run_s(s, now), 3)
        return v

    def _run_s(self, source: str, now: float) -> float:
        """How long the current run of rejections of ``source`` has lasted (module docstring); 0 without one."""
        first, span = self._run_first[source], self._run_stamps[source]
        if first is None:
            return 0.0
        return max(now - first, 1e-9 * (span[1] - span[0]) if span else 0.0)

    # ---- rules --------------------------------------------------------------------------------------------
    def _prune(self, now: float) -> None:
        w = self.params.hop_window_s
        while self._hops and self._hops[0] <= now - w:
            self._hops.popleft()

    def _check_bias_and_hops(self, now: float) -> None:
        """The two WARN rules on the newest output (bias) and on the hops within the window ending at ``now``."""
        p = self.params
        self._prune(now)
        if self.bias_norm_m > p.bias_max_m:
            self._held[("bias", GLOBAL)].mark(now, (
                f"target '{self.target}': compensation of the {self.names[GLOBAL]} is implausible: "
                f"|bias| = {1e3 * self.bias_norm_m:.1f} mm > {1e3 * p.bias_max_m:.1f} mm (bias [mm] "
                f"{np.round(1e3 * self._bias, 1).tolist()}; the global source jumped, the base marker moved or a "
                "static link is wrong)"))
        if len(self._hops) > p.hop_max:
            self._held[("hop_rate", GLOBAL)].mark(now, (
                f"target '{self.target}': the {self.names[GLOBAL]} hops too often: {len(self._hops)} hops "
                f"within {p.hop_window_s:g} s (more than {p.hop_max}; single hops when cameras change are normal)"))

    def _check_offset(self, now: float) -> None:
        """The stamp-offset rule on a new estimate (none due: the alarm's hold decides)."""
        a = self.offset.estimate()
        if a is None or not math.isfinite(a.offset_s):
            return
        d, sd, warn = a.offset_s, a.offset_sigma_s, self.params.offset_warn_s
        if abs(d) > warn and abs(d) > 3 * sd:
            late = "late" if d > 0 else "early"
            self._held[("stamp_offset", LOCAL)].mark(now, (
                f"target '{self.target}': the {self.names[LOCAL]}'s stamps are {late} by {1e3 * abs(d):.1f} ms "
                f"(+- {1e3 * sd:.1f}) against the {self.names[GLOBAL]}'s, more than {1e3 * warn:.1f} ms (half of "
                "slop): pairs form with the wrong partner; measure and set device_latency_s with time_align "
                "(docs/time_alignment.md)"))

    def _check_rejected(self, source: str, now: float) -> None:
        last, T, run = self._run_last[source], self.params.reject_timeout_s, self._run_s(source, now)
        if last is None or run < T or now - last >= T:
            return
        why = self._run_reason[source]
        self._held[("rejected", source)].mark(now, (
            f"target '{self.target}': every sample of the {self.names[source]} rejected for {run:.1f} s "
            f"({self._run_count[source]} samples, none used)" + (f"; last: {why}" if why else "")))
