"""Issue 41's acceptance checks, per tracked target and twin profile, on ``make accuracy``'s task-seed rows.

Why a module of their own: :mod:`.accuracy_goals` checks issue 18's goals of the arm-held tool on a profile's
summary (seed means per task). These checks must hold for *every* target the bags hold (the twin's hand-held
``instrument`` too, and any target with ``/sim/truth/<target>``), and one of them is about single task-seeds, so
they read the rows of one (profile, target) -- the per-task-seed figures ``accuracy.run_seed`` writes -- and the
NEES pooled over them. Nothing here reads a bag or knows a figure: the checks are pure functions of their input.

The checks, for :data:`GOAL_METHOD` (``fullperc``) against the raw OMC (``omc``) and the paper's best filter
(``cbkf``):

a. ``mae_vs_omc_every_task_seed``: in every task-seed MAE_fullperc / MAE_omc <= 1.0. Value = the worst ratio,
   ``where`` = its task and seed; the detail counts the task-seeds within the bound. One bad run is a failure:
   the filter must never make the tracking worse than the camera it fuses.
b. ``mae_vs_omc_GVV`` and ``mae_vs_omc_PVV``: per region of the true path outside the Vega's volume (GVV: the
   OMC's camera pairs see the target well, PVV: poorly; docs/evaluation.md), where only the OMC measures:
   fullperc's region MAE averaged over the task-seeds divided by the OMC's averaged over the same task-seeds
   <= 1.0. A ratio of means, not a mean of ratios: a task-seed where the OMC happens to be very good in a region (a
   short pass, a small denominator) would dominate a mean of ratios; the means compare the two methods' average
   error there in mm, as Table 1 does. The mean of the per-task-seed ratios is given in the detail.
c. ``mae_vs_cbkf``: 1 - mean MAE_fullperc / mean MAE_cbkf over the task-seeds >= 0 (fullperc no worse than CBKF);
   for the tool in the ``paper`` profile >= 0.10 (:data:`CBKF_REDUCTION`: the profile the paper's figures come from,
   on the target the paper tracks).
d. ``nees_position_share95`` / ``nees_pose_share95`` per published filter (:func:`published_filters`: every method
   with NEES figures but the raw OMC pass-through, whose covariance is the sensor's, not a filter's): the share of
   its outputs inside the chi2 95 % bound, pooled over every output of every task-seed, >= 0.90; the pose only for
   filters that fuse the orientation (n > 0). ``nees_share95_filters`` says which filters meet it (both kinds
   they report): value = their share of the filters, ok = all of them.

e. ``motion_auto_vs_best_preset``: fullperc with the shipped ``motion: auto`` (fullperc_fusion/filters/motion.py)
   against the same filter with each motion preset on the same task-seeds (``motion_presets_mae_mm`` of the rows,
   :func:`.accuracy_targets.preset_maes`): mean MAE of auto / mean MAE of the best preset <= 1.05. Value = that
   ratio, the detail every preset's mean.

Each check is a dict ``{"goal", "profile", "target" (the tracked target), "method", "value", "bound" (e.g.
"<= 1.0"), "ok", "margin", "detail"}`` (+ ``"where"`` for a), + ``"meet"``/``"miss"`` for the filter list).
``margin`` is by how much: bound - value for an upper bound, value - bound for a lower one, so > 0 passes by that
much and < 0 misses by it (in the value's unit). A check whose figures are missing has ``ok`` None (never met by
default) and ``value``/``margin`` None -- except a region check of a target whose true path never enters that
region in any task-seed (the patient reference, always inside the Vega's volume): nothing to check, ``ok`` True,
``value`` None, the detail says so.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .accuracy_goals import GOAL_METHOD

REFERENCE = "omc"              # the single source the filter must never be worse than
BASELINE = "cbkf"              # the paper's best filter
GOAL_REGIONS = ("GVV", "PVV")  # where the OTS and the OMC disagree or the OMC is alone: the checks of b)
NEES_SHARE = 0.90              # d) share of outputs inside the chi2 95 % bound
CBKF_REDUCTION = {("paper", "tool"): 0.10}   # c) (profile, target) -> least 1 - MAE_f / MAE_cbkf; others 0.0
NOT_FILTERS = ("omc",)         # raw pass-throughs: their covariance is the sensor's
AUTO_VS_PRESET = 1.05          # e) motion auto's mean MAE at most this times the best preset's


def _check(goal: str, profile: str, target: str, method: str, value: float | None, bound: str, detail: str,
           **extra: Any) -> dict[str, Any]:
    """One check record; ``ok`` and ``margin`` follow from ``value`` and ``bound`` ("<= x" or ">= x")."""
    op, lim = bound.split()
    if value is None or not np.isfinite(value):
        ok, margin, value = None, None, None
    else:
        margin = float(lim) - value if op == "<=" else value - float(lim)
        ok = bool(margin >= 0)
    return {"goal": goal, "profile": profile, "target": target, "method": method, "value": value, "bound": bound,
            "ok": ok, "margin": margin, "detail": detail, **extra}


def _mae(r: dict[str, Any], m: str) -> float | None:
    v = (r.get("mae_mm") or {}).get(m)
    return None if v is None or not np.isfinite(v) else float(v)


def every_task_seed(profile: str, target: str, rows: list[dict[str, Any]],
                    method: str = GOAL_METHOD) -> dict[str, Any]:
    """a) The worst task-seed ratio MAE_method / MAE_omc, <= 1.0."""
    ratios = [(_mae(r, method) / _mae(r, REFERENCE), r) for r in rows
              if _mae(r, method) is not None and _mae(r, REFERENCE)]
    name = "mae_vs_omc_every_task_seed"
    if not ratios:
        return _check(name, profile, target, method, None, "<= 1.0", f"no task-seed with {method} and OMC figures")
    worst, r = max(ratios, key=lambda x: x[0])
    inside = sum(x <= 1.0 for x, _ in ratios)
    return _check(name, profile, target, method, worst, "<= 1.0",
                  f"worst {r['task']} seed {r['seed']}: {_mae(r, method):.3f} mm vs OMC {_mae(r, REFERENCE):.3f} mm; "
                  f"{inside} of {len(ratios)} task-seeds within", where={"task": r["task"], "seed": r["seed"]})


def region_vs_omc(profile: str, target: str, rows: list[dict[str, Any]], region: str,
                  method: str = GOAL_METHOD) -> dict[str, Any]:
    """b) Mean over task-seeds of the method's MAE in ``region`` / the OMC's mean over the same task-seeds, <= 1.0."""
    pairs = []
    for r in rows:
        per = (r.get("mae_by_region_mm") or {}).get(region) or {}
        f, o = per.get(method), per.get(REFERENCE)
        if f is not None and o is not None and np.isfinite(f) and np.isfinite(o):
            pairs.append((float(f), float(o)))
    name = f"mae_vs_omc_{region}"
    if rows and not any(((r.get("mae_by_region_mm") or {}).get(region) or {}).get(REFERENCE) is not None for r in rows):
        c = _check(name, profile, target, method, None, "<= 1.0",
                   f"the target is never in {region} (no task-seed's true path enters it): nothing to check")
        return {**c, "ok": True}   # not applicable (a marker fixed where the Vega always sees it)
    if not pairs or not sum(o for _, o in pairs):
        return _check(name, profile, target, method, None, "<= 1.0", f"no task-seed with {method} figures in {region}")
    f, o = np.array(pairs).T
    by_seed = f[o > 0] / o[o > 0]
    return _check(name, profile, target, method, float(f.mean() / o.mean()), "<= 1.0",
                  f"{region}: {f.mean():.3f} mm vs OMC {o.mean():.3f} mm over {len(pairs)} task-seeds "
                  f"(mean of the per-task-seed ratios {by_seed.mean():.3f})")


def vs_cbkf(profile: str, target: str, rows: list[dict[str, Any]], method: str = GOAL_METHOD) -> dict[str, Any]:
    """c) 1 - mean MAE_method / mean MAE_cbkf over the task-seeds that have both, >= the (profile, target)'s least
    reduction (:data:`CBKF_REDUCTION`, else 0: no worse than CBKF)."""
    least = CBKF_REDUCTION.get((profile, target), 0.0)
    pairs = [(_mae(r, method), _mae(r, BASELINE)) for r in rows
             if _mae(r, method) is not None and _mae(r, BASELINE) is not None]
    bound = f">= {least:.2f}"
    if not pairs or not sum(c for _, c in pairs):
        return _check("mae_vs_cbkf", profile, target, method, None, bound, f"no task-seed with {method} and CBKF")
    f, c = np.array(pairs).T
    return _check("mae_vs_cbkf", profile, target, method, 1.0 - float(f.mean() / c.mean()), bound,
                  f"mean MAE {f.mean():.3f} mm vs CBKF {c.mean():.3f} mm over {len(pairs)} task-seeds "
                  f"(ratio {f.mean() / c.mean():.3f})")


def published_filters(nees: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """The methods of a pooled NEES table (:func:`.accuracy_targets.pooled_nees`) that are filters: every one with
    position NEES figures but the raw pass-throughs (:data:`NOT_FILTERS`)."""
    return [m for m, k in nees.items() if m not in NOT_FILTERS and (k.get("position") or {}).get("n")]


def nees_checks(profile: str, target: str, nees: dict[str, dict[str, dict[str, Any]]]) -> list[dict[str, Any]]:
    """d) Per published filter and kind the pooled share inside the 95 % bound >= 0.90, then which filters meet it."""
    out, meet, miss = [], [], []
    bound = f">= {NEES_SHARE:.2f}"
    for m in published_filters(nees):
        ok = True
        for kind, dof in (("position", 3), ("pose", 6)):
            v = nees[m].get(kind) or {}
            if not v.get("n"):
                continue
            c = _check(f"nees_{kind}_share95", profile, target, m, v.get("share_95"), bound,
                       f"{v['n']} outputs, mean NEES {v['mean']:.3g} (dof {dof})")
            ok = ok and bool(c["ok"])
            out.append(c)
        (meet if ok else miss).append(m)
    filters = meet + miss
    share = len(meet) / len(filters) if filters else None
    detail = (f"meet: {', '.join(meet) or 'none'}; miss: {', '.join(miss) or 'none'}" if filters
              else "no filter with NEES figures")
    out.append(_check("nees_share95_filters", profile, target, "all", share, ">= 1.0", detail, meet=meet, miss=miss))
    return out


def auto_vs_presets(profile: str, target: str, rows: list[dict[str, Any]], method: str = GOAL_METHOD) -> dict[str, Any]:
    """e) mean MAE of ``method`` (motion auto) over the mean MAE of its best motion preset, on the task-seeds that have
    every preset's figure, <= AUTO_VS_PRESET."""
    bound = f"<= {AUTO_VS_PRESET:.2f}"
    have = [r for r in rows if r.get("motion_presets_mae_mm") and _mae(r, method) is not None]
    names = sorted({p for r in have for p in r["motion_presets_mae_mm"]})
    have = [r for r in have if all(r["motion_presets_mae_mm"].get(p) is not None for p in names)]
    if not have or not names:
        return _check("motion_auto_vs_best_preset", profile, target, method, None, bound, "no preset figures")
    auto = float(np.mean([_mae(r, method) for r in have]))
    means = {p: float(np.mean([r["motion_presets_mae_mm"][p] for r in have])) for p in names}
    best = min(means, key=means.get)
    return _check("motion_auto_vs_best_preset", profile, target, method, auto / means[best], bound,
                  f"auto {auto:.3f} mm vs " + ", ".join(f"{p} {v:.3f}" for p, v in means.items())
                  + f" mm over {len(have)} task-seeds (best: {best})")


def target_goal_checks(profile: str, target: str, rows: list[dict[str, Any]],
                       nees: dict[str, dict[str, dict[str, Any]]], method: str = GOAL_METHOD) -> list[dict[str, Any]]:
    """Every check a)-e) of one (profile, target): its task-seed ``rows`` and their pooled ``nees``."""
    return [every_task_seed(profile, target, rows, method),
            *(region_vs_omc(profile, target, rows, reg, method) for reg in GOAL_REGIONS),
            vs_cbkf(profile, target, rows, method), auto_vs_presets(profile, target, rows, method),
            *nees_checks(profile, target, nees)]


def _r4(v: float | None) -> float | None:
    return None if v is None else round(float(v), 4)


def target_goal_lines(checks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The checks as JSON lines: ``name`` = ``goal41_<goal>_<method>_<target>``, value, bound, ok, margin."""
    return [{"name": f"goal41_{c['goal']}_{c['method']}_{c['target']}", "value": _r4(c["value"]),
             "unit": "fraction" if "share" in c["goal"] else "ratio", "bound": c["bound"], "ok": c["ok"],
             "margin": _r4(c["margin"]), "target": c["target"],
             **({"where": c["where"]} if c.get("where") else {}),
             **({"meet": c["meet"], "miss": c["miss"]} if "meet" in c else {})} for c in checks]


def format_target_goals(checks: list[dict[str, Any]]) -> list[str]:
    """A human table: one line per check, PASS / FAIL / n/a, value, bound, margin and what it was computed from."""
    if not checks:
        return []
    state = {True: "PASS", False: "FAIL", None: "n/a"}
    head = ["target", "check", "method", "", "value", "bound", "margin", "from"]
    body = [[c["target"], c["goal"], c["method"].upper(), state[c["ok"]],
             "-" if c["value"] is None else f"{c['value']:.3f}", c["bound"],
             "-" if c["margin"] is None else f"{c['margin']:+.3f}", c["detail"]] for c in checks]
    widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]
    right = {4, 6}   # the figures; the labels and the text left-aligned

    def line(cells: list[str]) -> str:
        return "  ".join(c.rjust(w) if i in right else c.ljust(w)
                         for i, (c, w) in enumerate(zip(cells, widths, strict=True))).rstrip()

    return [f"Issue 41 acceptance checks, profile {checks[0]['profile']} (margin > 0: passed by, < 0: missed by):",
            *(line(r) for r in [head, *body])]
