"""``scripts/hop_trace.py`` (docs/fullperc_filter.md "Where a hop goes") on a committed bag: it prints the hops it
finds with the filter's own figures and the motion model that flagged each, and leaves the filter as it was."""

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
    # motion: auto (the shipped fusion.yaml): each line names the IMM model it shows
    assert {r.split(" model ")[1].split()[0] for r in rows} <= {"arm", "hand", "static"}
    assert any(line.startswith("velocity error rms") for line in out)
    assert any(line.startswith("task MAE [mm]:") and "'fullperc'" in line for line in out)
    assert any(line.startswith("MAE in the window [mm]:") and "'omc'" in line for line in out)


def test_a_hop_of_any_model_is_shown_and_a_replayed_update_replaces_its_first_run(load_script):
    """motion: auto updates every stamp once per model: the stamp shows the model that flagged a hop (here not the
    last one), else the last model; an update replayed after a rewind (same stamp and model) replaces the first."""
    def rec(t, model, hp=0, hr=0, tag=""):
        return (t, 1, hp, hr, 0.0, None, None, None, 0.0, 1.0, model, tag)
    log = [rec(1, "static"), rec(1, "arm", hp=1), rec(1, "hand"),
           rec(2, "static"), rec(2, "arm"), rec(2, "hand", tag="first"),
           rec(2, "hand", tag="replayed"), rec(3, "arm", hr=1, tag="first"), rec(3, "arm", tag="replayed")]
    shown = load_script("hop_trace").shown_updates(log)
    assert shown[1][10] == "arm" and shown[1][2] == 1
    assert shown[2][10] == "hand" and shown[2][11] == "replayed"
    assert shown[3][11] == "replayed" and shown[3][3] == 0   # the replay flagged nothing: no hop at 3
