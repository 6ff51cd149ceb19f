"""The twin's second target (sim/walker.py): a hand-held instrument walked through the room, and its truth topic.

Pinned: the arm-held tool's data do not change when the instrument is added (own random streams, the carrier does
not occlude the others); the instrument crosses the regions its path was laid through; its measurements agree with
its truth within each device's noise; the carrier occludes it; the truth survives a bag round trip and the
evaluator picks the truth source by target.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from fullperc_eval.evaluation.ground_truth import TruthTrack, load_truth_track, target_truth
from fullperc_eval.sim import run_task
from fullperc_eval.sim.dataset import TRUTH_PREFIX, write_truth_bag
from fullperc_eval.sim.scene import build_scene
from fullperc_eval.sim.tasks import plan_task
from fullperc_eval.sim.walker import HandHeldPath, add_hand_held, load_hand_held

TASK, SEED, NAME = "P-G-B", 1, "instrument"


@pytest.fixture(scope="module")
def runs():
    """(run without, run with the extra targets) of run_task, once per module: the first two tests compare them, the
    jitter test adds the instrument to copies of the first (``simulate`` is what run_task runs before add_hand_held,
    so the run without is the jitter test's base run, not a second simulation of it) and compares with the second.
    Only read: every test that adds to a run adds to a deep copy."""
    return run_task(TASK, seed=SEED, extra_targets=False), run_task(TASK, seed=SEED)


def test_the_arm_held_tool_is_unchanged_by_the_second_target(runs):
    without, with_ = runs
    assert NAME not in without.omc.bodies and NAME in with_.omc.bodies and NAME in with_.ots.tools
    for dev, group in (("omc", "bodies"), ("ots", "tools")):
        for name, a in getattr(getattr(without, dev), group).items():
            b = getattr(getattr(with_, dev), group)[name]
            for field in ("position", "quat_xyzw"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f"{dev} {name} {field}")
    np.testing.assert_array_equal(without.diana.q, with_.diana.q)
    np.testing.assert_array_equal(without.truth.T_base_tool, with_.truth.T_base_tool)


def test_the_instrument_crosses_every_region_and_is_measured_within_the_noise(runs):
    _, run = runs
    tr = run.extra_truth[NAME]
    assert {1, 2, 3} <= set(np.unique(tr.region).tolist())
    b = run.omc.bodies[NAME]
    assert 0.2 < b.tracked.mean() < 0.95          # tracked over much of the path, lost on the occluded stretches
    assert b.tracked[tr.region == 2].mean() > b.tracked[tr.region == 3].mean()
    e_omc = np.linalg.norm(b.position[b.tracked] - tr.T_omc_tool[b.tracked, :3, 3], axis=1)
    assert np.median(e_omc) < 0.005               # the OMC's miscalibration: millimetres
    v = run.ots.tools[NAME]
    assert v.visible.any()
    T = HandHeldPath(load_hand_held(build_scene(SEED).config), run.static["T_omc_ots"], SEED).poses(run.ots.t_ns / 1e9)
    p_ots = (np.linalg.inv(run.static["T_omc_ots"]) @ T)[:, :3, 3]
    e_ots = np.linalg.norm(v.position[v.visible] - p_ots[v.visible], axis=1)
    assert np.median(e_ots) < 0.0005              # the Vega: a few tenths of a millimetre
    # the truth in base is the truth in omc through the base marker's true pose
    np.testing.assert_allclose(tr.T_base_tool, np.linalg.inv(run.static["T_omc_base"]) @ tr.T_omc_tool, atol=1e-12)


def test_seeded_jitter_and_the_carrier_occludes(runs):
    scene = build_scene(SEED)
    plan = plan_task(TASK, scene)
    scene = scene.with_diana_base(plan.T_omc_diana_base)
    base, a = runs        # simulate(scene, plan.arc, task=TASK) as run_task runs it, and run_task's add_hand_held of it
    assert base.task == TASK and base.info["plan_attempts"] == plan.attempts and base.arc == plan.arc
    b = add_hand_held(copy.deepcopy(base), scene)     # the same scene again, outside run_task: the same instrument
    np.testing.assert_array_equal(a.extra_truth[NAME].T_omc_tool, b.extra_truth[NAME].T_omc_tool)
    other = add_hand_held(copy.deepcopy(base), build_scene(SEED + 1).with_diana_base(plan.T_omc_diana_base))
    jitter = np.linalg.norm(other.extra_truth[NAME].T_omc_tool[:, :3, 3] - a.extra_truth[NAME].T_omc_tool[:, :3, 3],
                            axis=1)
    assert 1e-4 < np.median(jitter) < 0.02        # another seed: another hand (mm), the same path (not metres)
    cfg = copy.deepcopy(scene.config)
    cfg["second_target"]["carrier"]["radius"] = 0.001
    thin = add_hand_held(copy.deepcopy(base), build_scene(SEED, config=cfg).with_diana_base(plan.T_omc_diana_base))
    # camera rays to the instrument's markers: the person blocks a good share (16 % here; a tracked pose needs only
    # 3 markers x 2 of 12 cameras, so the tracked share changes far less)
    assert thin.omc.bodies[NAME].rays.sum() > 1.1 * a.omc.bodies[NAME].rays.sum(), "the carrier hides no ray"


def test_a_scene_without_the_section_has_no_second_target():
    scene = build_scene(SEED)
    cfg = copy.deepcopy(scene.config)
    cfg["second_target"]["enabled"] = False
    assert load_hand_held(cfg) is None
    del cfg["second_target"]
    assert load_hand_held(cfg) is None
    cfg = copy.deepcopy(scene.config)
    cfg["second_target"]["name"] = "tool"
    with pytest.raises(ValueError, match="second_target.name"):
        load_hand_held(cfg)


def test_truth_topic_round_trip_and_interpolation(tmp_path):
    # a pose moving at 0.5 m/s along x and turning about z at 1 rad/s: linear and slerp interpolation are exact
    t = np.arange(0, 1_000_000_000, 10_000_000, dtype=np.int64) + 1_700_000_000_000_000_000
    s = (t - t[0]) * 1e-9
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, 0, 3] = 0.5 * s
    T[:, 0, 0] = T[:, 1, 1] = np.cos(s)
    T[:, 1, 0], T[:, 0, 1] = np.sin(s), -np.sin(s)
    bag = write_truth_bag(tmp_path / "b", {NAME: (t, T)})
    track = load_truth_track(bag, NAME)
    assert isinstance(track, TruthTrack) and isinstance(target_truth(bag, NAME), TruthTrack)
    assert target_truth(bag, "tool") is None      # the arm-held target: the Diana's joints, as before
    q = t[:-1] + 5_000_000
    Tq, ok = track.T_base_tool(np.concatenate([q, [t[0] - 1, t[-1] + 1]]))
    assert ok[:-2].all() and not ok[-2:].any()
    sq = (q - t[0]) * 1e-9
    np.testing.assert_allclose(Tq[:-2, 0, 3], 0.5 * sq, atol=1e-9)
    np.testing.assert_allclose(np.arctan2(Tq[:-2, 1, 0], Tq[:-2, 0, 0]), sq, atol=1e-9)
    with pytest.raises(ValueError, match=f"{TRUTH_PREFIX}/other"):
        load_truth_track(bag, "other")


def test_merge_bag_adds_the_truth_file_and_refuses_a_clash(tmp_path):
    from fullperc_eval.bag.errors import BagError
    from fullperc_eval.bag.reader import BagReader
    from fullperc_eval.sim.dataset import merge_bag

    t = np.arange(5, dtype=np.int64) * 10_000_000 + 1_700_000_000_000_000_000
    T = np.tile(np.eye(4), (5, 1, 1))
    dst = write_truth_bag(tmp_path / "dst", {"a": (t, T)})
    src = write_truth_bag(tmp_path / "src", {"b": (t + 1, T)})
    merge_bag(dst, src)
    assert not src.exists()
    r = BagReader(dst)
    assert {f"{TRUTH_PREFIX}/a", f"{TRUTH_PREFIX}/b"} <= set(r.topics) and r.message_count == 10
    assert len(r.info["relative_file_paths"]) == 2
    with r:
        got = [m.topic for m in r.messages()]
    assert got.count(f"{TRUTH_PREFIX}/b") == 5 and got.count(f"{TRUTH_PREFIX}/a") == 5
    with pytest.raises(BagError, match="both hold"):
        merge_bag(dst, write_truth_bag(tmp_path / "again", {"a": (t, T)}))
