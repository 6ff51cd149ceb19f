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
  (its bit is set in an output). It is an alarm while ``now - first_rejection >= reject_timeout_s`` and the
  newest rejection is less than ``reject_timeout_s`` old (the source is still sending; a source that went
  silent is reported as silent by the node, not here). "Rejected" = refused at the input (non-finite, non-unit
  quaternion, bad stamp, late, duplicate) or skipped by the chain (local_skipped); "accepted" = taken by the
  pipeline at the input. Outputs of samples accepted before the run (they come out up to ``reorder_delay`` or
  ``idle_flush`` later) do not end it; samples waiting for the static links neither start nor end one.
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

OK, WARN, ERROR = 0, 1, 2
GLOBAL, LOCAL = "global", "local"
_BITS = {GLOBAL: 1, LOCAL: 2}   # fullperc_msgs/FusionStatus SOURCE_GLOBAL / SOURCE_LOCAL


@dataclass(frozen=True)
class HealthParams:
    """Alarm thresholds; see the module docstring for the rules."""

    hop_window_s: float = 2.0     # [s] window of the hop count
    hop_max: int = 5              # [hops] more than this many within the window -> WARN
    bias_max_m: float = 0.02      # [m] |b| above this -> WARN
    reject_timeout_s: float = 1.0  # [s] every sample rejected for this long -> ERROR
    hold_s: float = 10.0          # [s] an alarm stays raised this long after its condition last held

    def validate(self) -> HealthParams:
        for name in ("hop_window_s", "bias_max_m", "reject_timeout_s", "hold_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"health parameter {name} must be finite and > 0, got {v!r}")
        if isinstance(self.hop_max, bool) or not isinstance(self.hop_max, int) or self.hop_max < 1:
            raise ValueError(f"health parameter hop_max must be an integer >= 1, got {self.hop_max!r}")
        return self


@dataclass(frozen=True)
class Alarm:
    level: int          # WARN or ERROR
    rule: str           # 'hop_rate' | 'bias' | 'rejected'
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


class TargetHealth:
    """The alarm state of one target; ``sources`` names the two sources, e.g. {"global": "OMC body 'tool'"}."""

    def __init__(self, target: str, sources: dict[str, str], params: HealthParams | None = None) -> None:
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
        self._last_accept: dict[str, float | None] = {GLOBAL: None, LOCAL: None}
        self._held = {("hop_rate", GLOBAL): _Held(), ("bias", GLOBAL): _Held(),
                      ("rejected", GLOBAL): _Held(), ("rejected", LOCAL): _Held()}

    # ---- input --------------------------------------------------------------------------------------------
    def accepted(self, source: str, now: float) -> None:
        """A sample of ``source`` was taken by the pipeline at ``now``."""
        self._last_accept[source] = now

    def rejected(self, source: str, now: float, reason: str = "", n: int = 1) -> None:
        """``n`` samples of ``source`` were refused at ``now`` (``reason``: the pipeline's description)."""
        if n <= 0:
            return
        if self._run_first[source] is None:
            self._run_first[source] = now
            self._run_count[source] = 0
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
        for s in (GLOBAL, LOCAL):
            first = self._run_first[s]
            v[f"{s}_rejected_run_s"] = 0.0 if first is None else round(now - first, 3)
        return v

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

    def _check_rejected(self, source: str, now: float) -> None:
        first, last = self._run_first[source], self._run_last[source]
        T = self.params.reject_timeout_s
        if first is None or last is None or now - first < T or now - last >= T:
            return
        why = self._run_reason[source]
        self._held[("rejected", source)].mark(now, (
            f"target '{self.target}': every sample of the {self.names[source]} rejected for {now - first:.1f} s "
            f"({self._run_count[source]} samples, none used)" + (f"; last: {why}" if why else "")))
