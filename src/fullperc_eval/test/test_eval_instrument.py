"""The hand-held instrument of the committed bags, evaluated with fusion.yaml (docs/targets.md).

Its own motion model, velocity prior and hop rule (fusion.yaml's `instrument` block: `accel_noise` from its truth's
v_max * a_max, `init_vel_std` its v_max, `hop_to_bias: false`) keep the compensated filters at the OMC's level on
the walk; with the arm-held tool's values (the node-wide `noise.accel`, `init.vel_std`, `hop_to_bias`) the walk's
accelerations leave the hop gate and go into the bias, and so does the motion of a target already walking when first
seen; that bias is applied metres away where the Vega cannot correct it -- the defect this pins.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_fusion.fusion_config import default_fusion_config_path, node_key

ROOT = Path(__file__).resolve().parents[3]
BAG = ROOT / "bags" / "paper" / "G-B-P"
COMPENSATED = ("ckf", "cbkf", "fullperc")


@pytest.fixture(scope="module")
def shipped():
    return evaluate_bag(BAG, target="instrument", progress=False).result["mae_mm"]


def test_the_compensated_filters_stay_at_the_omcs_level_on_the_walk(shipped):
    for m in COMPENSATED:
        assert shipped[m] <= 1.15 * shipped["omc"], (m, shipped)
    assert shipped["kf"] <= shipped["omc"]


def test_with_the_spec_omc_ckf_and_fullperc_stay_near_it():
    """The `spec` OMC (0.2 mm) leaves little room: CKF and fullperc within 1.5x of it (with the arm's values: 39x and
    42x). CBKF is not held to it: its biased estimator (paper eq. 4-8) shrinks a coordinate that crosses a plane of
    `base` while the position's variance is large (13 mm^2 before the Vega first sees the instrument) towards 0, by up
    to 1.5 mm, kept until the Vega sees it (docs/targets.md)."""
    spec = evaluate_bag(ROOT / "bags" / "spec" / "G-B-P", target="instrument", progress=False).result["mae_mm"]
    for m in ("ckf", "fullperc"):
        assert spec[m] <= 1.5 * spec["omc"], (m, spec)


def test_with_the_arms_motion_model_and_hop_rule_the_walk_goes_into_the_bias(shipped, tmp_path):
    doc = yaml.safe_load(default_fusion_config_path().read_text())
    del doc[node_key(doc)]["ros__parameters"]["instrument"]
    path = tmp_path / "arm_tuning.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    arm = evaluate_bag(BAG, target="instrument", progress=False, fusion_config=path).result["mae_mm"]
    assert arm["omc"] == shipped["omc"]
    for m in COMPENSATED:
        assert arm[m] > 1.5 * shipped["omc"] and arm[m] > 1.5 * shipped[m], (m, arm, shipped)
