"""``scripts/truth_motion.py`` (docs/fullperc_filter.md: ``<target>.ang_accel_noise``; docs/targets.md:
``<target>.accel_noise``) on committed bags: how the arm-held tool and the hand-held instrument move and
turn, from their ground truth."""

from __future__ import annotations

import math
import re
from pathlib import Path

from fullperc_fusion.fusion_config import node_key

ROOT = Path(__file__).resolve().parents[1]


def test_truth_motion_reports_the_turn_rate_and_its_change(load_script, capsys):
    mod = load_script("truth_motion")
    f = mod.turn_figures(str(ROOT / "bags" / "paper" / "G-B-P"))
    assert all(math.isfinite(v) for v in f.values())
    assert 0.01 < f["w_max"] < 1.0                     # the arm turns the tool, slowly
    assert 0.0 < f["a_median"] <= f["a_p99"] <= f["a_max"] < 0.5
    assert 0.01 < f["v_max"] < 0.2 and f["acc_max"] < 0.1 and f["q_cv"] == f["v_max"] * f["acc_max"]
    mod.main([str(ROOT / "bags" / "paper" / "G-B-P"), str(ROOT / "bags" / "spec" / "P-B-G-P")])
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 3 and all("|w| max" in line for line in out)
    m = re.search(r"over 2 bags \(tool\): \|w\| max ([0-9.]+) rad/s, \|dw/dt\| max ([0-9.]+) rad/s\^2", out[-1])
    assert m and float(m.group(1)) >= f["w_max"] and float(m.group(2)) >= f["a_max"]


def test_the_hand_held_instrument_needs_a_motion_model_of_its_own(load_script, capsys):
    """The instrument walks: its v_max * a_max (the white-acceleration density a constant-velocity model needs) is
    three orders above the arm-held tool's; fusion.yaml's `instrument.accel_noise` is that figure and its
    `instrument.init_vel_std` the walk's top speed, each to one significant digit."""
    import yaml

    mod = load_script("truth_motion")
    inst = mod.motion_figures(str(ROOT / "bags" / "paper" / "G-B-P"), "instrument")
    tool = mod.motion_figures(str(ROOT / "bags" / "paper" / "G-B-P"), "tool")
    assert 0.5 < inst["v_max"] < 1.5 and 1.0 < inst["acc_max"] < 5.0     # a walking hand (0.88 m/s, 2.4 m/s^2)
    assert inst["q_cv"] > 100 * tool["q_cv"]
    doc = yaml.safe_load((ROOT / "src/fullperc_fusion/config/fusion.yaml").read_text())
    block = doc[node_key(doc)]["ros__parameters"]["instrument"]
    assert block["accel_noise"] == float(f"{inst['q_cv']:.1g}"), (block, inst["q_cv"])
    assert block["init_vel_std"] == float(f"{inst['v_max']:.1g}"), (block, inst["v_max"])   # its top speed
    mod.main(["--target", "instrument", str(ROOT / "bags" / "spec" / "G-B-P")])
    assert "over 1 bags (instrument)" in capsys.readouterr().out


def test_the_arm_held_tools_turn_model_is_its_truth_motion(load_script):
    """fusion.yaml's `tool.ang_accel_noise` (fullperc's constant-angular-velocity model for the arm-held tool) is the
    largest |w| max * |dw/dt| max of the committed bags' truth, to one significant digit, as the instrument's
    `accel_noise` is its v_max * a_max; and far below the node-wide default, which is a hand-held instrument's."""
    import yaml

    from fullperc_fusion.filters.fullperc_params import FullpercParams

    mod = load_script("truth_motion")
    q = max(mod.motion_figures(str(bag), "tool")["q_turn"] for bag in sorted((ROOT / "bags" / "paper").iterdir())
            if bag.is_dir())
    doc = yaml.safe_load((ROOT / "src/fullperc_fusion/config/fusion.yaml").read_text())
    assert doc[node_key(doc)]["ros__parameters"]["tool"]["ang_accel_noise"] == float(f"{q:.1g}"), q
    assert q < FullpercParams().ang_accel_noise / 50
