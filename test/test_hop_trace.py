"""``scripts/hop_trace.py`` (docs/fullperc_filter.md "Where a hop goes") on a committed bag: it prints the hops it
finds with the filter's own figures, and leaves the filter as it was."""

from __future__ import annotations

import ast
from pathlib import Path

import fullperc_fusion.filters.fullperc as ff

ROOT = Path(__file__).resolve().parents[1]


def test_hop_trace_prints_every_hop_and_restores_the_filter(load_script, capsys):
    update = ff.FullpercFilter.update
    load_script("hop_trace").main([str(ROOT / "bags" / "spec" / "P-G-B-P"), "--all", "--from", "10", "--to", "12"])
    assert ff.FullpercFilter.update is update
    out = capsys.readouterr().out.splitlines()
    rows = [line for line in out if " s src " in line]
    counts = next(line for line in out if line.startswith("updates, position hops"))
    n = ast.literal_eval(counts.split(":", 1)[1])   # {'OMC alone': [updates, position hops, rotation hops], ...}
    assert len(rows) == sum(v[0] for v in n.values()) > 100            # --all: one line per update in the window
    assert all(10.0 <= float(r.split()[0]) <= 12.0 for r in rows)
    assert any(line.startswith("velocity error rms") for line in out)
    assert any(line.startswith("task MAE [mm]:") and "'fullperc'" in line for line in out)
    assert any(line.startswith("MAE in the window [mm]:") and "'omc'" in line for line in out)
