"""The six tasks of the paper's Table 1 on the default scene: the true target path crosses the regions in order.

The check recomputes the path independently of the generator: joint angles from the arc, flange poses from
the shared :class:`DianaKinematics` (``fk_many``), labels from the margin model. The plans come from the shipped
file ``config/task_plans.yaml`` (re-checked before use); one test plans the cheapest task cold and must reproduce
the shipped plan (same discrete choices, floats to 1e-7), so the generator itself stays tested and the file cannot
drift from it.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from fullperc_eval.sim import tasks as T
from fullperc_eval.sim.run import simulate_ideal_visibility
from fullperc_eval.sim.scene import PROFILES, build_scene, load_scene_config
from fullperc_eval.sim.tasks import (
    TASKS,
    StalePlanWarning,
    TaskPlanningError,
    check_arc_order,
    compress,
    load_shipped_plans,
    parse_task,
    plan_from_dict,
    plan_task,
    plan_to_dict,
)
from fullperc_fusion.margin.view_margin import BVV, label_points

CHEAPEST = "P-B-G"  # the task whose cold search is shortest (a few seconds)


def assert_same_plan(got, want, path: str = "plan") -> None:
    """Equal structure and discrete choices; floats to 1e-7.

    The search's IK stops at a convergence tolerance, so the last bits of a joint angle depend on the CPU's
    floating-point paths (a fresh clone on another machine differed from the shipped plan by 3e-10 rad).
    A different arc, cart pose or attempt count differs by far more than 1e-7.
    """
    if isinstance(want, dict):
        assert isinstance(got, dict) and got.keys() == want.keys(), path
        for k in want:
            assert_same_plan(got[k], want[k], f"{path}.{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), path
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            assert_same_plan(g, w, f"{path}[{i}]")
    elif isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-7, abs=1e-7), path
    else:
        assert got == want, path


def test_assert_same_plan_tells_a_different_plan_from_rounding():
    want = {"task": "P-B-G", "attempts": 31, "arc": {"q0": [0.5, -1.0], "joint": 0}}
    assert_same_plan({"task": "P-B-G", "attempts": 31, "arc": {"q0": [0.5 + 3e-10, -1.0], "joint": 0}}, want)
    for bad in ({"task": "P-B-G", "attempts": 30, "arc": {"q0": [0.5, -1.0], "joint": 0}},
                {"task": "P-B-G", "attempts": 31, "arc": {"q0": [0.5 + 1e-5, -1.0], "joint": 0}},
                {"task": "P-B-G", "attempts": 31, "arc": {"q0": [0.5], "joint": 0}},
                {"task": "P-B-G", "attempts": 31, "arc": {"q0": [0.5, -1.0], "joint": 1}}):
        with pytest.raises(AssertionError):
            assert_same_plan(bad, want)


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
    # one start configuration: the first attempt aims at no boundary, so the search's boundary points (~3 s per
    # layout) are not computed; the error path -- every attempt rejected, the task named -- is the same for 2000
    cfg["tasks"]["max_attempts"] = 1
    sc = build_scene(0, config=cfg, layout=scene.layout)
    with pytest.raises(TaskPlanningError, match="B-P-B-P-B-P-B"):
        plan_task("B-P-B-P-B-P-B", sc, cache=False)


def test_shipped_plans_cover_every_task_and_realise_it(scene):
    """A stale committed file fails here, loudly, instead of silently costing minutes of re-planning."""
    shipped = load_shipped_plans()
    assert list(shipped) == list(TASKS)
    for task in TASKS:
        plan = plan_from_dict(shipped[task])
        assert plan.task == task
        sc = scene.with_diana_base(plan.T_omc_diana_base)
        assert check_arc_order(sc, plan.arc, parse_task(task), rate_hz=120.0) == "", task


@pytest.mark.parametrize("profile", PROFILES)
def test_profile_plans_realise_every_task_near_the_operating_site(profile):
    """The twin profiles' shipped plans (task_plans_site.yaml): the order, no collision, the B part within the
    profile's Vega range and the tool clear of the moved reference marker (check_arc_order checks all four)."""
    sc0 = build_scene(0, profile=profile)
    shipped = load_shipped_plans(T.default_plans_path(T.plans_file_of(sc0)))
    assert list(shipped) == list(TASKS)
    assert sc0.config["tasks"]["max_b_range_m"] and sc0.config["tasks"]["base_marker_clearance_m"]
    for task in TASKS:
        plan = plan_from_dict(shipped[task])
        sc = sc0.with_diana_base(plan.T_omc_diana_base)
        assert check_arc_order(sc, plan.arc, parse_task(task), rate_hz=120.0) == "", task


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_vega_sees_most_of_the_b_part(scene, task):
    """Recomputed physics (noise-free, no staff): the Vega measures the tool in >= 80 % of the BVV frames."""
    plan = plan_task(task, scene)
    sc = scene.with_diana_base(plan.T_omc_diana_base)
    f_ots, f_omc = simulate_ideal_visibility(sc, plan.arc, rate_hz=30.0)
    assert BVV in parse_task(task)
    assert f_ots >= 0.8 and f_omc >= 0.8, (f_ots, f_omc)


def test_cold_planning_reproduces_the_shipped_plan_and_replaces_a_stale_one(scene, monkeypatch, tmp_path):
    monkeypatch.setenv("FULLPERC_CACHE", str(tmp_path))  # no disk cache from earlier runs
    monkeypatch.setattr(T, "_MEM_CACHE", {})
    good = load_shipped_plans()[CHEAPEST]
    stale = plan_to_dict(plan_from_dict(good))
    a = stale["arc"]
    a["end"] = a["start"] + 0.1 * (a["end"] - a["start"])  # a tenth of the arc cannot cross all three regions
    monkeypatch.setattr(T, "_SHIPPED", {T.PLANS_FILE: {CHEAPEST: stale}})
    with pytest.warns(StalePlanWarning, match=f"{CHEAPEST}.*stale"):
        plan = plan_task(CHEAPEST, scene)
    # the deterministic search found the committed plan again (arc, cart pose, attempts, fractions)
    assert_same_plan(plan_to_dict(plan), good)
    assert list((tmp_path / "task_plans").glob("*.json"))  # and it went to the disk cache


def test_plans_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("- just a list\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        load_shipped_plans(bad)
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump({"plan_version": T.PLAN_VERSION - 1, "plans": {"G-B-P": {}}}))
    with pytest.warns(StalePlanWarning, match="plan_version"):
        assert load_shipped_plans(old) == {}
    entry = load_shipped_plans()["G-B-P"]
    for mutate in (lambda d: d.pop("arc"), lambda d: d["arc"]["q0"].pop(),
                   lambda d: d.update(T_omc_diana_base=[[1.0, 0.0]])):
        d = yaml.safe_load(yaml.safe_dump(entry))
        mutate(d)
        with pytest.raises((KeyError, TypeError, ValueError)):
            plan_from_dict(d)


def test_write_plans_cli_round_trip_and_merge(tmp_path, monkeypatch):
    shipped = load_shipped_plans()
    calls = []

    def fake_search(task, scene):
        calls.append(task)
        return plan_from_dict(shipped[task])

    monkeypatch.setattr(T, "search_task", fake_search)
    out = tmp_path / "plans.yaml"
    assert T.main(["--write-plans", "--out", str(out), "--tasks", "B-G-P", "P-B-G"]) == 0
    got = load_shipped_plans(out)
    assert list(got) == ["P-B-G", "B-G-P"] and calls == ["B-G-P", "P-B-G"]  # written in TASKS order
    assert got["B-G-P"] == shipped["B-G-P"]  # exact round trip of every number
    assert T.main(["--write-plans", "--out", str(out), "--tasks", "G-B-P"]) == 0  # keeps the other entries
    assert list(load_shipped_plans(out)) == ["G-B-P", "P-B-G", "B-G-P"]
    assert T.main([]) == 2  # nothing to do without --write-plans
