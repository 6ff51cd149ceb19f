"""``make accuracy`` per tracked target: the figures of every target the bags hold, beside the tool's tables.

The twin's bags hold the arm-held ``tool`` (the paper's target: truth from the Diana's joints) and targets without a
robot, e.g. the hand-held ``instrument`` (truth ``/sim/truth/<target>``, :func:`.ground_truth.target_truth`).
:func:`task_targets` lists them per bag the way ``evaluate_all --targets all`` does (:func:`.evaluate_all.bag_targets`),
so a future target with a truth topic is evaluated without a change here. Each task-seed row carries its
``"target"`` (:func:`task_row`); the tool's rows keep every former key, and :func:`.accuracy.summarize`, its JSON
lines and its tables stay the tool's alone. Per (profile, target) this module adds (:func:`target_summary`):

* ``table1_mae_mm``: MAE per task and method, mean ± sd over seeds (Table 1 of that target);
* ``mae_by_region_mm``: MAE per region (BVV/GVV/PVV) and method, mean ± sd over task-seeds, and
  ``region_over_omc``: each method's mean over the OMC's mean on the same task-seeds (the figure the issue-41
  region check reads, :mod:`.target_goals`);
* ``nees``: NEES per method pooled over every output of every task-seed (:func:`pooled_nees`).

It also holds the helpers :mod:`.accuracy` shares with it (mean ± sd, pooled NEES, the NEES and mean ± sd tables):
they live here so that this module needs nothing from :mod:`.accuracy`, which imports it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .config import METHODS
from .evaluate_all import TASK_ORDER, bag_targets
from .ground_truth import ARM_TARGET, TRUTH_PREFIX
from .tables import _grid
from .target_goals import REFERENCE, format_target_goals

REGIONS = ("BVV", "GVV", "PVV")


# ------------------------------------------------------------------------------ shared with accuracy.py
def _ms(v: list[float]) -> tuple[float, float]:
    a = np.asarray([x for x in v if x is not None], float)
    return (float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0) if a.size else (float("nan"), float("nan"))


def _methods(rows: list[dict[str, Any]], key: str = "mae_mm") -> list[str]:
    """The methods the rows carry under ``key``, in METHODS order (rows of an older run may lack a new filter)."""
    have = {m for r in rows for m in (r.get(key) or {})}
    return [m for m in METHODS if m in have] + sorted(have - set(METHODS))


def pooled_nees(rows: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, float | int | None]]]:
    """Per method and kind (position / pose): the share inside the 95 % bound and the mean NEES over every output
    of every task-seed (each task-seed weighted by its number of outputs)."""
    out: dict[str, dict[str, dict[str, float | int | None]]] = {}
    for m in _methods(rows, "nees"):
        out[m] = {}
        for kind in ("position", "pose"):
            parts = [(r["nees"][m][kind]) for r in rows if (r.get("nees") or {}).get(m)]
            parts = [x for x in parts if x and x.get("n")]
            n = sum(x["n"] for x in parts)
            out[m][kind] = {"n": n, "share_95": sum(x["share_95"] * x["n"] for x in parts) / n if n else None,
                            "mean": sum(x["mean"] * x["n"] for x in parts) / n if n else None}
    return out


def _ms_table(title: str, table: dict[str, dict[str, tuple[float, float]]], digits: int = 2) -> list[str]:
    """A mean ± sd table, every column padded to its widest cell (figures right-aligned)."""
    cols = list(dict.fromkeys(m for per in table.values() for m in per))
    body = [[t] + [("-" if not np.isfinite(per[m][0]) else f"{per[m][0]:.{digits}f} ± {per[m][1]:.{digits}f}")
                   if m in per else "-" for m in cols] for t, per in table.items()]
    return [title, *_grid(["task"] + [m.upper() for m in cols], body)]


def format_nees(s: dict[str, Any]) -> list[str]:
    nees = s.get("nees") or {}
    body = []
    for kind, dof in (("position", 3), ("pose", 6)):
        have = [m for m in nees if nees[m][kind]["n"]]
        if have:
            body.append([f"{kind} (dof {dof})"] + [f"{100 * nees[m][kind]['share_95']:.1f}%/{nees[m][kind]['mean']:.3g}"
                                                  if m in have else "-" for m in nees])
    if not body:
        return []
    return ["NEES pooled over every output: share inside the chi2 95 % bound / mean (honest: 95 % / dof)",
            *_grid([""] + [m.upper() for m in nees], body)]


# ------------------------------------------------------------------------------------- rows per target
def task_targets(bag: Path) -> list[str]:
    """The targets to evaluate in one bag: the tool and every target with simulator truth in it."""
    return bag_targets(bag, ["all"])


def task_row(task: str, seed: int, profile: str, target: str, r: dict[str, Any]) -> dict[str, Any]:
    """The per-task-seed row of one target's :func:`.metrics.evaluate_bag` result ``r`` (the figures accuracy.json
    keeps, in the order it always kept the tool's, then ``target``)."""
    return {"task": task, "seed": seed, "profile": profile, "mae_mm": r["mae_mm"],
            "mae_by_region_mm": r["mae_by_region_mm"], "b_to_p": r["b_to_p"],
            "orientation_mae_deg": r.get("orientation_mae_deg"),
            "orientation_by_region_deg": r.get("orientation_by_region_deg"),
            "orientation_by_local_deg": r.get("orientation_by_local_deg"),
            "before_first_local": r.get("before_first_local"),
            "nees": {m: {k: {x: v[k][x] for x in ("n", "share_95", "mean")} for k in ("position", "pose")}
                     for m, v in (r.get("nees") or {}).items()},
            "target": target}


def preset_maes(bag: Path, fusion_config: str | None, target: str, evaluate_bag) -> dict[str, float]:
    """fullperc's MAE [mm] on one bag with each motion preset instead of the configured motion (the target's motion
    set to the preset, nothing else changed): the figures :func:`.target_goals.auto_vs_presets` compares ``motion:
    auto`` with. ``evaluate_bag`` is :func:`.metrics.evaluate_bag` (passed in: this module stays light)."""
    from dataclasses import replace

    from fullperc_fusion.filters.motion import PRESETS, with_preset

    from .config import replay_config

    config, _ = replay_config(fusion_config, target)
    out = {}
    for name in PRESETS:
        cfg = replace(config, filters=("omc", "fullperc"), params=with_preset(config.params, name))
        out[name] = evaluate_bag(bag, target=target, config=cfg, progress=False).result["mae_mm"]["fullperc"]
    return out


def target_of(row: dict[str, Any]) -> str:
    """A row's target; rows without one (a run before targets were evaluated) are the tool's."""
    return row.get("target") or ARM_TARGET


def split_targets(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """The rows per target, in their order: the tool first, the others by name."""
    out: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(target_of(r), []).append(r)
    return {t: out[t] for t in sorted(out, key=lambda t: (t != ARM_TARGET, t))}


# --------------------------------------------------------------------------------------------- summary
def region_table(rows: list[dict[str, Any]]) -> tuple[dict[str, dict[str, tuple[float, float]]],
                                                       dict[str, dict[str, float | None]], dict[str, int]]:
    """Per region and method the MAE mean ± sd over the task-seeds that have the region; per region and method its
    mean over the OMC's mean on the task-seeds that have both (None without OMC figures); per region how many
    task-seeds have it."""
    ms = _methods(rows)
    table: dict[str, dict[str, tuple[float, float]]] = {}
    ratio: dict[str, dict[str, float | None]] = {}
    count: dict[str, int] = {}
    for reg in REGIONS:
        per = [(r.get("mae_by_region_mm") or {}).get(reg) or {} for r in rows]
        per = [p for p in per if any(v is not None for v in p.values())]
        count[reg] = len(per)
        table[reg] = {m: _ms([p.get(m) for p in per]) for m in ms}
        ratio[reg] = {}
        for m in ms:
            both = [(p[m], p[REFERENCE]) for p in per if p.get(m) is not None and p.get(REFERENCE) is not None]
            o = sum(x[1] for x in both)
            ratio[reg][m] = sum(x[0] for x in both) / o if both and o else None
    return table, ratio, count


def target_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One (profile, target)'s figures: Table 1 (mean ± sd over seeds), MAE by region (and over the OMC), pooled
    NEES; ``tasks`` in the paper's order, then any other task by name."""
    ms = _methods(rows)
    tasks = [t for t in TASK_ORDER if any(r["task"] == t for r in rows)]
    tasks += sorted({r["task"] for r in rows} - set(tasks))
    t1 = {t: {m: _ms([r["mae_mm"].get(m) for r in rows if r["task"] == t]) for m in ms} for t in tasks}
    by_region, over_omc, count = region_table(rows)
    return {"n_task_seeds": len(rows), "seeds": sorted({r["seed"] for r in rows}), "table1_mae_mm": t1,
            "mae_by_region_mm": by_region, "region_over_omc": over_omc, "region_n": count,
            "nees": pooled_nees(rows)}


# ------------------------------------------------------------------------------------------------ output
def _r4(v: float | None) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), 4)


def target_json_lines(profile: str, target: str, ts: dict[str, Any]) -> list[dict[str, Any]]:
    """One (profile, target)'s lines, every one named ``<target>_...`` and carrying ``target``: its Table 1 and
    pooled NEES (not for the tool: the tool's own lines have them), and its MAE by region for every target."""
    out = []
    if target != ARM_TARGET:
        for t, per in ts["table1_mae_mm"].items():
            for m, (mu, sd) in per.items():
                out.append({"name": f"{target}_mae_{m}_{t}", "value": _r4(mu), "sd": _r4(sd), "unit": "mm"})
        for m, kinds in ts["nees"].items():
            for kind, v in kinds.items():
                if v["n"]:
                    out.append({"name": f"{target}_nees_{kind}_share95_{m}", "value": _r4(v["share_95"]),
                                "unit": "fraction", "n": v["n"]})
                    out.append({"name": f"{target}_nees_{kind}_mean_{m}", "value": _r4(v["mean"]), "unit": "nees",
                                "n": v["n"]})
    for reg, per in ts["mae_by_region_mm"].items():
        for m, (mu, sd) in per.items():
            out.append({"name": f"{target}_region_mae_{m}_{reg}", "value": _r4(mu), "sd": _r4(sd), "unit": "mm",
                        "over_omc": _r4(ts["region_over_omc"][reg].get(m)), "n": ts["region_n"][reg]})
    for rec in out:
        rec.update(target=target, profile=profile, seeds=len(ts["seeds"]))
    return out


def format_regions(ts: dict[str, Any]) -> list[str]:
    """MAE by region: mean ± sd over the task-seeds in the region, and (in brackets) over the OMC's mean."""
    by_region = ts["mae_by_region_mm"]
    cols = list(dict.fromkeys(m for per in by_region.values() for m in per))
    body = []
    for reg, per in by_region.items():
        if not ts["region_n"][reg]:
            continue
        cells = []
        for m in cols:
            mu, sd = per[m]
            q = ts["region_over_omc"][reg].get(m)
            cells.append("-" if not np.isfinite(mu) else f"{mu:.2f} ± {sd:.2f}" + (f" ({q:.2f})" if q else ""))
        body.append([f"{reg} ({ts['region_n'][reg]})"] + cells)
    return ["MAE [mm] by region, mean ± sd over the task-seeds in it (their number), (method mean / OMC mean):",
            *_grid(["region"] + [m.upper() for m in cols], body)]


def format_target(profile: str, target: str, ts: dict[str, Any], checks: list[dict[str, Any]]) -> str:
    """The human block of one (profile, target): Table 1 and pooled NEES (others than the tool, whose tables come
    before), MAE by region and the issue-41 checks."""
    seeds = ts["seeds"]
    truth = "the Diana's joints" if target == ARM_TARGET else f"{TRUTH_PREFIX}/{target}"
    lines = [f"profile {profile}, target {target} (truth: {truth}), {len(seeds)} seeds, {ts['n_task_seeds']} "
             "task-seeds"]
    if target != ARM_TARGET:
        lines += _ms_table("Table 1, MAE [mm] mean ± sd over seeds:", ts["table1_mae_mm"])
        nees = format_nees(ts)
        if nees:
            lines += nees
    lines += format_regions(ts)
    if checks:
        lines += format_target_goals(checks)
    return "\n".join(lines)
