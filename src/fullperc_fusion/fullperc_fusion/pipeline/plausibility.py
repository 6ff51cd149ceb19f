"""What a target sample must pass before a pipeline takes it: a valid sample (:func:`validate`), then a plausible one
(:class:`Plausibility`). ROS-free; :class:`~.ordered.TargetPipeline`'s ``push_*`` run both.

Validation (NaN, non-unit quaternions, bad stamps, the time guard, the covariance) says a sample *can* be a pose.
Plausibility says it can be *this target's* pose: a sample of a target's body/tool from one source (the global OMC
or a local source) that lies further from that same source's last accepted target sample than the target can have
moved is rejected::

    |p - p_prev| > jump + max_speed * (t - t_prev)   ->   rejected_jump   (dropped, counted, named)

with ``(t_prev, p_prev)`` the source's accepted sample with the newest stamp *before* t, ``max_speed``
(``plausibility.max_speed``, 2 m/s) the fastest the target moves and ``jump`` (``plausibility.jump``, 0.01 m) what a
sample may be off besides: the source's noise and its legitimate hops (the OMC's marker swaps, a few mm). Why: the
rate alarms (hop rate, bias, every sample rejected) see a stream that is wrong for a while; a single injected or
corrupt sample -- a second publisher on the topic (issue 40), a driver bug -- would be fused as if it were true
and, without the local source, moves the fused pose as far as it is off.

Rules, each pinned by ``test_plausibility.py``:

* Positions are compared in the frame the source measures in (``omc`` / ``ots``), before the frame chain: a static
  chain maps them with one rigid transform (T_base = A T_dev), which preserves distances, so the bound is the
  target's own motion; the static links being re-estimated or recalibrated never looks like a jump. With a
  ``tracked`` chain (the tracker on a moving arm) the tracker's own motion adds to the distance: ``max_speed`` then
  bounds the target's speed relative to the tracker.
* Only *accepted* samples are compared with: after a rejected one the next honest sample is compared with the last
  accepted one (a longer dt, a larger bound), so one injected sample costs one sample.
* Only earlier stamps: a sample that arrives after a later-stamped one of its source is compared with the accepted
  sample just before its own stamp, never with a later one (a sample is not judged by its future; a late honest
  sample is not judged by an injected one stamped after it). A sample with no earlier accepted sample kept -- the
  first of a source, the first after :meth:`Plausibility.restart` (a timeline restart on arrival, ``~/initialize``),
  one older than everything kept -- is accepted: nothing to compare it with. What is kept: the accepted samples of
  the last ``keep_ns`` of stamps (max(history, 2·slop + reorder_delay): the window in which the stamp rules take a
  sample) and the one before them, so a sample the stamp rules can still take is compared with the accepted one
  just before it (one older than the one before them is older than an item already final: late).
* The verdict is made once, on arrival, before the synchronizer (like validation): ordered processing and fusion on
  arrival judge the same pushes identically, and a rewind on arrival (arrival.py) never judges a sample again nor
  counts it twice -- this state is input-side, kept by a rewind (``TargetPipeline.KEPT``).
* A wrong anchor heals by itself: if the accepted sample is the bad one (the first of a source), the honest samples
  are rejected only until the bound has grown past their distance, dt > (d - jump) / max_speed.

Measured on the committed bags (``bags/paper``, ``bags/spec``, seed 0: both targets, every source, in bag order):
the largest |p - p_prev| - max_speed * dt of a target sample is -9.2 mm with max_speed = 2 m/s (-17.6 mm with 3 m/s,
-0.9 mm with 1 m/s): every honest sample, the twin's OMC hops (up to 4.6 mm) included, is within max_speed * dt
alone, and jump = 10 mm is headroom. The fastest target there is the hand-held instrument, 0.92 m/s. Why 2 m/s and
not more: at dt = 4 ms the bound is 18 mm, so a sample 20 mm off stamped 4 ms after an honest one (the issue's
injection) is rejected; 3 m/s (a 22 mm bound) let it through.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from fullperc_fusion.filters.api import BadMeasurement, check_covariance
from fullperc_fusion.pipeline.frame_chain import BadSample, pose_to_T
from fullperc_fusion.pipeline.problems import Problems

__all__ = ["Plausibility", "validate"]


def validate(what: str, t_ns, pose, cov, now_ns: int | None, max_future_ns: int,
             diag: Problems) -> tuple[int, np.ndarray, np.ndarray | None] | None:
    """``(t, T, C)`` of a valid sample of ``what`` (source and body), else None with the problem reported to
    ``diag``: ``rejected_stamp`` (not an int > 0), ``rejected_future`` (more than ``max_future_ns`` ahead of the
    caller's clock ``now_ns``; None: not checked), ``rejected_nonfinite`` / ``rejected_nonunit`` / ``rejected_pose``
    (:func:`~.frame_chain.pose_to_T`), ``rejected_cov`` (:func:`~fullperc_fusion.filters.api.check_covariance`)."""
    report = diag.report
    try:
        t = int(t_ns)
    except (TypeError, ValueError, OverflowError):
        report("rejected_stamp", f"{what}: invalid stamp {t_ns!r}", None)
        return None
    if t <= 0:
        report("rejected_stamp", f"{what}: invalid stamp {t}", None)
        return None
    if now_ns is not None and t - now_ns > max_future_ns:
        report("rejected_future", f"{what}: stamp {t} ns is {(t - now_ns) * 1e-9:.3f} s ahead of the clock "
                                  f"({now_ns} ns; max_future {max_future_ns * 1e-9:g} s); dropped", t)
        return None
    try:
        T = pose_to_T(pose)
    except BadSample as e:
        why = str(e)
        key = "rejected_nonfinite" if "non-finite" in why else "rejected_nonunit" if "non-unit" in why \
            else "rejected_pose"
        report(key, f"{what}: {why}", t)
        return None
    if cov is None:
        return t, T, None
    try:
        return t, T, check_covariance(cov)
    except BadMeasurement as e:
        report("rejected_cov", f"{what}: {e}", t)
        return None


class Plausibility:
    """The accepted target samples of each synchronizer stream (0 global, 1 + k local source k) and the check
    against them; see the module docstring. ``check`` then, once the pipeline took the sample, ``accept``."""

    __slots__ = ("_p", "_t", "jump", "keep_ns", "max_speed")

    def __init__(self, streams: int, max_speed: float, jump: float, keep_ns: int) -> None:
        self.max_speed = float(max_speed)   # [m/s]
        self.jump = float(jump)             # [m]
        self.keep_ns = int(keep_ns)
        self._t: list[list[int]] = [[] for _ in range(streams)]   # accepted stamps per stream, ascending
        self._p: list[list[tuple[float, float, float]]] = [[] for _ in range(streams)]   # their positions

    def check(self, stream: int, t: int, T: np.ndarray, what: str) -> str | None:
        """None if the sample of ``stream`` at ``t`` (4x4 ``T`` in its device frame) is plausible, else the problem
        text naming ``what`` (source and body), the jump [mm] and dt [ms]."""
        ts = self._t[stream]
        i = bisect.bisect_left(ts, t)   # ts[i - 1]: the newest accepted stamp before t
        if i == 0:
            return None
        t0, p0 = ts[i - 1], self._p[stream][i - 1]
        dt = (t - t0) * 1e-9
        d = math.dist(p0, (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])))
        bound = self.jump + self.max_speed * dt
        if d <= bound:
            return None
        return (f"{what}: jumped {d * 1e3:.1f} mm in {dt * 1e3:.1f} ms from its last accepted sample ({t0} ns), "
                f"more than plausibility.jump {self.jump * 1e3:g} mm + max_speed {self.max_speed:g} m/s x dt = "
                f"{bound * 1e3:.1f} mm; dropped")

    def accept(self, stream: int, t: int, T: np.ndarray) -> None:
        """The sample of ``stream`` at ``t`` was taken: later ones are compared with it. Samples more than
        ``keep_ns`` older than the newest are forgotten, but for the newest of them (module docstring)."""
        ts, ps = self._t[stream], self._p[stream]
        p = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        if not ts or t > ts[-1]:
            ts.append(t)
            ps.append(p)
        else:
            i = bisect.bisect_left(ts, t)
            ts.insert(i, t)
            ps.insert(i, p)
        n = bisect.bisect_left(ts, ts[-1] - self.keep_ns) - 1   # ts[n]: the newest before the window, kept
        if n > 0:
            del ts[:n], ps[:n]

    def restart(self) -> None:
        """Forget every accepted sample: the next sample of each source is accepted as its first."""
        for ts, ps in zip(self._t, self._p, strict=True):
            ts.clear()
            ps.clear()
