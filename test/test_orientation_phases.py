"""``scripts/orientation_phases.py`` (docs/fullperc_filter.md "The orientation bias after the Vega lost the tool") on
a committed bag: the three phases partition the outputs, the seen / unseen figures are the evaluation's own
(``orientation_by_local_deg``), and the raw figures are the sensors' error where the Vega sees the tool."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from fullperc_eval.evaluation import sensor_stats

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "bags" / "paper" / "P-G-B-P"


def test_phases_partition_the_outputs_and_match_the_evaluation(load_script, capsys, monkeypatch, cached_evaluate_bag,
                                                               cached_bag_rows):
    """The bag's evaluation and raw rows are the session's (root conftest: the same as evaluate_bag with the default
    configuration and sensor_stats.bag_rows give, computed once for every test of the committed bags)."""
    mod = load_script("orientation_phases")
    ev = cached_evaluate_bag(BAG)
    ph = mod.phases(ev)
    by_local = ev.result["orientation_by_local_deg"]
    for f in ("fullperc", "omc"):
        (mb, nb), (ms, ns), (ma, na) = ph[f]["before"], ph[f]["seen"], ph[f]["after"]
        assert nb + ns + na == len(ev.series["outputs"][f]["t_ns"]) and min(nb, ns, na) > 0
        assert ms == by_local[f]["seen"]
        # unseen = before and after together, weighted by their outputs (all have an orientation here)
        assert math.isclose((mb * nb + ma * na) / (nb + na), by_local[f]["unseen"], rel_tol=1e-9)
    # this task's point: while the Vega sees the tool fullperc is far below the raw OMC
    assert ph["fullperc"]["seen"][0] < 0.5 * ph["omc"]["seen"][0]
    evaluated = []

    def evaluate_bag(bag, fusion_config=None, progress=True):   # the script's call, default configuration
        assert fusion_config is None and not progress
        evaluated.append(bag)
        return cached_evaluate_bag(Path(bag))
    monkeypatch.setattr(mod, "evaluate_bag", evaluate_bag)
    monkeypatch.setattr(sensor_stats, "bag_rows", cached_bag_rows)
    mod.main([str(BAG), "--raw"])
    assert evaluated == [str(BAG)]
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 3 and out[0].startswith(str(BAG))
    assert f"fullperc after {ph['fullperc']['after'][0]:.3f}" in out[0]
    for line, name in zip(out[1:], ("omc", "local"), strict=True):
        m = re.search(rf"raw {name} rotation error .*: std \[([0-9. ]+)\], white \[([0-9. ]+)\]", line)
        assert m, line
        sd, white = (np.array(g.split(), dtype=float) for g in m.groups())
        assert sd.shape == white.shape == (3,) and np.all(sd > 0) and np.all(white > 0)
