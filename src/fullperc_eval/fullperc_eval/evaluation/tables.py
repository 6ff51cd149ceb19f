"""Text tables and JSON of evaluation results: Table 1 (MAE per method), Table 2 (the B->P segment)."""

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
    body = []
    for r in rows:
        mae = r["mae_mm"]
        ratio = (mae["cbkf"] / mae["omc"]) if mae.get("cbkf") and mae.get("omc") else None
        body.append([str(r["task"])] + [_fmt(mae.get(m)) for m in methods] + [_fmt(ratio)])
    head = ["task"] + [m.upper() for m in methods] + ["CBKF/OMC"]
    return "\n".join(["Table 1: MAE [mm] (every pose each method outputs, vs Diana ground truth)",
                      *_grid(head, body)])


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
