"""The twin's extra targets (targets without a robot), added to a simulated run in a fixed order.

* ``instrument`` (section ``second_target``, :mod:`.walker`): a nurse walks it through the room; occluded also by
  its carrier (the nurse); streams 4, 5, 6;
* ``reference`` (section ``reference_target``, :mod:`.breathing`): on the patient, static apart from the breathing;
  occluded also by the instrument's carrier; streams 7, 8, 9.

Each has its own ``SeedSequence`` children of the run seed, and the only occluder one adds (the nurse) hides the extra
targets alone, so switching one off (``enabled: false`` in its section) changes no sample of the tool, the base
marker, the rig or the joints, and switching off the reference none of the instrument either (without the
instrument, its nurse no longer hides the reference). A further target takes children 10-12 and a kind of its own
(a pose function for :func:`.target_model.measure_target`), after these two.
"""

from __future__ import annotations

from .breathing import add_reference, load_breathing
from .run import SimRun
from .scene import Scene, SceneError
from .walker import add_hand_held, hand_held, load_hand_held


def check_targets(cfg: dict) -> None:
    """Two extra targets may not share a name or an OMC rigid-body id (the second would replace the first)."""
    defs = [d for d in (load_hand_held(cfg), load_breathing(cfg)) if d is not None]
    for key in ("name", "id"):
        seen = [getattr(d.body, key) for d in defs]
        if len(set(seen)) != len(seen):
            raise SceneError(f"scene file {cfg.get('_source', '<memory>')}: two extra targets with the {key} "
                             f"{seen}")


def add_targets(run: SimRun, scene: Scene, noise: bool = True, staff: bool = True) -> SimRun:
    """Measure every extra target of ``scene`` over ``run``'s frames and add it to ``run`` (in place; returned)."""
    check_targets(scene.config)
    add_hand_held(run, scene, noise=noise, staff=staff)
    nurse = hand_held(scene)
    add_reference(run, scene, [] if nurse is None else [nurse.carrier_capsule], noise=noise, staff=staff)
    return run
