"""One live calibration of the static links, as the ``calibrate`` executable and ``fusion_node``'s ``~/calibrate``
run it: a :class:`~.collector.Collector` plus a bound on host time, then the result or the reason
it was refused, and a one-line summary. ROS-free; the caller passes ``now`` (a monotonic clock [s]).
``background``: the robust means at the end (~70-100 ms) run on the worker thread
(:mod:`fullperc_common.background`; ``fusion_node``, whose executor thread meanwhile fuses), and :meth:`poll` is
True at a later call; sightings that come meanwhile are not collected.

The collection ends by the sensor stamps (``duration_s`` after the first sighting, :attr:`Collector.complete`), or
at the latest ``timeout_s`` seconds of host time after ``duration_s`` has passed since :meth:`CalibrationRun.__init__`
-- when a body is never seen or its stream stops, the run ends anyway and is refused (a shorter collection than
asked for is never used).
"""

from __future__ import annotations

from collections.abc import Sequence

from fullperc_common.background import Job
from fullperc_fusion.calibration.collector import Collector
from fullperc_fusion.calibration.se3_stats import (
    Calibration,
    CalibrationBodies,
    CalibrationError,
    CalibrationSettings,
)


class CalibrationRun:
    """Collect ``links`` of ``bodies`` for ``duration_s`` s of stamps; :meth:`poll` finishes it.

    After :meth:`poll` returned True, exactly one of :attr:`result` (a :class:`Calibration`) and :attr:`error`
    (the refusal, one line naming the body) is set.
    """

    def __init__(self, links: Sequence[str], bodies: CalibrationBodies, duration_s: float,
                 settings: CalibrationSettings | None = None, *, now: float, timeout_s: float = 10.0,
                 source: str = "", background: bool = False) -> None:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self.collector = Collector(links, bodies, duration_s, settings)
        self.duration_s = float(duration_s)
        self.deadline = now + duration_s + timeout_s
        self.timeout_s = float(timeout_s)
        self.source = source
        self.result: Calibration | None = None
        self.error: str | None = None
        self._job = Job(self._finish, background)

    @property
    def done(self) -> bool:
        return self.result is not None or self.error is not None

    def add(self, device: str, body: str, stamp_ns: int, position, quat_xyzw=None) -> bool:
        """One sighting (see :meth:`Collector.add`); ignored once the run is done."""
        if self.done or self._job.running:
            return False
        return self.collector.add(device, body, stamp_ns, position, quat_xyzw)

    def poll(self, now: float) -> bool:
        """Finish the run when the collection is complete or the host-time bound passed; True when done."""
        if self.done:
            return True
        col = self.collector
        if not self._job.running:
            if not col.complete:
                if now < self.deadline:
                    return False
                span = 0.0 if col.start_ns is None or col.last_ns is None else (col.last_ns - col.start_ns) / 1e9
                counts = ", ".join(f"{Collector.label(*k.split(':', 1))}: {n}" for k, n in col.counts().items())
                self.error = (f"too few sightings: they span {span:.1f} s of the {self.duration_s:g} s needed "
                              f"after {self.duration_s + self.timeout_s:g} s of host time ({counts}); is every "
                              "body seen?")
                return True
            self._job.start()
            if self._job.background:
                return False   # its result at a later poll, never at the one that started it
        finished, out = self._job.poll()
        if finished:
            self.result, self.error = out
        return finished

    def _finish(self) -> tuple[Calibration | None, str | None]:
        try:
            return self.collector.finish(source=self.source), None
        except CalibrationError as e:
            return None, " ".join(str(e).split()).removeprefix("calibration refused: ")


def summary(cal: Calibration) -> str:
    """One line: per link the position [m], inliers of samples and the residuals of the inliers."""
    parts = []
    for name, e in cal.links.items():
        p = ", ".join(f"{x:.4f}" for x in e.position)
        parts.append(f"{name} p=[{p}] m, {e.n_inliers}/{e.n_samples} inliers, rms {e.rms_trans_mm:.3f} mm / "
                     f"{e.rms_rot_mrad:.3f} mrad")
    return f"calibrated over {cal.duration_s:.2f} s: " + "; ".join(parts)
