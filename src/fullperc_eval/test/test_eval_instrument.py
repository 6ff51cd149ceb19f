"""The hand-held instrument of the committed bags: how a target's motion decides its fusion (docs/targets.md).

With the arm's motion (the ``arm`` preset: the paper filters' tuning) the walk's jumps pass the hop gate and go into
the bias, and so does the motion of a target already walking when first seen; that bias is applied metres away where
the Vega cannot correct it -- the defect this pins (for ``fullperc`` under CBKF's hop rule, ``hop_needs_local:
never``; by default its hops wait for the Vega's first sample, and the walk before it is fused as samples). The
``hand`` preset keeps the compensated filters at the OMC's level. ``motion: auto`` (the shipped fusion.yaml sets no
target's motion) lets fullperc find that itself (filters/fullperc_imm.py); the paper's filters, one motion model
each, then keep the node-wide (arm) values.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_fusion.fusion_config import default_fusion_config_path, node_key

ROOT = Path(__file__).resolve().parents[3]
BAG = ROOT / "bags" / "paper" / "G-B-P"
SPEC_BAG = ROOT / "bags" / "spec" / "G-B-P"
COMPENSATED = ("ckf", "cbkf", "fullperc")


def _with_motion(tmp_path: Path, motion: str, hop_needs_local: str = "once") -> Path:
    doc = yaml.safe_load(default_fusion_config_path().read_text())
    doc[node_key(doc)]["ros__parameters"]["instrument"] = {"motion": motion}
    doc[node_key(doc)]["ros__parameters"]["fullperc"]["hop_needs_local"] = hop_needs_local
    path = tmp_path / f"{motion}-{hop_needs_local}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _result(bag: Path, config: Path | None = None) -> dict:
    return evaluate_bag(bag, target="instrument", progress=False, fusion_config=config).result


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """MAE [mm] per method of each run; ``<run>_result``: the whole evaluation of the paper runs auto and hand."""
    tmp = tmp_path_factory.mktemp("motion")
    runs = {"auto": _result(BAG), "hand": _result(BAG, _with_motion(tmp, "hand")),
            "arm": _result(BAG, _with_motion(tmp, "arm", "never")),
            "arm_once": _result(BAG, _with_motion(tmp, "arm")), "spec_auto": _result(SPEC_BAG),
            "spec_hand": _result(SPEC_BAG, _with_motion(tmp, "hand"))}
    return {**{k: r["mae_mm"] for k, r in runs.items()}, "auto_result": runs["auto"], "hand_result": runs["hand"]}


def test_with_the_hand_preset_the_compensated_filters_stay_at_the_omcs_level(results):
    hand = results["hand"]
    for m in COMPENSATED:
        assert hand[m] <= 1.15 * hand["omc"], (m, hand)
    assert hand["kf"] <= hand["omc"]


def test_with_the_arms_motion_the_walk_goes_into_the_bias(results):
    arm, hand = results["arm"], results["hand"]
    assert arm["omc"] == hand["omc"]
    for m in COMPENSATED:
        assert arm[m] > 1.5 * hand["omc"] and arm[m] > 1.5 * hand[m], (m, arm, hand)


def test_fullperc_keeps_the_walk_out_of_the_bias_before_the_vega_sees_it(results):
    """The instrument is walking when the OMC first sees it (G-B-P): with the arm's values and the default
    ``hop_needs_local: once`` fullperc fuses those jumps as samples, so it stays at the OMC's level where CBKF's hop
    rule (the run above) put them into the bias."""
    once, hand = results["arm_once"], results["hand"]
    assert once["fullperc"] <= 1.15 * hand["omc"] and once["fullperc"] < results["arm"]["fullperc"] / 1.5, once


def test_auto_finds_the_hand_for_fullperc_and_the_paper_filters_keep_the_arms_values(results):
    """motion auto, the shipped default: fullperc stays at the OMC's level and near the hand preset (its goal: within
    5 % over 10 seeds, `make accuracy`; one bag here); the paper's filters fuse with the node-wide values as with the
    arm preset, bit for bit."""
    auto, hand, arm = results["auto"], results["hand"], results["arm"]
    assert auto["fullperc"] <= 1.15 * auto["omc"], auto
    assert auto["fullperc"] <= 1.10 * hand["fullperc"], (auto, hand)
    for m in ("kf", "bkf", "ckf", "cbkf"):
        assert auto[m] == arm[m], m


def test_with_the_spec_omc_fullperc_stays_near_it(results):
    """The `spec` OMC (0.2 mm) leaves little room: fullperc within 1.5x of it, with auto as with the hand preset (with
    the arm's values: ~40x). CBKF is not held to it: its biased estimator (paper eq. 4-8) shrinks a coordinate that
    crosses a plane of `base` while the position's variance is large (13 mm^2 before the Vega first sees the
    instrument) towards 0, by up to 1.5 mm, kept until the Vega sees it (docs/targets.md)."""
    for key in ("spec_auto", "spec_hand"):
        spec = results[key]
        assert spec["fullperc"] <= 1.5 * spec["omc"], (key, spec)
    assert results["spec_hand"]["ckf"] <= 1.5 * results["spec_hand"]["omc"], results["spec_hand"]


def test_auto_turns_as_the_hand_does_and_its_pose_covariance_holds(results):
    """The instrument's orientation under auto: the models' states are mixed at every sample, so a class whose turn
    allowance (q_alpha) is below how a hand turns takes the weight whenever the innovations are small and carries the
    hand's turns with too small a covariance (filters/motion.py). With the classes' allowances, fullperc's
    orientation error stays within 1.3x the hand preset's and its pose NEES inside the 95 % bound for >= 80 % of the
    samples (an arm q_alpha of 0.005 gave 2.4x and 58 %)."""
    auto, hand = results["auto_result"], results["hand_result"]
    assert auto["orientation_mae_deg"]["fullperc"] <= 1.3 * hand["orientation_mae_deg"]["fullperc"]
    assert auto["nees"]["fullperc"]["pose"]["share_95"] >= 0.8, auto["nees"]["fullperc"]
