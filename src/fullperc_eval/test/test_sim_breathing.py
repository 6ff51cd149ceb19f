"""The twin's third target (sim/breathing.py): a patient reference frame that moves only as the patient breathes.

Pinned: every other body's data are the same with and without it (own random streams, it occludes nothing); its
truth breathes at a rate and depth within the configured ranges and is otherwise static; it is seen most of the time,
and the arm (the Vega) and the nurse carrying the instrument (OMC cameras) occlude it at times; its topics and truth
reach a bag, and the evaluator gives it rows of its own.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from scipy.signal import find_peaks
from scipy.spatial.transform import Rotation

from fullperc_eval.evaluation import evaluate_all
from fullperc_eval.evaluation.evaluate_all import bag_targets
from fullperc_eval.sim import run_task, target_model
from fullperc_eval.sim.breathing import BreathingMotion, add_reference, load_breathing
from fullperc_eval.sim.dataset import TRUTH_PREFIX, content_from_sim, write_bag
from fullperc_eval.sim.omc_model import Occluders
from fullperc_eval.sim.scene import SceneError, build_scene, load_scene_config
from fullperc_eval.sim.targets import check_targets
from fullperc_eval.sim.tasks import plan_task
from fullperc_eval.sim.walker import HandHeldPath, hand_held

# the committed bags' profile and seed; P-B-G-P's arc sweeps the arm through the Vega's line of sight to the frame
TASK, SEED, PROFILE, NAME = "P-B-G-P", 0, "paper", "reference"


def _config(enabled: bool = True) -> dict:
    cfg = load_scene_config(profile=PROFILE)
    cfg["reference_target"]["enabled"] = enabled
    return cfg


@pytest.fixture(scope="module")
def runs():
    """(run without, run with the reference) of run_task, once per module; only read."""
    return run_task(TASK, seed=SEED, config=_config(False)), run_task(TASK, seed=SEED, config=_config())


@pytest.fixture(scope="module")
def scene():
    """The scene of the runs (seed, profile, the task's cart position)."""
    s = build_scene(SEED, config=_config())
    return s.with_diana_base(plan_task(TASK, s).T_omc_diana_base)


def test_every_other_body_is_unchanged_by_the_reference(runs):
    without, with_ = runs
    assert NAME not in without.omc.bodies and NAME in with_.omc.bodies and NAME in with_.ots.tools
    assert "instrument" in without.omc.bodies    # the second target stays: only the reference is switched off
    a, b = without.flat(), with_.flat()
    assert set(b) - set(a) == {k for k in b if k.startswith((f"omc/{NAME}/", f"ots/{NAME}/", f"truth_{NAME}/"))}
    for k in a:   # every OMC body and Vega tool, the joints, the tool's and the instrument's truth
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def _breaths(run, d):
    """The truth's displacement [m] along the breathing direction from the frame's end-exhale pose, and what is left."""
    tr = run.extra_truth[NAME]
    dp = tr.T_omc_tool[:, :3, 3] - d.T_rest[:3, 3]
    s = dp @ d.direction
    return tr.t_ns * 1e-9, s, dp - s[:, None] * d.direction


def test_the_truth_breathes_within_the_configured_rate_and_depth(runs):
    _, run = runs
    d = load_breathing(_config())
    t, s, rest = _breaths(run, d)
    assert np.abs(rest).max() < 1e-12                      # static apart from the breathing ...
    assert s.min() > -1e-12                                 # ... which starts from end-exhale
    peaks, _ = find_peaks(s, prominence=1e-3)
    assert 5 <= len(peaks) <= 10, len(peaks)                # 28 s at 12-20 /min
    lo, hi = (v * 1e-3 for v in d.amplitude_mm)
    depth = s[peaks]                                        # end-inhale of each breath (sampled at 120 Hz)
    assert np.all(depth >= lo * (1 - 1e-3)) and np.all(depth <= hi), depth
    rate = 60.0 / np.diff(t[peaks])                         # breaths/min from one end-inhale to the next
    r_lo, r_hi = d.rate_per_min
    assert np.all(rate >= r_lo * 0.99) and np.all(rate <= r_hi * 1.01), rate
    assert np.ptp(depth) > 0 and np.ptp(rate) > 0           # breath-to-breath variation
    # the frame turns with the skin: 0.3 deg/mm about omc x
    R_rel = run.extra_truth[NAME].T_omc_tool[:, :3, :3] @ d.T_rest[:3, :3].T
    rv = Rotation.from_matrix(R_rel).as_rotvec()
    np.testing.assert_allclose(rv[:, 0], np.radians(d.tilt_deg_per_mm) * s * 1e3, atol=1e-9)
    np.testing.assert_allclose(rv[:, 1:], 0.0, atol=1e-12)
    info = run.info["extra_targets"][NAME]
    assert info["kind"] == "breathing" and info["omc_id"] == 5 and info["rom_file"] == "reference.rom"


def test_each_seed_breathes_its_own_rate_and_depth():
    d = load_breathing(_config())
    m = [BreathingMotion(d, seed) for seed in range(20)]
    rates = np.array([x.rate_per_min for x in m])
    depths = np.array([x.amplitude_m * 1e3 for x in m])
    assert np.all((rates >= 12.0) & (rates <= 20.0)) and np.all((depths >= 2.0) & (depths <= 4.0))
    assert np.ptp(rates) > 4.0 and np.ptp(depths) > 1.0     # drawn per seed across the ranges, not fixed
    np.testing.assert_array_equal(m[3].displacement(np.arange(0, 30, 0.01)),
                                  BreathingMotion(d, 3).displacement(np.arange(0, 30, 0.01)))


def _without_arm(monkeypatch) -> None:
    """The run's occluders with the arm's links made infinitely thin (the staff, boxes and carriers stay)."""
    orig = target_model._occluders

    def occluders(scene, origins, t_ns, staff):
        occ = orig(scene, origins, t_ns, staff)
        r = occ.cap_r.copy()
        r[:len(r) - (len(scene.staff) if staff else 0)] = 0.0   # link_capsules come first (run._occluders)
        return Occluders(occ.cap_a, occ.cap_b, r, occ.boxes)

    monkeypatch.setattr(target_model, "_occluders", occluders)


def test_seen_most_of_the_time_and_occluded_by_the_arm_and_the_nurse(runs, scene, monkeypatch):
    without, with_ = runs
    o, v = with_.omc.bodies[NAME], with_.ots.tools[NAME]
    assert o.tracked.mean() > 0.95                          # the OMC: 4-6 robot-side and end cameras
    assert 0.8 < v.visible.mean() < 1.0, v.visible.mean()   # the Vega: lost while the arm crosses its line of sight
    nurse = [hand_held(scene).carrier_capsule]
    again = add_reference(copy.deepcopy(without), scene, nurse)   # outside run_task: the same reference
    np.testing.assert_array_equal(again.ots.tools[NAME].visible, v.visible)
    np.testing.assert_array_equal(again.omc.bodies[NAME].rays, o.rays)
    # the nurse carrying the instrument hides OMC cameras: fewer rays with her than without her
    alone = add_reference(copy.deepcopy(without), scene, [])
    assert alone.omc.bodies[NAME].rays.sum() > o.rays.sum() + 500, "the nurse hides no ray"
    assert (alone.omc.bodies[NAME].rays >= o.rays).all()
    # the arm: without its links the Vega sees the frame in every frame, and the OMC cameras more rays
    _without_arm(monkeypatch)
    no_arm = add_reference(copy.deepcopy(without), scene, nurse)
    assert no_arm.ots.tools[NAME].visible.all()
    assert no_arm.omc.bodies[NAME].rays.sum() > o.rays.sum(), "the arm hides no camera ray"


def test_a_scene_without_the_section_has_no_reference_and_names_stay_apart():
    # its own SeedSequence children: after the scene's 0-3, apart from the instrument's
    assert not set(HandHeldPath.streams) & set(BreathingMotion.streams)
    assert min(HandHeldPath.streams + BreathingMotion.streams) > 3
    cfg = _config(False)
    assert load_breathing(cfg) is None
    del cfg["reference_target"]
    assert load_breathing(cfg) is None
    cfg = _config()
    cfg["reference_target"]["name"] = "base"
    with pytest.raises(SceneError, match="reference_target.name"):
        load_breathing(cfg)
    for key, value in (("name", "instrument"), ("id", 4)):
        cfg = _config()
        cfg["reference_target"][key] = value
        with pytest.raises(SceneError, match=f"two extra targets with the {key}"):
            check_targets(cfg)
    cfg = _config()
    cfg["reference_target"]["breathing"]["rate_per_min"] = [20.0, 12.0]
    with pytest.raises(SceneError, match="rate_per_min"):
        load_breathing(cfg)


def test_the_bag_holds_its_topics_and_truth_and_the_evaluator_gives_it_rows(runs, tmp_path):
    _, run = runs
    bag = write_bag(tmp_path / "bags" / TASK, content_from_sim(run))
    assert bag_targets(bag, ["all"]) == ["tool", "instrument", NAME]
    out = tmp_path / "eval.json"
    assert evaluate_all.main(["--bags", str(tmp_path / "bags"), "--targets", NAME, "--json", str(out),
                              "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["tasks"] == [] and [r["task"] for r in doc["targets"][NAME]] == [f"{TASK} {NAME}"]
    r = doc["targets"][NAME][0]
    assert r["target"] == NAME
    counts = r["topic_counts"]
    assert counts[f"/omc/{NAME}/pose"] == int(run.omc.bodies[NAME].tracked.sum())
    assert counts[f"/ots/{NAME}/pose"] == int(run.ots.tools[NAME].visible.sum())
    assert TRUTH_PREFIX not in "".join(counts)   # the truth is the reference the rows are measured against
    mae = r["mae_mm"]
    assert all(np.isfinite(mae[m]) and mae[m] > 0 for m in ("omc", "kf", "ckf", "cbkf"))
    assert mae["ckf"] < mae["omc"]     # the Vega sees the frame most of the time: the OMC's bias is compensated
