"""The text tables (evaluation/tables.py): every figure sits right under its column name, whatever the labels.

``make demo`` labels its rows ``P-B-G-P offline`` / ``P-B-G-P live`` (longer than the task names of ``make eval``),
some methods have no figure (``-``), and an MAE can exceed 1 m when a run goes wrong: none of it may shift a column.
"""

from __future__ import annotations

import re

from fullperc_eval.evaluation.config import METHODS
from fullperc_eval.evaluation.tables import format_table1, format_table2


def _ends(line: str) -> list[int]:
    return [m.end() for m in re.finditer(r"\S+", line)]


def _assert_aligned(lines: list[str], labels: list[str]) -> None:
    head, rows = lines[0], lines[1:]
    col_ends = _ends(head)[1:]  # the right edge of every figure column (the label column is left-aligned)
    for row, label in zip(rows, labels, strict=True):
        assert row.startswith(label + " "), (row, label)
        assert _ends(row)[-len(col_ends):] == col_ends, "\n" + "\n".join(lines)


def _row(task: str, values: list[float | None]) -> dict:
    return {"task": task, "mae_mm": dict(zip(METHODS, values, strict=True))}


def test_table1_columns_line_up_with_long_labels_missing_and_large_values():
    rows = [_row("P-B-G-P offline", [3.81, 2.21, 2.2, 1.77, 1.76]),
            _row("P-B-G-P live", [1234.56, None, float("nan"), 1.8, 1.79]),
            _row("G-B-P", [3.39, 1.84, 1.82, 1.64, 1.63])]
    text = format_table1(rows)
    lines = text.splitlines()
    assert lines[0].startswith("Table 1")
    _assert_aligned(lines[1:], [r["task"] for r in rows])
    head = lines[1].split()
    assert head[1:] == [m.upper() for m in METHODS] + ["CBKF/OMC"]
    assert lines[2].split()[-1] == f"{1.76 / 3.81:.2f}"  # the ratio column
    assert lines[3].split()[2:5] == ["1234.56", "-", "-"]  # no figure: a dash in its column


def test_table2_columns_line_up():
    mm = dict(zip(METHODS, [6.36, 18.32, 6.76, 2.02, 2.02], strict=True))
    r = {"task": "G-B-P", "b_to_p": {"t0_s": 1.0, "t1_s": 2.5, "max_mm": mm,
                                     "median_mm": dict(zip(METHODS, [5.81, 5.77, None, 0.25, 0.25], strict=True))}}
    lines = format_table2(r).splitlines()
    assert lines[0].startswith("Table 2 (G-B-P)")
    _assert_aligned(lines[1:], ["max", "median"])
