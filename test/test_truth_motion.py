"""``scripts/truth_motion.py`` on committed bags: how the arm-held tool and the hand-held instrument move and turn,
from their ground truth -- a check of the twin against the motion classes of filters/motion.py (docs/targets.md
"How a target moves"), never a source of a filter setting."""

from __future__ import annotations

import math
import re
from pathlib import Path

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


def test_the_twins_targets_move_as_their_motion_classes_say(load_script, capsys):
    """The motion presets (filters/motion.py) are physical classes, not fits to the twin's truth; the twin's targets
    are instances of them. The arm-held tool stays inside the ``arm`` class's speed envelope, its motion density
    (v_max a_max) below the preset's q_a (the paper's tuning, 20x it) and its turn density (w_max dw/dt_max) below
    the preset's q_alpha (10x it: the class allows a reorientation an arm can make, the twin's arm turns slowly);
    the walking instrument is faster than any arm moves a tool (so the envelope tells them apart, ``motion:
    auto``), within a walking hand's, and its v_max a_max of the ``hand`` preset's q_a's order."""
    from fullperc_fusion.filters.motion import MAX_SPEED, PRESETS

    mod = load_script("truth_motion")
    bags = [b for p in ("paper", "spec") for b in sorted((ROOT / "bags" / p).iterdir()) if b.is_dir()]
    tool = [mod.motion_figures(str(b), "tool") for b in bags]
    assert max(f["v_max"] for f in tool) < MAX_SPEED["arm"]
    assert max(f["q_cv"] for f in tool) < PRESETS["arm"]["accel_noise"]
    assert max(f["q_turn"] for f in tool) < PRESETS["arm"]["ang_accel_noise"]
    inst = mod.motion_figures(str(ROOT / "bags" / "paper" / "G-B-P"), "instrument")
    assert MAX_SPEED["arm"] < inst["v_max"] < MAX_SPEED["hand"] and 1.0 < inst["acc_max"] < 5.0
    assert 0.5 < inst["q_cv"] / PRESETS["hand"]["accel_noise"] < 2.0
    assert inst["q_cv"] > 100 * max(f["q_cv"] for f in tool)
    mod.main(["--target", "instrument", str(ROOT / "bags" / "spec" / "G-B-P")])
    assert "over 1 bags (instrument)" in capsys.readouterr().out
