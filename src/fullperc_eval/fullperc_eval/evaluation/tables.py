"""Text tables and JSON of evaluation results: Table 1 (MAE per method), Table 2 (the B->P segment).

:func:`format_table1` prints the paper's Table 1 (position MAE) and, when the results carry them, two more blocks
under it: **Table 1b**, the orientation MAE [deg] of every method and of the raw local chain (``LOCAL``), and the
**consistency** block, each method's position NEES as ``<share inside the chi2 95 % bound> %/<mean NEES>`` (and the
full-pose NEES for methods that fuse the orientation). Every column is padded to its widest cell, figures
right-aligned (:func:`_grid`), whatever the row labels or the number of methods.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .config import METHODS


def _fmt(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"


def _grid(head: list[str], rows: list[list[str]]) -> list[str]:
    """Columns as wide as their widest cell: the first (a label) left-aligned, the figures right-aligned."""
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]

    def line(cells: list[str]) -> str:
        out = [cells[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(cells[1:], widths[1:], strict=True)]
        return "  ".join(out).rstrip()

    return [line(head)] + [line(r) for r in rows]


def format_table1(rows: list[dict[str, Any]], methods=METHODS) -> str:
    """Table 1 (position MAE [mm], CBKF/OMC ratio), then Table 1b and the consistency block when present."""
    body = []
    for r in rows:
        mae = r["mae_mm"]
        ratio = (mae["cbkf"] / mae["omc"]) if mae.get("cbkf") and mae.get("omc") else None
        body.append([str(r["task"])] + [_fmt(mae.get(m)) for m in methods] + [_fmt(ratio)])
    head = ["task"] + [m.upper() for m in methods] + ["CBKF/OMC"]
    blocks = ["\n".join(["Table 1: MAE [mm] (every pose each method outputs, vs Diana ground truth)",
                         *_grid(head, body)])]
    for extra in (format_orientation(rows, methods), format_consistency(rows, methods)):
        if extra:
            blocks.append(extra)
    return "\n\n".join(blocks)


def _columns(rows: list[dict[str, Any]], key: str, methods) -> list[str]:
    """The methods (in ``methods`` order), then any further series (``local``) the rows carry under ``key``."""
    seen = [m for m in methods if any(m in (r.get(key) or {}) for r in rows)]
    more = [k for r in rows for k in (r.get(key) or {}) if k not in methods]
    return seen + list(dict.fromkeys(more))


def format_orientation(rows: list[dict[str, Any]], methods=METHODS) -> str:
    """Table 1b: orientation MAE [deg] per method and of the raw local chain; '' when no row has one."""
    cols = _columns(rows, "orientation_mae_deg", methods)
    if not cols:
        return ""
    body = [[str(r["task"])] + [_fmt3(r.get("orientation_mae_deg", {}).get(m)) for m in cols] for r in rows]
    return "\n".join(["Table 1b: orientation MAE [deg] (angle of R_true^T R_est; LOCAL = raw Vega chain in base)",
                      *_grid(["task"] + [m.upper() for m in cols], body)])


def _fmt3(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def nees_cell(s: dict[str, Any] | None) -> str:
    """``<share inside the bound> %/<mean>`` of one NEES summary (:func:`.consistency.summary`), '-' when empty."""
    if not s or not s.get("n"):
        return "-"
    return f"{100.0 * s['share_95']:.0f}%/{s['mean']:.3g}"


def format_consistency(rows: list[dict[str, Any]], methods=METHODS) -> str:
    """NEES per method: position (dof 3) for every row; full pose (dof 6) for the methods that have it."""
    cols = _columns(rows, "nees", methods)
    if not cols:
        return ""
    out = ["Consistency: NEES, cell = share inside the chi2 95 % bound / mean (honest: 95 % / dof)"]
    for kind, dof in (("position", 3), ("pose", 6)):
        have = [m for m in cols if any((r.get("nees", {}).get(m) or {}).get(kind, {}).get("n") for r in rows)]
        if not have:
            continue
        body = [[str(r["task"])] + [nees_cell((r.get("nees", {}).get(m) or {}).get(kind)) for m in have]
                for r in rows]
        out += [f"{kind} (dof {dof}):", *_grid(["task"] + [m.upper() for m in have], body)]
    return "\n".join(out) if len(out) > 1 else ""


def format_table2(r: dict[str, Any], methods=METHODS) -> str:
    bp = r.get("b_to_p")
    if not bp:
        return f"Table 2 ({r['task']}): no B->P segment on this path (regions {r['regions']['order']})"
    body = [[key[:-3]] + [_fmt(bp[key].get(m)) for m in methods] for key in ("max_mm", "median_mm")]
    return "\n".join([f"Table 2 ({r['task']}): B->P segment {bp['t0_s']:.2f}-{bp['t1_s']:.2f} s, error [mm]",
                      *_grid(["value"] + [m.upper() for m in methods], body)])


def to_json(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars -> Python, NaN/inf -> null."""
    if isinstance(obj, dict):
        return {str(k): to_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path: str | Path, data: Any) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(to_json(data), indent=1) + "\n")
    return p
