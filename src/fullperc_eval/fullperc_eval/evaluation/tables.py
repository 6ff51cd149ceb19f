"""Text tables and JSON of evaluation results: Table 1 (MAE per method), Table 2 (the B->P segment)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .config import METHODS


def _fmt(v) -> str:
    return "   -  " if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:6.2f}"


def format_table1(rows: list[dict[str, Any]], methods=METHODS) -> str:
    head = f"{'task':<10}" + "".join(f"{m.upper():>7}" for m in methods) + "   CBKF/OMC"
    lines = ["Table 1: MAE [mm] (every pose each method outputs, vs Diana ground truth)", head]
    for r in rows:
        mae = r["mae_mm"]
        ratio = (mae["cbkf"] / mae["omc"]) if mae.get("cbkf") and mae.get("omc") else None
        lines.append(f"{r['task']:<10}" + "".join(f" {_fmt(mae.get(m))}" for m in methods)
                     + (f"   {ratio:9.2f}" if ratio is not None else ""))
    return "\n".join(lines)


def format_table2(r: dict[str, Any], methods=METHODS) -> str:
    bp = r.get("b_to_p")
    if not bp:
        return f"Table 2 ({r['task']}): no B->P segment on this path (regions {r['regions']['order']})"
    lines = [f"Table 2 ({r['task']}): B->P segment {bp['t0_s']:.2f}-{bp['t1_s']:.2f} s, error [mm]",
             f"{'value':<10}" + "".join(f"{m.upper():>7}" for m in methods)]
    for key in ("max_mm", "median_mm"):
        lines.append(f"{key[:-3]:<10}" + "".join(f" {_fmt(bp[key].get(m))}" for m in methods))
    return "\n".join(lines)


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
