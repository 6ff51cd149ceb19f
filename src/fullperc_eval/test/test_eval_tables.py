"""The text tables (evaluation/tables.py): every figure sits right under its column name, whatever the labels.

``make demo`` labels its rows ``P-B-G-P offline`` / ``P-B-G-P live`` (longer than the task names of ``make eval``),
some methods have no figure (``-``), and an MAE can exceed 1 m when a run goes wrong: none of it may shift a column.
The same holds for Table 1b (orientation) and the NEES block, and for any number of registered methods.
"""

from __future__ import annotations

import re

import numpy as np

from fullperc_eval.evaluation.config import METHODS, PAPER_METHODS
from fullperc_eval.evaluation.consistency import summary
from fullperc_eval.evaluation.tables import format_table1, format_table2, nees_cell
from fullperc_fusion.pipeline.ordered import FILTER_NAMES


def _ends(line: str) -> list[int]:
    return [m.end() for m in re.finditer(r"\S+", line)]


def _assert_aligned(lines: list[str], labels: list[str]) -> None:
    head, rows = lines[0], lines[1:]
    col_ends = _ends(head)[1:]  # the right edge of every figure column (the label column is left-aligned)
    for row, label in zip(rows, labels, strict=True):
        assert row.startswith(label + " "), (row, label)
        assert _ends(row)[-len(col_ends):] == col_ends, "\n" + "\n".join(lines)


def _vals(first: float, n: int = len(METHODS)) -> list[float]:
    return [round(first - 0.37 * i, 2) for i in range(n)]


def _row(task: str, values: list[float | None]) -> dict:
    return {"task": task, "mae_mm": dict(zip(METHODS, values, strict=True))}


def test_methods_put_the_papers_five_first_and_every_registered_filter_after():
    assert METHODS[:len(PAPER_METHODS)] == PAPER_METHODS
    assert sorted(METHODS) == sorted(FILTER_NAMES)


def test_table1_columns_line_up_with_long_labels_missing_and_large_values():
    live = _vals(3.9)
    live[0], live[1], live[2] = 1234.56, None, float("nan")
    rows = [_row("P-B-G-P offline", _vals(3.81)), _row("P-B-G-P live", live), _row("G-B-P", _vals(3.39))]
    text = format_table1(rows)
    lines = text.splitlines()
    assert lines[0].startswith("Table 1")
    assert len(lines) == 2 + len(rows)          # no orientation / NEES in these rows: no further block
    _assert_aligned(lines[1:], [r["task"] for r in rows])
    head = lines[1].split()
    assert head[1:] == [m.upper() for m in METHODS] + ["CBKF/OMC"]
    mae = rows[0]["mae_mm"]
    assert lines[2].split()[-1] == f"{mae['cbkf'] / mae['omc']:.2f}"  # the ratio column
    assert lines[3].split()[2:5] == ["1234.56", "-", "-"]  # no figure: a dash in its column


def _full_row(task: str, k: int) -> dict:
    rng = np.random.default_rng(k)
    r = _row(task, _vals(3.0 + k))
    r["orientation_mae_deg"] = {**{m: float(rng.uniform(0.01, 150.0)) for m in METHODS}, "local": 0.1234}
    r["orientation_mae_deg"][METHODS[1]] = None
    good = summary(rng.chisquare(3, 400), 3)
    bad = summary(100 * rng.chisquare(3, 400), 3)
    r["nees"] = {m: {"position": good if i % 2 else bad, "pose": summary(np.array([]), 6)}
                 for i, m in enumerate(METHODS)}
    r["nees"][METHODS[-1]]["pose"] = summary(rng.chisquare(6, 300), 6)
    return r


def _blocks(text: str) -> list[list[str]]:
    return [b.splitlines() for b in text.split("\n\n")]


def test_orientation_and_nees_blocks_line_up_and_show_every_series():
    rows = [_full_row("P-B-G-P offline", 0), _full_row("P-B-G-P live", 1), _full_row("G", 2)]
    labels = [r["task"] for r in rows]
    t1, ori, cons = _blocks(format_table1(rows))
    _assert_aligned(t1[1:], labels)
    assert ori[0].startswith("Table 1b: orientation MAE [deg]")
    _assert_aligned(ori[1:], labels)
    assert ori[1].split()[1:] == [m.upper() for m in METHODS] + ["LOCAL"]
    assert ori[2].split()[-1] == "0.123" and ori[2].split()[3] == "-"  # the label has two words
    assert cons[0].startswith("Consistency: NEES")
    i_pose = cons.index("pose (dof 6):")
    assert cons[1] == "position (dof 3):"
    _assert_aligned(cons[2:i_pose], labels)
    _assert_aligned(cons[i_pose + 1:], labels)
    assert cons[i_pose + 1].split()[1:] == [METHODS[-1].upper()]   # only the method with a fused orientation
    s = rows[0]["nees"][METHODS[1]]["position"]
    assert cons[3].split()[3] == f"{100 * s['share_95']:.0f}%/{s['mean']:.3g}"


def test_nees_cell_from_the_summary():
    s = summary(np.array([1.0, 2.0, 3.0, 100.0, np.nan]), 3)
    assert (s["n"], s["share_95"], s["mean"]) == (4, 0.75, 26.5)
    assert nees_cell(s) == "75%/26.5"
    assert nees_cell(summary(np.array([]), 6)) == "-" and nees_cell(None) == "-"


def test_table2_columns_line_up():
    mm = dict(zip(METHODS, _vals(18.32), strict=True))
    med = dict(zip(METHODS, _vals(5.81), strict=True))
    med[METHODS[2]] = None
    r = {"task": "G-B-P", "b_to_p": {"t0_s": 1.0, "t1_s": 2.5, "max_mm": mm, "median_mm": med}}
    lines = format_table2(r).splitlines()
    assert lines[0].startswith("Table 2 (G-B-P)")
    _assert_aligned(lines[1:], ["max", "median"])
