"""Simulator speed: one task's offline measurements (OMC 120 Hz + Vega 60 Hz + Diana 100 Hz, ~28 s of motion).

Baseline (same run): the batch forward kinematics of the same OMC frames alone, i.e. the cheapest possible
pass over the trajectory. Planning is excluded (it is cached; see fullperc_eval.sim.tasks.plan_task).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchlib import emit, median_time  # noqa: E402

from fullperc_eval.sim.run import _time_grid, simulate  # noqa: E402
from fullperc_eval.sim.scene import build_scene  # noqa: E402
from fullperc_eval.sim.tasks import plan_task  # noqa: E402
from fullperc_eval.sim.trajectories import arm_geometry  # noqa: E402


def main() -> None:
    task = "P-B-G-P"
    scene = build_scene(0)
    plan = plan_task(task, scene)
    scene = scene.with_diana_base(plan.T_omc_diana_base)
    t = _time_grid(plan.arc.duration, 120.0)
    base = median_time(lambda: arm_geometry(scene.dk, plan.arc.sample(t / 1e9)[0]), repeats=3)
    sim = median_time(lambda: simulate(scene, plan.arc, task=task), repeats=3)
    emit("sim_offline_task_s", sim, "s", baseline=base, task=task, motion_s=plan.arc.duration, omc_frames=len(t))
    emit("sim_realtime_factor", plan.arc.duration / sim, "x", task=task)


if __name__ == "__main__":
    main()
