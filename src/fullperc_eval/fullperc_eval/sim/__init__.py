"""Physics-based digital twin of the operating room (issue 6): ROS-free core.

* :mod:`.scene` — cameras (shared layout), marker bodies, obstacles, staff, arm placement, true transforms;
* :mod:`.omc_model` — OMC: per-marker visibility, noisy projection, triangulation with miscalibrated
  extrinsics, Kabsch rigid-body fit;
* :mod:`.ots_model` — NDI Vega: stereo pair with frustum, line of sight, ~0.1 mm noise, MISSING outside;
* :mod:`.occluders` — capsules (staff, arm links) and boxes, seeded staff walks;
* :mod:`.trajectories` — Diana 7 single-joint arcs (minimum jerk) on the shared kinematic model;
* :mod:`.tasks` — the six region orders of the paper's Table 1 and the arc generator (shipped plans in
  ``config/task_plans.yaml``; regenerate with ``python -m fullperc_eval.sim --write-plans``);
* :mod:`.run` — offline: :func:`run_task` returns a :class:`SimRun` of arrays (see its docstring);
* :mod:`.live` — plays a run out on the UDP streams and the Vega emulator (``sim`` executable).
"""

from .run import SimRun, omc_errors, run_task, simulate
from .scene import Scene, build_scene
from .tasks import TASKS, TaskPlanningError, plan_task

__all__ = ["SimRun", "Scene", "TASKS", "TaskPlanningError", "build_scene", "omc_errors", "plan_task", "run_task",
           "simulate"]
