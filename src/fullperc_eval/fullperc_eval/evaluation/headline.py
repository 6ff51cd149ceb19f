"""What a newcomer reads first in a report (issue 17 item 4): the regions defined, the OMC's hops, one paragraph.

Everything here is computed from the evaluation's own figures (:mod:`.metrics`), never typed in: the best method
and its margin over the OMC come from ``mae_mm``, the time in each region from the labelled true path, the hop
times from the compensated filters' hop test and the hop sizes from the OMC's true error around them, and the
region definitions quote the margin threshold of the layout the labels were made with.
"""

from __future__ import annotations

from typing import Any

import numpy as np

REGION_ORDER = ("BVV", "GVV", "PVV")
HOP_METHODS = ("cbkf", "bkf")   # filters with the paper's hop test, the first present is asked
HOP_MERGE_S = 0.5               # hop flags closer than this are one hop (the test may fire on consecutive frames)
HOP_WINDOW_S = 0.5              # the OMC error is compared over this long before and after a hop


def region_definitions(threshold_deg: float) -> dict[str, str]:
    """BVV / GVV / PVV as the labels of this run were made (paper §4.2, :mod:`fullperc_fusion.margin.view_margin`)."""
    t = f"{threshold_deg:g}"
    return {"BVV": "best view volume: inside the local tracker's (Vega's) measurement volume with a clear line of "
                   "sight from it -- the fusion has the precise local measurement",
            "GVV": f"good view volume: outside the BVV, view margin of the OMC cameras >= {t} deg -- enough camera "
                   "pairs see the tool from well-separated directions",
            "PVV": f"poor view volume: outside the BVV, view margin < {t} deg -- few or badly placed camera pairs; "
                   "the OMC error grows and can hop"}


def hop_events(outputs: dict[str, dict[str, np.ndarray]], omc_err: np.ndarray | None, t0_ns: int,
               merge_s: float = HOP_MERGE_S, window_s: float = HOP_WINDOW_S) -> list[dict[str, Any]]:
    """The OMC's hops in a run: time [s from t0_ns] where the hop test of the first of :data:`HOP_METHODS` fired
    (flags within ``merge_s`` merged), and the size [mm] of the jump of the OMC's true error vector: median
    over ``window_s`` after minus median over ``window_s`` before (``omc_err``: (N, 3) [mm] at the ``omc``
    outputs, NaN where no truth; None: no sizes)."""
    name = next((m for m in HOP_METHODS if m in outputs and outputs[m]["t_ns"].size), None)
    if name is None:
        return []
    o = outputs[name]
    flags = o["t_ns"][np.asarray(o["hop"], bool)]
    events: list[int] = []
    for t in flags.tolist():
        if not events or t - events[-1] > merge_s * 1e9:
            events.append(int(t))
    out = []
    for t in events:
        e = {"t_s": (t - t0_ns) * 1e-9, "detected_by": name, "jump_mm": None}
        if omc_err is not None and "omc" in outputs:
            to = outputs["omc"]["t_ns"]
            w = int(window_s * 1e9)
            before = omc_err[(to >= t - w) & (to < t)]
            after = omc_err[(to >= t) & (to <= t + w)]
            before, after = before[np.all(np.isfinite(before), 1)], after[np.all(np.isfinite(after), 1)]
            if len(before) and len(after):
                e["jump_mm"] = float(np.linalg.norm(np.median(after, 0) - np.median(before, 0)))
        out.append(e)
    return out


def _pct(a: float, b: float) -> str:
    return f"{100.0 * abs(a - b) / b:.0f} %"


def headline(r: dict[str, Any], target: str = "tool") -> str:
    """One paragraph on an evaluation result: best method, by how much vs the OMC, hops, time per region."""
    mae = {m: v for m, v in r["mae_mm"].items() if v is not None}
    parts = []
    if mae:
        best = min(mae, key=lambda m: mae[m])
        s = f"Best position accuracy in this run ({r['task']}, {r['duration_s']:.1f} s): {best.upper()}, MAE " \
            f"{mae[best]:.2f} mm"
        if "omc" in mae and best != "omc":
            s += f", {_pct(mae[best], mae['omc'])} below the raw OMC ({mae['omc']:.2f} mm)"
        elif best == "omc":
            s += " -- no fusion method beat the raw OMC in this run"
        ori_all = r.get("orientation_mae_deg") or {}
        ori = {m: v for m, v in ori_all.items() if v is not None and m in r["mae_mm"]}
        if ori:
            ob = min(ori, key=lambda m: ori[m])
            s += f"; best orientation: {ob.upper()}, {ori[ob]:.3f} deg"
            if ori_all.get("local") is not None:
                s += f" (the raw local chain, only where the Vega sees the tool: {ori_all['local']:.3f} deg)"
        parts.append(s + ".")
    hops = r.get("omc_hops") or []
    if hops:
        desc = ", ".join(f"{h['t_s']:.1f} s" + (f" ({h['jump_mm']:.1f} mm)" if h.get("jump_mm") is not None else "")
                         for h in hops)
        parts.append(f"The OMC hopped {len(hops)} time{'s' if len(hops) != 1 else ''} (hop test of "
                     f"{hops[0]['detected_by'].upper()}; size = jump of the OMC's true error): {desc}.")
    else:
        parts.append("The hop test detected no OMC hop.")
    reg = r.get("regions", {})
    sec = reg.get("seconds") or {}
    if sec:
        parts.append(f"The {target} spent " + ", ".join(f"{sec.get(k, 0.0):.1f} s in {k}" for k in REGION_ORDER)
                     + f" (path {reg.get('order', '?')}).")
    return " ".join(parts)
