"""How long fusion_node's executor thread is held by its occasional heavy computations, at once vs on the worker.

Why (issue 38 item 3, tails): the stamp-offset estimate (every 10 s of stamps, per target) and a ``~/calibrate``
collection's robust means (once) ran on the executor thread, so every sample arriving meanwhile waited for them.
``fullperc_common.background`` runs them on a worker thread. This measures what an input path sees: a loop that
should run every 1 ms (the node's input callbacks, ~0.1 ms of numpy each) starts the computation at its 20th tick
and records how late each later tick runs; the figure is the largest lateness [ms], median over repeats, on the
worker (``value``) against at once (``baseline``) in the same run.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
from benchlib import emit

from fullperc_common.transforms import T_to_pq, make_T
from fullperc_fusion.calibration.run import CalibrationRun
from fullperc_fusion.calibration.se3_stats import CalibrationBodies, se3_retract
from fullperc_fusion.fusion_health import GLOBAL, LOCAL, StampOffsetWatch

S = 1_000_000_000
TICK_S = 1e-3


def offset_watch(background: bool) -> StampOffsetWatch:
    """10.5 s of a waving target at 240 Hz (OMC) and 120 Hz (Vega, 10 ms late): one estimate due."""
    rng = np.random.default_rng(0)
    w = StampOffsetWatch(10.0, 10.0, background=background)
    for k in range(int(10.5 * 240)):
        t = k / 240
        p = 0.08 * np.array([np.sin(2.1 * t) + 0.5 * np.sin(5.3 * t + 1), np.sin(1.3 * t + 2) * np.cos(3.7 * t),
                             0.4 * np.sin(4.1 * t + 0.3)]) + rng.normal(0, 2e-4, 3)
        w.add(GLOBAL, round(t * S), p)
        if k % 2 == 0:
            w.add(LOCAL, round((t + 0.01) * S), p + 1.0)
    return w


def calibration_run(background: bool) -> CalibrationRun:
    """10.5 s of two still bodies at 240 Hz: the collection of a ``~/calibrate`` complete, its means due."""
    rng = np.random.default_rng(1)
    run = CalibrationRun(("T_omc_base", "T_base_ots"), CalibrationBodies(), 10.0, now=0.0, background=background)
    a, b = make_T([1.0, 0.5, 0.8]), make_T([0.1, 0.2, -1.9])
    for k in range(int(10.5 * 240)):
        t = round(k / 240 * S)
        run.add("omc", "base", t, *T_to_pq(se3_retract(a, rng.normal(size=6) * 2e-4)))
        run.add("ots", "base", t, *T_to_pq(se3_retract(b, rng.normal(size=6) * 1e-4)))
    return run


def worst_lateness(start, finished, ticks: int = 400) -> float:
    """The input loop: ``start()`` at tick 20, then until ``finished()`` and at least ``ticks``; the largest
    lateness of a tick after the start [s]."""
    x = np.random.default_rng(2).normal(size=(200, 3))
    t0 = time.perf_counter()
    worst, k = 0.0, 0
    while k < ticks or not finished():
        due = t0 + k * TICK_S
        now = time.perf_counter()
        if now < due:
            time.sleep(due - now)
        late = time.perf_counter() - due
        if k > 20:
            worst = max(worst, late)
            t0 += late            # the next ticks are due a tick after this one ran, not all at once
        np.linalg.norm(x @ x.T)   # ~0.1 ms of a callback's work
        if k == 20:
            start()
        k += 1
    return worst


def measure(make, start, finished, repeats: int = 7) -> tuple[float, float]:
    out = {}
    for bg in (True, False):
        lates = []
        for _ in range(repeats):
            obj = make(bg)
            lates.append(worst_lateness(lambda o=obj: start(o), lambda o=obj: finished(o)))
        out[bg] = statistics.median(lates)
    return out[True], out[False]


def main() -> None:
    bg, fg = measure(offset_watch, lambda w: w.estimate(), lambda w: not w._job.running or w._job.ready)
    emit("stamp_offset_stall", bg * 1e3, "ms", baseline=fg * 1e3,
         what="largest lateness of a 1 kHz input loop while the stamp-offset estimate runs: on the worker vs at once")
    bg, fg = measure(calibration_run, lambda r: r.poll(20.0), lambda r: r.poll(20.0))
    emit("calibrate_stall", bg * 1e3, "ms", baseline=fg * 1e3,
         what="the same while a ~/calibrate collection's robust means run: on the worker vs at once")


if __name__ == "__main__":
    main()
