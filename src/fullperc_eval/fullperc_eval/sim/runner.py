"""Offline entry point: plan a task and simulate it (:func:`run_task`).

It sits above both halves it joins -- :mod:`.tasks` (planning, which checks a candidate arc with the
simulation's noise-free visibility) and :mod:`.run` (the simulation), plus :mod:`.targets` (the extra targets) --
so neither of them imports the other's caller.
"""

from __future__ import annotations

from .run import SimRun, simulate
from .scene import VegaBump, build_scene
from .targets import add_targets
from .tasks import plan_task


def run_task(task: str = "P-B-G-P", seed: int = 0, config=None, layout=None, noise: bool = True,
             staff: bool = True, miscalibration: bool = True, profile: str | None = None,
             vega_bump: VegaBump | None = None, extra_targets: bool = True) -> SimRun:
    """Plan ``task`` (one of :data:`~fullperc_eval.sim.tasks.TASKS`) and simulate it with ``seed``.

    ``config``: scene.yaml path or dict (default: the installed one); ``layout``: a loaded layout (default:
    the shared or_layout.yaml). ``noise``/``staff``/``miscalibration`` switch the error sources off for tests.
    ``profile``: twin profile (``paper``, ``spec``; None or ``base``: scene.yaml alone). ``vega_bump``: the Vega
    stand is bumped during the run (:class:`~fullperc_eval.sim.scene.VegaBump`; applied after planning, so the task's
    arc is the same as without it). ``extra_targets``: also measure the scene's targets without a robot, the hand-held
    instrument and the breathing patient reference (:mod:`~fullperc_eval.sim.targets`; each with its own random
    streams: every other body's data are the same without them; one is left out with ``enabled: false`` in its
    section of the scene).
    """
    scene = build_scene(seed, config=config, layout=layout, miscalibration=miscalibration, profile=profile)
    plan = plan_task(task, scene)
    scene = scene.with_diana_base(plan.T_omc_diana_base).with_vega_bump(vega_bump)
    run = simulate(scene, plan.arc, task=task, noise=noise, staff=staff)
    if extra_targets:
        add_targets(run, scene, noise=noise, staff=staff)
    run.info["plan_attempts"] = plan.attempts
    run.info["region_path_m"] = plan.region_path_m
    run.info["ots_fraction_b"] = plan.ots_fraction_b
    run.info["omc_fraction"] = plan.omc_fraction
    run.info["profile"] = scene.config.get("_profile", "base")
    return run
