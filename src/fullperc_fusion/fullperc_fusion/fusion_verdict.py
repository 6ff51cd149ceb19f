"""fusion_node's /diagnostics verdict of one target: level, message and values from what the node saw.

ROS-free and clock-free, as :mod:`fusion_health`: every call takes ``now`` [s] on one monotonic clock of the
caller's, so :class:`~fullperc_fusion.fusion_core.FusionCore` (and its unit tests, with made-up times) decide what
``fusion_node`` only converts into a DiagnosticStatus. Levels are the diagnostic_msgs values (OK 0, WARN 1, ERROR 2).
What the verdict weighs besides a target's alarms lives here too: the samples a source's stream lost
(:class:`SourceLoss`) and the node's input load and latency (:class:`InputLoad`).

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
  ``hold`` seconds after a source's lost samples (:class:`~SourceLoss`) rose.
  What still waits for its pose counts as lost once the source was silent for max(``stale``, LOSS_SILENCE_S)
  while the node kept up (behind, its quality callbacks starve and the poses still queue).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fullperc_common.latency import LatencyHistogram
from fullperc_fusion.fusion_health import OK, WARN, TargetHealth
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


# ---- the node's inputs: samples that never came, lag and latency ---------------------------------------------------
class SourceLoss:
    """Samples of one source the node never got, from the driver's TrackingQuality (issue 16 item 5).

    Why: under overload DDS drops samples (a reader's keep-last history overflows) and nothing said so -- at
    1 kHz + 1 kHz the node took in a quarter of the OMC samples while /diagnostics said OK. The drivers publish a
    TrackingQuality per device frame, visible or not, with the device's frame counter and the pose's stamp:

    * ``frames_lost``: gaps in ``frame_number`` -- quality messages that never arrived (a counter that goes back,
      e.g. a driver restart, starts a new count without a gap);
    * ``samples_lost``: pose samples that never arrived: frames whose quality says *visible* and whose pose (same
      stamp) did not come within ``match_ns`` (stamp time) of it, plus the frames of the gaps whose pose did not
      come either -- the gap frames minus the poses that came without a quality message. Frames of a gap are taken
      as visible (their quality is unknown), so this is an upper bound when the body was occluded during a gap.

    A visible frame waits for its pose until a *pose* ``match_ns`` newer arrives, and a pose for its quality until a
    *quality* message ``match_ns`` newer arrives: each topic comes in order, but the two are taken in separate
    callbacks, and a node that lags in its pose callbacks has the quality messages seconds ahead (a demo run on a
    busy machine counted 678 OMC samples lost, every one of which it had fused). At the end of a stream nothing
    newer comes, so the caller says when the source has gone silent (:meth:`end_of_stream`) and what is still
    waiting is settled then.

    Pure: the caller passes stamps; a source without quality messages reports nothing.
    """

    def __init__(self, match_ns: int = 1_000_000_000) -> None:
        self.match_ns = int(match_ns)
        self.frames_lost = 0
        self._unmatched = 0                    # visible frames whose pose did not come
        self._orphans = 0                      # poses that came without their quality message
        self._last_frame: int | None = None
        self._waiting: dict[int, None] = {}    # stamps of visible frames whose pose has not arrived (insertion order)
        self._poses: dict[int, None] = {}      # stamps of poses whose quality has not arrived
        self._newest_pose = 0
        self._newest_quality = 0

    @property
    def samples_lost(self) -> int:
        return self._unmatched + max(0, self.frames_lost - self._orphans - len(self._poses))

    @property
    def lost(self) -> int:
        return self.samples_lost

    def quality(self, frame_number: int, stamp_ns: int, visible: bool) -> int:
        """One TrackingQuality; returns the frames this one shows lost (a gap before it)."""
        gap = 0
        if self._last_frame is not None and frame_number > self._last_frame + 1:
            gap = frame_number - self._last_frame - 1
            self.frames_lost += gap
        self._last_frame = frame_number
        if stamp_ns in self._poses:
            del self._poses[stamp_ns]
        elif visible:
            self._waiting[stamp_ns] = None
        self._newest_quality = max(self._newest_quality, stamp_ns)
        self._expire(self._poses, self._newest_quality, "_orphans")
        return gap

    def pose(self, stamp_ns: int) -> None:
        """One pose sample of the source arrived (whatever the pipeline then did with it)."""
        if stamp_ns in self._waiting:
            del self._waiting[stamp_ns]
        else:
            self._poses[stamp_ns] = None
        self._newest_pose = max(self._newest_pose, stamp_ns)
        self._expire(self._waiting, self._newest_pose, "_unmatched")

    @property
    def pending(self) -> int:
        """Visible frames still waiting for their pose plus poses still waiting for their quality."""
        return len(self._waiting) + len(self._poses)

    def end_of_stream(self) -> None:
        """The source went silent (the caller has had neither a pose nor a quality message of it for a while):
        the visible frames still waiting for their pose will not get it and count as lost now -- else a loss in
        a stream's last ``match_ns`` would never be counted -- and the poses still waiting for their quality are
        orphans (they reduce the gap frames' share, as when they expire)."""
        self._unmatched += len(self._waiting)
        self._orphans += len(self._poses)
        self._waiting.clear()
        self._poses.clear()

    def _expire(self, pending: dict[int, None], newest_ns: int, counter: str) -> None:
        """Settle the entries of ``pending`` more than match_ns older than ``newest_ns`` (the other topic's newest
        stamp) as ``counter``."""
        old = newest_ns - self.match_ns
        while pending:
            t = next(iter(pending))
            if t >= old:
                break
            del pending[t]
            setattr(self, counter, getattr(self, counter) + 1)


STAGES = ("callback_delay", "wakeup", "received_to_published")   # fullperc_common.latency: what each measures


@dataclass
class LoadWindow:
    """The input callbacks of one stretch of time: the largest queue depth and lag, the smallest lag, the number of
    callbacks (None where no callback measured it), and a histogram of each latency stage (:data:`STAGES`)."""

    depth_max: int = 0
    lag_max_ns: int | None = None
    lag_min_ns: int | None = None
    callbacks: int = 0
    stages: dict[str, LatencyHistogram] = field(default_factory=lambda: {s: LatencyHistogram() for s in STAGES})

    def add(self, depth: int, delay_ns: int | None, lag_ns: int | None, work_ns: int | None = None) -> None:
        self.callbacks += 1
        self.depth_max = max(self.depth_max, depth)
        self.lag_max_ns = _opt(max, self.lag_max_ns, lag_ns)
        self.lag_min_ns = _opt(min, self.lag_min_ns, lag_ns)
        for stage, ns in zip(STAGES, (delay_ns, work_ns, None if delay_ns is None or work_ns is None
                                      else delay_ns + work_ns), strict=True):
            if ns is not None:
                self.stages[stage].add(ns)

    def merged(self, other: LoadWindow) -> LoadWindow:
        """Both stretches as one."""
        return LoadWindow(max(self.depth_max, other.depth_max), _opt(max, self.lag_max_ns, other.lag_max_ns),
                          _opt(min, self.lag_min_ns, other.lag_min_ns), self.callbacks + other.callbacks,
                          {s: self.stages[s].merged(other.stages[s]) for s in STAGES})


def _opt(f, a: int | None, b: int | None) -> int | None:
    """f(a, b) of two optional values; the one that is there when the other is None."""
    return b if a is None else a if b is None else f(a, b)


class InputLoad:
    """What fusion_node's input callbacks saw (issue 16 item 5: overload visible).

    Why: at 1 kHz + 1 kHz the node fell half a second behind and /diagnostics said OK. ``depth``: samples waiting
    besides the one that started the callback (taken in the same callback); ``delay``: from the DDS reception of
    that sample to the callback; ``lag``: node clock - stamp of the newest sample, after it was fused (with arrival
    processing the fused estimate is that old; with ordered processing add the synchronizer's wait).

    Two stretches. The **window** is one evaluation period of the node (``_update_diagnostics``, every 0.5 s): its
    ``lag_min`` is what the overload WARN looks at -- a lag that never came down for a whole period is overload, a
    single late callback on a busy machine is not. The **report** is what /diagnostics shows: every window since
    the last report that was published (:meth:`begin_report`). The node evaluates twice per /diagnostics period,
    and each evaluation replaces the status; a report of its own window alone left every other window unpublished,
    so a burst processed in one of those (a node catching up after a stall) never showed as a queue depth or a lag.
    """

    def __init__(self) -> None:
        self.depth = 0
        self.lag_ns: int | None = None
        self.window = LoadWindow()
        self.report = LoadWindow()

    # the window's figures, for the overload verdict
    @property
    def depth_max(self) -> int:
        return self.window.depth_max

    @property
    def lag_min_ns(self) -> int | None:
        return self.window.lag_min_ns

    def callback(self, depth: int, delay_ns: int | None, lag_ns: int | None, work_ns: int | None = None) -> None:
        """``depth`` samples were waiting besides the callback's own; ``delay_ns`` from its reception to the
        callback; ``lag_ns`` node clock - stamp of the newest sample, after it was fused; ``work_ns`` from the
        callback's start until its outputs were published."""
        self.depth = depth
        if lag_ns is not None:
            self.lag_ns = lag_ns
        self.window.add(depth, delay_ns, lag_ns, work_ns)

    def begin_report(self, previous_published: bool) -> None:
        """Fold the window into the report; ``previous_published``: the report set at the last evaluation went out
        on /diagnostics, so the new one starts with this window (else it adds it: nothing is dropped unpublished).
        """
        self.report = replace(self.window) if previous_published else self.report.merged(self.window)

    def values(self) -> dict:
        """The report's figures, and the newest depth and lag."""
        def ms(v: int | None) -> float | None:
            return None if v is None else round(v * 1e-6, 3)

        r = self.report
        out = {"queue_depth": self.depth, "queue_depth_max": r.depth_max, "lag_ms": ms(self.lag_ns),
               "lag_min_ms": ms(r.lag_min_ns), "lag_max_ms": ms(r.lag_max_ns), "input_callbacks": r.callbacks}
        for stage in STAGES:   # median, p99 and maximum of each latency stage (fullperc_common.latency)
            out.update(r.stages[stage].figures_ms(stage))
        return out

    def reset_period(self) -> None:
        """End of one evaluation period: a new window."""
        self.window = LoadWindow()


# ---- the verdict ----------------------------------------------------------------------------------------------------


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
