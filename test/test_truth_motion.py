"""``scripts/truth_motion.py`` (README "The `fullperc` filter", ``<target>.ang_accel_noise``) on committed bags: the
arm-held tool's turn rate and its change, from the Diana's forward kinematics."""

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
    mod.main([str(ROOT / "bags" / "paper" / "G-B-P"), str(ROOT / "bags" / "spec" / "P-B-G-P")])
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 3 and all("|w| max" in line for line in out)
    m = re.search(r"over 2 bags: \|w\| max ([0-9.]+) rad/s, \|dw/dt\| max ([0-9.]+) rad/s\^2", out[-1])
    assert m and float(m.group(1)) >= f["w_max"] and float(m.group(2)) >= f["a_max"]
