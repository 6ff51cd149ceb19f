"""Issue 18's acceptance goals, checked on ``make accuracy``'s summary of one twin profile.

The goals (measured over seeds 0-9 in the issue) for the filter :data:`GOAL_METHOD`:

* ``position_vs_cbkf`` (``paper`` profile): its mean position MAE over every task-seed at least 20 % below CBKF's,
  value = 1 - MAE_fullperc / MAE_cbkf, goal >= 0.20; ``ceiling`` = 1 - (best method's MAE contribution before the
  first Vega sample) / MAE_cbkf, what a filter would reach with no error after that sample and none better than
  every method before it (:func:`.accuracy.first_local_summary`);
* ``position_vs_omc`` (``spec`` profile): never more than 5 % above the OMC in any task, value = the largest
  per-task ratio of seed-mean MAEs MAE_fullperc / MAE_omc, goal <= 1.05;
* ``orientation_vs_single_sources`` (every profile): orientation MAE no worse than the better single source --
  the raw OMC (``omc``) or the raw local chain (``local``) -- in every task, value = the largest per-task ratio
  to the better one, goal <= 1.0;
* ``orientation_vs_single_sources_same_samples`` (every profile): the same goal on the same outputs. The raw local
  chain exists only while the Vega sees the tool, so its task figure covers those samples alone while every
  method's covers the whole task; here each task's outputs are split by :func:`.metrics.local_seen_mask`: where
  the local source sees the tool the method is compared with the better of the OMC (on those outputs) and the
  local chain, elsewhere with the OMC (the only single source there). Value = the largest of these per-task
  ratios of seed means, goal <= 1.0. The goal above is kept as it was, beside this one;
* ``nees_position_share95`` / ``nees_pose_share95`` (every profile): NEES consistent, the share of all outputs
  inside the chi2 95 % bound >= 0.90 (pose only when the method reports a fused orientation).

A goal whose figures are missing (the method not registered or not evaluated) is reported with ``ok`` None,
never as met.
"""

from __future__ import annotations

from typing import Any

import numpy as np

GOAL_METHOD = "fullperc"
SINGLE_SOURCES = ("omc", "local")


def _goal(name: str, profile: str, value: float | None, target: str, ok: bool | None, detail: str,
          method: str) -> dict[str, Any]:
    return {"goal": name, "profile": profile, "method": method, "value": value, "target": target, "ok": ok,
            "detail": detail}


def _mean(table: dict[str, dict[str, tuple[float, float]]], task: str, m: str) -> float:
    v = table.get(task, {}).get(m)
    return float("nan") if v is None else float(v[0])


def goal_checks(profile: str, s: dict[str, Any], method: str = GOAL_METHOD) -> list[dict[str, Any]]:
    """The goals that apply to ``profile``, computed from its :func:`.accuracy.summarize` summary ``s``."""
    t1 = s["table1_mae_mm"]
    tasks = [t for t in t1 if np.isfinite(_mean(t1, t, "omc"))]
    out = []
    if profile == "paper":
        f = np.array([_mean(t1, t, method) for t in tasks])
        c = np.array([_mean(t1, t, "cbkf") for t in tasks])
        if f.size and np.all(np.isfinite(f)) and np.all(np.isfinite(c)):
            red = 1.0 - float(f.mean() / c.mean())
            detail = f"mean MAE {f.mean():.3f} mm vs CBKF {c.mean():.3f} mm over {len(tasks)} tasks"
            best = (s.get("before_first_local") or {}).get("best_before_mm")
            g = _goal("position_vs_cbkf", profile, red, ">= 0.20", red >= 0.20, detail, method)
            if best:   # the floor of the first Vega sample (accuracy.first_local_summary)
                g["ceiling"] = 1.0 - float(best[0] / c.mean())
                g["detail"] += (f"; before the first Vega sample the best method already spends {best[0]:.3f} mm, so "
                                f"a filter perfect after it would reach {g['ceiling']:.3f}")
            out.append(g)
        else:
            out.append(_goal("position_vs_cbkf", profile, None, ">= 0.20", None, f"{method} not evaluated", method))
    if profile == "spec":
        ratios = {t: _mean(t1, t, method) / _mean(t1, t, "omc") for t in tasks}
        if ratios and all(np.isfinite(list(ratios.values()))):
            worst = max(ratios, key=lambda t: ratios[t])
            out.append(_goal("position_vs_omc", profile, ratios[worst], "<= 1.05", ratios[worst] <= 1.05,
                             f"worst task {worst}: {_mean(t1, worst, method):.3f} mm vs OMC "
                             f"{_mean(t1, worst, 'omc'):.3f} mm", method))
        else:
            out.append(_goal("position_vs_omc", profile, None, "<= 1.05", None, f"{method} not evaluated", method))
    ori = s.get("table1_orientation_deg") or {}
    ratios, better = {}, {}
    for t, per in ori.items():
        src = {k: per[k][0] for k in SINGLE_SOURCES if k in per and np.isfinite(per[k][0])}
        if method in per and np.isfinite(per[method][0]) and src:
            better[t] = min(src, key=lambda k: src[k])
            ratios[t] = per[method][0] / src[better[t]] if src[better[t]] > 0 else float("inf")
    if ratios:
        worst = max(ratios, key=lambda t: ratios[t])
        out.append(_goal("orientation_vs_single_sources", profile, ratios[worst], "<= 1.0", ratios[worst] <= 1.0,
                         f"worst task {worst}: {ori[worst][method][0]:.3f} deg vs {better[worst].upper()} "
                         f"{ori[worst][better[worst]][0]:.3f} deg", method))
    else:
        out.append(_goal("orientation_vs_single_sources", profile, None, "<= 1.0", None,
                         f"no orientation figures of {method} and a single source", method))
    out.append(_same_samples_goal(profile, s.get("orientation_by_local_deg") or {}, method))
    nees = (s.get("nees") or {}).get(method) or {}
    for kind in ("position", "pose"):
        v = nees.get(kind) or {}
        if v.get("n"):
            out.append(_goal(f"nees_{kind}_share95", profile, v["share_95"], ">= 0.90", v["share_95"] >= 0.90,
                             f"{v['n']} outputs, mean NEES {v['mean']:.3g} (dof {3 if kind == 'position' else 6})",
                             method))
        elif kind == "position":
            out.append(_goal("nees_position_share95", profile, None, ">= 0.90", None, f"{method} not evaluated",
                             method))
    return out


def _same_samples_goal(profile: str, split: dict[str, Any], method: str) -> dict[str, Any]:
    """``orientation_vs_single_sources_same_samples`` from the summary's ``orientation_by_local_deg``
    ({task: {method: {"seen"|"unseen": (mean, sd)}}})."""
    name = "orientation_vs_single_sources_same_samples"
    ratios: dict[tuple[str, str], tuple[float, str, float, float]] = {}
    for t, per in split.items():
        f = per.get(method) or {}
        for part, refs in (("seen", ("omc", "local")), ("unseen", ("omc",))):
            fm = (f.get(part) or (np.nan,))[0]
            src = {k: per[k][part][0] for k in refs if k in per and per[k].get(part) and np.isfinite(per[k][part][0])}
            if np.isfinite(fm) and src:
                best = min(src, key=lambda k: src[k])
                ratios[(t, part)] = (fm / src[best] if src[best] > 0 else float("inf"), best, fm, src[best])
    if not ratios:
        return _goal(name, profile, None, "<= 1.0", None, f"no split orientation figures of {method}", method)
    worst = max(ratios, key=lambda k: ratios[k][0])
    r, best, fm, ref = ratios[worst]
    where = "while the Vega sees the tool" if worst[1] == "seen" else "while it does not"
    return _goal(name, profile, r, "<= 1.0", r <= 1.0,
                 f"worst task {worst[0]} {where}: {fm:.3f} deg vs {best.upper()} {ref:.3f} deg", method)


def goal_lines(goals: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The goals as JSON lines (``goal_<name>``; ``ok`` true / false / null)."""
    return [{"name": f"goal_{g['goal']}_{g['method']}", "value": None if g["value"] is None else round(g["value"], 4),
             "unit": "ratio" if "share" not in g["goal"] else "fraction", "target": g["target"], "ok": g["ok"],
             **({"ceiling": round(g["ceiling"], 4)} if g.get("ceiling") is not None else {})}
            for g in goals]


def format_goals(goals: list[dict[str, Any]]) -> list[str]:
    """Human lines: one per goal, MET / MISSED / n/a, value, target and what it was computed from."""
    if not goals:
        return []
    out = [f"Issue 18 goals for {goals[0]['method'].upper()}:"]
    for g in goals:
        state = {True: "MET", False: "MISSED", None: "n/a"}[g["ok"]]
        val = "-" if g["value"] is None else f"{g['value']:.3f}"
        out.append(f"  {state:<6} {g['goal']:<43} {val:>7} (goal {g['target']}): {g['detail']}")
    return out
