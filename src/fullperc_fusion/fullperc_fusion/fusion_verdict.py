"""fusion_node's /diagnostics verdict of one target: level, message and values from what the node saw.

ROS-free and clock-free, as :mod:`fusion_health`: every call takes ``now`` [s] on one monotonic clock of the
caller's, so :class:`~fullperc_fusion.fusion_core.FusionCore` (and its unit tests, with made-up times) decide what
``fusion_node`` only converts into a DiagnosticStatus. Levels are the diagnostic_msgs values (OK 0, WARN 1, ERROR 2).

The rules of one status (:meth:`TargetVerdict.evaluate`, then :meth:`InputBook.overload`), each adding a message:

* the alarms of :class:`~fullperc_fusion.fusion_health.TargetHealth` (hop rate, bias, every sample rejected);
* WARN while the global static link (then: the local one) is not known yet -- the target is *initializing*;
* WARN while the link monitor sees a bump of the static link, and ``hold`` seconds after it cleared;
* WARN for ``hold`` seconds after a problem count of the pipeline (:data:`PROBLEM_KEYS`) last rose -- a burst
  between two publications is not lost;
* a source with no sample yet, or none for more than ``stale`` seconds, is named; WARN only for the global one (an
  occluded local source is normal: global only, bias compensated);
* overload: WARN when the smallest processing lag of the whole evaluation period (node clock - stamp of the newest
  fused sample) stayed above ``lag_warn`` -- one late callback on a busy machine is no overload --, and for
  ``hold`` seconds after a source's lost samples (:class:`~fullperc_fusion.fusion_health.SourceLoss`) rose.
  What still waits for its pose counts as lost once the source was silent for max(``stale``, LOSS_SILENCE_S)
  while the node kept up (behind, its quality callbacks starve and the poses still queue).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from fullperc_fusion.fusion_health import OK, WARN, InputLoad, SourceLoss, TargetHealth
from fullperc_fusion.pipeline.ordered import TargetPipeline
from fullperc_fusion.pipeline.sources import Route

# [s] silence after which frames still waiting for their pose count as lost: > Fast DDS's 3 s heartbeat, after which
# a reliable reader gets a sample repaired (a demo: 166 OMC samples came 1-3 s late, each fused; 1 s counted them lost)
LOSS_SILENCE_S = 4.0
# the pipeline's problem counts that raise a held WARN (keys of TargetPipeline.counts)
PROBLEM_KEYS = ("rejected_nonfinite", "rejected_nonunit", "rejected_pose", "rejected_stamp", "rejected_future",
                "rejected_jump", "late", "duplicate", "rejected_cov", "local_skipped", "filter_error",
                "nonfinite_output", "publish_error", "calibration_refused", "timeline_restart")

Key = tuple[str, str]   # (device tag, body): one source stream of a target body


class RiseHold:
    """Counters whose rise raises a WARN held ``hold`` seconds: key -> (count, when it last rose)."""

    def __init__(self) -> None:
        self.seen: dict[Any, tuple[int, float]] = {}   # insertion order = the order the keys first rose

    def update(self, key: Any, n: int, now: float) -> None:
        if n > self.seen.get(key, (0, 0.0))[0]:
            self.seen[key] = (n, now)

    def held(self, key: Any, now: float, hold: float) -> bool:
        n, when = self.seen.get(key, (0, 0.0))
        return n > 0 and now - when < hold


class TargetVerdict:
    """The held state of one target's status (problem counts, the link bump) and its rules but overload."""

    def __init__(self, target: str, stale_s: float, hold_s: float) -> None:
        self.target = target
        self.stale_s = stale_s
        self.hold_s = hold_s
        self.problems = RiseHold()
        self.bump: tuple[float, str] | None = None   # when the link monitor last saw a bump, and its message

    def saw_bump(self, now: float, message: str) -> None:
        self.bump = (now, message)

    def evaluate(self, now: float, pipe: TargetPipeline, health: TargetHealth, last_rx: dict[str, float | None],
                 primary: str) -> tuple[int, list[str], dict]:
        """(level, messages, values) of the target at ``now``; ``last_rx``: device tag -> monotonic time of its
        newest target sample (None: none yet)."""
        s = pipe.stats()
        values = {k: v for k, v in s.items() if k != "init_progress"}
        values.update({f"init_{k}": v for k, v in s["init_progress"].items()})
        level, msgs = OK, []
        for a in health.alarms(now):
            level = max(level, a.level)
            msgs.append(a.message)
        values.update(health.values(now))
        links = pipe.chain.links
        if s["global_link"] != "ready":
            level = WARN
            msgs.append(f"initializing: {links.describe()}")
        elif s["local_link"] != "ready":
            level = WARN
            msgs.append("local link not calibrated yet (the OTS must see the base marker, or give T_rig_ots)"
                        + (f": {links.describe()}" if links.collecting else ""))
        bump = self.bump
        if bump is not None and (pipe.monitor.bumped or now - bump[0] < self.hold_s):
            level = max(level, WARN)
            msgs.append(bump[1] if pipe.monitor.bumped else f"{bump[1]} (cleared {now - bump[0]:.1f} s ago)")
        for key in PROBLEM_KEYS:
            self.problems.update(key, pipe.counts[key], now)
        for key, (n, _when) in self.problems.seen.items():
            if self.problems.held(key, now, self.hold_s):
                level = max(level, WARN)
                msgs.append(f"{key} x{n}: {pipe.problems.get(key, '')}")
        level = max(level, self._silence(now, last_rx, msgs))
        o = pipe.last_output.get(primary)
        if o is not None:
            values.update(bias_mm=np.round(1e3 * o.bias, 3).tolist(), last_stamp_ns=o.t_ns, nis=round(o.nis, 3))
        return level, msgs, values

    def _silence(self, now: float, last_rx: dict[str, float | None], msgs: list[str]) -> int:
        """Name every source without a sample yet or for longer than ``stale``; WARN for the global one (OMC)."""
        level = OK
        for dev, name in (("omc", "OMC (global)"), ("ots", "OTS (local)"),
                          *((d, f"{d} (local)") for d in last_rx if d not in ("omc", "ots"))):
            last = last_rx[dev]
            if last is None:
                msgs.append(f"no {name} sample received yet")
            elif now - last > self.stale_s:
                msgs.append(f"no {name} sample for {now - last:.1f} s"
                            + (" (target occluded or out of the OTS volume: global only, bias compensated)"
                               if dev == "ots" else ""))
            else:
                continue
            if dev == "omc":
                level = WARN
        return level


class InputBook:
    """What the input callbacks saw, for the overload part of every target's status: the load of the callbacks
    (:class:`InputLoad`), the samples of each target body's streams that never came (:class:`SourceLoss`)."""

    def __init__(self, keys: Iterable[Key], stale_s: float, hold_s: float, lag_warn_s: float) -> None:
        self.load = InputLoad()
        self.loss: dict[Key, SourceLoss] = {k: SourceLoss() for k in keys}
        self.rx: dict[Key, float] = {}   # monotonic time of the newest pose or quality message of each stream
        self.lost = RiseHold()
        self.behind_ns = 0   # node clock - newest stamp, at the end of the last input callback
        self.callback_at: float | None = None   # monotonic time of the last input callback's end
        self.stale_s, self.hold_s, self.lag_warn_s = stale_s, hold_s, lag_warn_s

    def callback(self, batch: Sequence[tuple], delay_ns: int | None, clock_ns: int, now: float,
                 work_ns: int | None = None) -> None:
        """One input callback took ``batch`` ((stamp_ns, device, body, ...) in stamp order); ``delay_ns``: from the
        reception of its first sample to the callback; ``clock_ns``: the node clock after fusing (0: not started);
        ``work_ns``: from the callback's start until its outputs were published. An empty batch (``inputs: frames``:
        frames without a visible body the node uses) knows no lag."""
        lag = clock_ns - batch[-1][0] if clock_ns and batch else None
        self.load.callback(max(0, len(batch) - 1), delay_ns, lag, work_ns)
        self.behind_ns = lag or 0
        self.callback_at = now
        for t_ns, dev, body, *_ in batch:
            loss = self.loss.get((dev, body))
            if loss is not None:
                loss.pose(t_ns)
                self.rx[(dev, body)] = now

    def catching_up(self, now: float) -> bool:
        """True while the node works through a backlog: its last input callback ended more than ``stale_s`` behind
        the newest stamp it fused *and* less than ``stale_s`` ago. Then the poses a silent-looking stream still owes
        may sit in the node's own queue, so nothing is settled as lost. The lag is measured only when a callback
        runs: once none has run for ``stale_s`` the queue is empty (the executor would have run one), and a lag
        frozen at the last callback of a stream that ended while the node was behind must not hold the settling
        off for good -- it did (a 1 kHz run ended 14.9 s behind and its OTS losses were never counted)."""
        return (self.behind_ns * 1e-9 > self.stale_s and self.callback_at is not None
                and now - self.callback_at < self.stale_s)

    def end_of_streams(self) -> None:
        """Nothing more comes (shutdown): settle every count."""
        for loss in self.loss.values():
            loss.end_of_stream()

    def overload(self, now: float, routes: Iterable[Route], level: int, msgs: list[str], values: dict) -> int:
        """Queue depth, processing lag, callback delay and lost samples of the target whose streams are ``routes``
        (WARN: lag above lag_warn for the whole period, samples lost within hold)."""
        values.update(self.load.values())
        lag = self.load.lag_min_ns
        if lag is not None and lag * 1e-9 > self.lag_warn_s:
            level = max(level, WARN)
            msgs.append(f"overload: processing lag {lag * 1e-6:.0f} ms or more since the last report > lag_warn "
                        f"{self.lag_warn_s * 1e3:g} ms (node clock - stamp of the newest fused sample; up to "
                        f"{self.load.depth_max} samples waiting)")
        for r in routes:
            dev, body = key = r.tag, r.target
            name = f"OMC body '{body}'" if dev == "omc" else f"OTS tool '{body}'" if dev == "ots" else \
                f"{dev} tool '{body}'"
            loss = self.loss.get(key)
            if loss is None:
                continue
            if loss.pending and now - self.rx.get(key, now) > max(self.stale_s, LOSS_SILENCE_S) \
                    and not self.catching_up(now):
                loss.end_of_stream()
            values[f"{dev}_frames_lost"] = loss.frames_lost
            values[f"{dev}_samples_lost"] = loss.samples_lost
            self.lost.update(key, loss.lost, now)
            if self.lost.held(key, now, self.hold_s):
                level = max(level, WARN)
                msgs.append(f"lost samples of the {name}: {loss.samples_lost} poses never arrived (frames of the "
                            f"driver's TrackingQuality; {loss.frames_lost} frame-number gaps: quality messages "
                            "lost on the way, or device frames the driver never read -- its skipped_frames)")
        return level
