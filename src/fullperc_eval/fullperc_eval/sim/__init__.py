"""Physics-based digital twin of the operating room (issue 6): ROS-free core, its executable and the dataset.

Layer: below :mod:`fullperc_eval.evaluation`, above :mod:`fullperc_eval.bag` and :mod:`fullperc_eval.emulators`
(it writes bags and serves the Vega emulator). Modules, each importing only the ones before it:

* :mod:`.occluders` — capsules (staff, arm links) and placed boxes (the margin model's Box), seeded staff walks;
* :mod:`.trajectories` — Diana 7 single-joint arcs (minimum jerk) on the shared kinematic model;
* :mod:`.omc_lens` — OMC: the lens residual of an incomplete calibration, common to all cameras;
* :mod:`.omc_model` — OMC: per-marker visibility, noisy projection, triangulation with miscalibrated
  extrinsics (and the lens residual), Kabsch rigid-body fit;
* :mod:`.ots_model` — NDI Vega: stereo pair with frustum, line of sight, ~0.1 mm noise, MISSING outside;
* :mod:`.scene` — cameras (shared layout), marker bodies, obstacles, staff, arm placement, true transforms;
* :mod:`.run` — :func:`simulate`: a planned arc measured in a scene, a :class:`SimRun` of arrays (see its
  docstring);
* :mod:`.tasks` — the six region orders of the paper's Table 1 and the arc generator (shipped plans in
  ``config/task_plans.yaml``; regenerate with ``python -m fullperc_eval.sim --write-plans``);
* :mod:`.target_model` — an extra target (one without a robot) measured by the OMC and Vega models;
* :mod:`.walker` — the second target: a hand-held instrument a staff member carries through the room (own
  random streams, truth in ``run.extra_truth``);
* :mod:`.breathing` — the third target: a patient reference frame that moves only as the patient breathes;
* :mod:`.targets` — the extra targets added to a run in a fixed order;
* :mod:`.runner` — :func:`run_task`: plan a task and simulate it (and the extra targets);
* :mod:`.sync_take` — a short take for time alignment: the tool waved in view of both trackers;
* :mod:`.live` — plays a run out on the UDP streams and the Vega emulator;
* :mod:`.dataset` — ``make dataset``: the six tasks as rosbag2 bags with their calibration;
* :mod:`.cli` — the ``sim`` executable.
"""

from .run import SimRun, omc_errors, simulate
from .runner import run_task
from .scene import Scene, build_scene
from .tasks import TASKS, TaskPlanningError, plan_task

__all__ = ["SimRun", "Scene", "TASKS", "TaskPlanningError", "build_scene", "omc_errors", "plan_task", "run_task",
           "simulate"]
