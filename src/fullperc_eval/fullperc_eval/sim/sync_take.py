"""A short twin take for time alignment: the arm waves the tool irregularly in view of both trackers.

Why: the time-alignment tool (:mod:`fullperc_fusion.calibration.time_offset`) needs a few seconds of motion that both
the OMC and the Vega see, and a known stamp offset to be checked against. The evaluation tasks are ~30 s of one
smooth single-joint arc (one speed bump, partly outside the Vega); this take is what a user records by hand instead:
the tool waved in the Vega's volume for a few seconds, at varying speed (a periodic wave would correlate at
multiples of its period too).

:class:`WiggleArc` is a :class:`~.trajectories.JointArc` whose sample adds, after ``hold_start``, a smooth sum of
sines on three joints (incommensurate frequencies, random phases from ``wiggle_seed``) faded in and out with the
minimum-jerk profile, around the pose where a task's plan starts in the Vega's volume (task ``B-G-P`` starts there).
:func:`sync_take` simulates it like any task; ``ots_stamp_offset_s`` sets the twin's ``ots.stamp_offset_s`` (the
Vega's stamps late by that much, :func:`fullperc_eval.sim.run.simulate`), which ``dataset.content_from_sim``
writes into the bag's OTS stamps.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .run import SimRun, simulate
from .scene import DEFAULT_PROFILE, build_scene, load_scene_config
from .tasks import plan_task
from .trajectories import JointArc, min_jerk

WIGGLE_JOINTS = (0, 3, 5)           # shoulder yaw, elbow, wrist: translation and rotation of the tool
WIGGLE_FREQS_HZ = (0.37, 0.61, 0.89, 1.27)


@dataclass(frozen=True)
class WiggleArc(JointArc):
    """Hold at ``q0`` (with ``joint`` at ``start``), wiggle for ``move`` seconds, hold; ``end`` is not used."""

    amplitude: float = 0.06         # [rad] per sine component and joint: tool speeds up to ~0.5 m/s, and the tool
                                    # stays in the Vega's volume most of the time
    wiggle_seed: int = 0
    fade_s: float = 0.8             # [s] minimum-jerk fade in and out of the wiggle

    def _parts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng = np.random.default_rng([int(self.wiggle_seed), 7])
        w = 2 * np.pi * np.asarray(WIGGLE_FREQS_HZ) * rng.uniform(0.9, 1.1, (len(WIGGLE_JOINTS), 1))
        phase = rng.uniform(0, 2 * np.pi, w.shape)
        amp = self.amplitude * rng.uniform(0.5, 1.0, w.shape)
        return w, phase, amp

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float).ravel()
        Q = np.tile(np.asarray(self.q0, dtype=float), (t.size, 1))
        Q[:, self.joint] = self.start
        dQ = np.zeros_like(Q)
        u = t - self.hold_start
        e_in, de_in = min_jerk(u / self.fade_s)
        e_out, de_out = min_jerk((self.move - u) / self.fade_s)
        env = e_in * e_out
        denv = de_in / self.fade_s * e_out - e_in * de_out / self.fade_s
        w, phase, amp = self._parts()
        for i, j in enumerate(WIGGLE_JOINTS):
            arg = w[i][None, :] * u[:, None] + phase[i][None, :]
            s = (amp[i] * (np.sin(arg) - np.sin(phase[i]))).sum(axis=1)      # 0 at u = 0: no step at the fade
            ds = (amp[i] * w[i] * np.cos(arg)).sum(axis=1)
            Q[:, j] += env * s
            dQ[:, j] += denv * s + env * ds
        return Q, dQ


def sync_take(seed: int = 0, ots_stamp_offset_s: float = 0.0, duration_s: float = 8.0,
              profile: str | None = DEFAULT_PROFILE, task: str = "B-G-P", staff: bool = True,
              amplitude: float = 0.06) -> SimRun:
    """Simulate a time-alignment take: 0.5 s still, ``duration_s`` of waving, 0.5 s still (no second target).

    ``ots_stamp_offset_s``: the Vega's stamps are late by this much relative to the truth (and so to the OMC's).
    The arm's placement and starting pose are those of ``task``'s plan (its first part must be in the Vega's view).
    """
    cfg = copy.deepcopy(load_scene_config(profile=profile))
    cfg["ots"]["stamp_offset_s"] = float(ots_stamp_offset_s)
    scene = build_scene(seed, config=cfg)
    plan = plan_task(task, scene)
    scene = scene.with_diana_base(plan.T_omc_diana_base)
    a = plan.arc
    arc = WiggleArc(q0=a.q0, joint=a.joint, start=a.start, end=a.start, move=float(duration_s), hold_start=0.5,
                    hold_end=0.5, amplitude=float(amplitude), wiggle_seed=int(seed))
    run = simulate(scene, arc, task=f"sync-{task}", staff=staff)
    run.info["profile"] = cfg.get("_profile", "base")
    return run


__all__ = ["WiggleArc", "sync_take"]
