"""The six tasks of the paper's Table 1 on the default scene: the true target path crosses the regions in order.

The check recomputes the path independently of the generator: joint angles from the arc, flange poses from
the shared :class:`DianaKinematics` (``fk_many``), labels from the margin model. Planning is cached on disk
(``$FULLPERC_CACHE``), so only a cold run is slow.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_eval.sim.scene import build_scene, load_scene_config
from fullperc_eval.sim.tasks import TASKS, TaskPlanningError, compress, parse_task, plan_task
from fullperc_fusion.margin import label_points


@pytest.fixture(scope="module")
def scene():
    return build_scene(0)


def test_parse_and_compress():
    assert parse_task("P-B-G") == (3, 1, 2)
    assert compress(np.array([3, 3, 1, 1, 1, 2])) == (3, 1, 2)
    for bad in ("P-P-G", "X-B", "B"):
        with pytest.raises(ValueError):
            parse_task(bad)


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_task_path_crosses_regions_in_order(scene, task):
    plan = plan_task(task, scene)
    arc = plan.arc
    sc = scene.with_diana_base(plan.T_omc_diana_base)
    t = np.arange(0.0, arc.duration, 1.0 / 120.0)  # every OMC frame
    Q, _ = arc.sample(t)
    assert np.all(Q >= sc.dk.lower) and np.all(Q <= sc.dk.upper)
    assert np.count_nonzero(np.ptp(Q, axis=0) > 0) == 1  # a single-joint arc
    T = sc.T_omc_diana_base @ sc.dk.fk_many(Q) @ sc.T_flange_tool
    labels, _ = label_points(sc.layout, T[:, :3, 3])
    assert compress(labels) == parse_task(task)
    # every region is really crossed, not grazed
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    for region in set(parse_task(task)):
        assert step[labels[1:] == region].sum() > 0.03


def test_impossible_order_fails_loudly(scene):
    cfg = load_scene_config()
    cfg["tasks"]["max_attempts"] = 6
    sc = build_scene(0, config=cfg)
    with pytest.raises(TaskPlanningError, match="B-P-B-P-B-P-B"):
        plan_task("B-P-B-P-B-P-B", sc, cache=False)
