"""Render ``docs/results.md`` and the README's results block from the evaluation's JSON files.

    python scripts/results_page.py            # (re)write docs/results.md and the README block
    python scripts/results_page.py --check    # exit 1, naming the file, when either differs from what it would write

Inputs, as the evaluation writes them (nothing is simulated or evaluated here):

* ``bags/accuracy.json`` -- ``make accuracy`` (:mod:`fullperc_eval.evaluation.accuracy`): Table 1 as mean ± sd
  over seeds, ordering shares, the CBKF/OMC distribution, Table 2, orientation, pooled NEES, the MAE split at the
  first Vega sample, the goal checks of the ``fullperc`` filter and (when there) every tracked target's figures;
* ``bags/<profile>/eval.json`` -- ``make eval`` (:mod:`fullperc_eval.evaluation.evaluate_all`) on the committed
  seed-0 sample bags: the same tables per task, the paper's own Tables 1 and 2 and the ordering comparison, and the
  hand-held instrument's rows when the JSON has them (``--targets all``).

Every table is headed by the command that produced its JSON, reconstructed from what the JSON records (seeds,
profiles, fusion configuration, noise model). Why generated: a figure typed into a page goes stale the day the
filter changes; ``test/test_docs.py`` fails when the committed page differs from what this script renders from the
committed JSON, so the JSON and the page move together. The README quotes no figure of its own: its block between
``<!-- results:begin -->`` and ``<!-- results:end -->`` is rendered here too.

Stdlib only: the page can be rendered without the workspace built.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PAGE = Path("docs/results.md")
README = Path("README.md")
ACCURACY = Path("bags/accuracy.json")
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
TASKS = ("G-B-P", "P-G-B", "P-G-B-P", "P-B-G", "B-G-P", "P-B-G-P")
LABEL = {"omc": "OMC", "kf": "KF", "bkf": "BKF", "ckf": "CKF", "cbkf": "CBKF", "local": "LOCAL"}
REGIONS = ("BVV", "GVV", "PVV")
GOAL_TEXT = {   # what each goal of accuracy_goals.py asks, in a reader's words
    "position_vs_cbkf": "position: mean MAE at least 20 % below CBKF's (value: 1 − fullperc/CBKF)",
    "position_vs_omc": "position: no task more than 5 % above the OMC (value: worst fullperc/OMC)",
    "orientation_vs_single_sources": "orientation: no task worse than the better single source's task figure",
    "orientation_vs_single_sources_same_samples": "orientation, on the same outputs: no task worse than the better "
                                                  "single source (value: worst ratio)",
    "nees_position_share95": "position covariance: ≥ 90 % of outputs inside the χ² 95 % bound",
    "nees_pose_share95": "pose covariance: ≥ 90 % of outputs inside the χ² 95 % bound",
}
STATE = {True: "met", False: "**missed**", None: "n/a"}


# ------------------------------------------------------------------------------------------------ formatting
def finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def num(v: Any, digits: int = 2) -> str:
    return f"{v:.{digits}f}" if finite(v) else "–"


def pm(pair: Any, digits: int = 2) -> str:
    """``mean ± sd`` of a (mean, sd) pair as accuracy.json stores it; '–' without a finite mean."""
    if not pair or not finite(pair[0]):
        return "–"
    return f"{pair[0]:.{digits}f} ± {pair[1]:.{digits}f}" if finite(pair[1]) else num(pair[0], digits)


def pct(v: Any, digits: int = 0) -> str:
    return f"{100 * v:.{digits}f} %" if finite(v) else "–"


def label(m: str) -> str:
    return LABEL.get(m, f"`{m}`")


def table(head: list[str], rows: list[list[str]], left: int = 1) -> list[str]:
    """A Markdown table: the first ``left`` columns (labels, text) left-aligned, the figures right-aligned."""
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * left + "---:|" * (len(head) - left)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out + [""]


def methods_of(per_task: dict[str, dict[str, Any]]) -> list[str]:
    """The methods of a {task: {method: ...}} table in the order the JSON holds them (the evaluator's)."""
    return list(dict.fromkeys(m for per in per_task.values() for m in per))


def seeds_text(seeds: list[int]) -> str:
    s = sorted(seeds)
    if len(s) > 1 and s == list(range(s[0], s[-1] + 1)):
        return f"{s[0]}-{s[-1]}"
    return ",".join(str(x) for x in s)


def accuracy_command(acc: dict[str, Any]) -> str:
    """The ``make accuracy`` line that writes this bags/accuracy.json, from what the JSON records."""
    profiles = acc.get("profiles") or []
    profile = "both" if sorted(profiles) == ["paper", "spec"] else ",".join(profiles)
    cmd = f"make accuracy SEEDS={seeds_text(acc.get('seeds') or [])} PROFILE={profile}"
    if acc.get("fusion_config"):
        cmd += f" FUSION={acc['fusion_config']}"
    mode = (acc.get("noise_model") or {}).get("mode", "builtin")
    if mode != "builtin":
        cmd += f" NOISE={mode}"
    return cmd


def eval_seed(ev: dict[str, Any]) -> str | None:
    """The seed of the bags an eval.json evaluated, from their calibration source ("..., seed 0, profile paper)")."""
    for r in ev.get("tasks", []):
        text = str(r.get("calibration_source", ""))
        if ", seed " in text:
            return text.split(", seed ", 1)[1].split(",")[0].strip()
    return None


def eval_command(profile: str, ev: dict[str, Any]) -> str:
    if ev.get("targets"):
        return (f"python -m fullperc_eval.evaluation.evaluate_all --bags bags/{profile} --targets all "
                f"--json bags/{profile}/eval.json")
    return f"make eval PROFILE={profile}"


# ------------------------------------------------------------------------------------------ many-seed tables
def table1_rows(t1: dict[str, dict[str, Any]], ms: list[str], digits: int = 2) -> list[list[str]]:
    rows = []
    for t in [t for t in TASKS if t in t1] + [t for t in t1 if t not in TASKS]:
        per = t1[t]
        r = (per.get("cbkf") or [None])[0], (per.get("omc") or [None])[0]
        rows.append([t] + [pm(per.get(m), digits) for m in ms] + [num(r[0] / r[1]) if finite(r[0]) and finite(r[1])
                                                                  and r[1] else "–"])
    means = [[per[m][0] for per in t1.values() if per.get(m) and finite(per[m][0])] for m in ms]
    rows.append(["mean of the tasks"] + [num(sum(v) / len(v), digits) if len(v) == len(t1) else "–" for v in means]
                + [""])
    return rows


def paper_reference(ev: dict[str, Any] | None) -> list[str]:
    """The paper's Table 1 (real OR, one run per task), as the evaluator stores it for comparison."""
    paper = (ev or {}).get("paper") or {}
    t1 = paper.get("table1_mae_mm")
    if not t1:
        return []
    ms = methods_of(t1)
    rows = [[t] + [num(t1[t].get(m)) for m in ms] + [num(t1[t]["cbkf"] / t1[t]["omc"])] for t in t1]
    ratios = [t1[t]["cbkf"] / t1[t]["omc"] for t in t1]
    rows.append(["mean of the tasks"] + [num(sum(t1[t][m] for t in t1) / len(t1)) for m in ms]
                + [num(sum(ratios) / len(ratios))])
    return ["The paper's Table 1 (Sensors 2023, 23(20), 8637: the real OR, one run per task), for comparison:", "",
            *table(["task"] + [label(m) for m in ms] + ["CBKF/OMC"], rows)]


def ordering_block(s: dict[str, Any]) -> list[str]:
    c = s["cbkf_over_omc"]
    n = s["n_task_seeds"]
    return [f"- CBKF ≤ CKF ≤ BKF ≤ KF ≤ OMC in {pct(s['share_full_order'])} of the {n} task-seeds, "
            f"CBKF ≤ KF ≤ OMC in {pct(s['share_cbkf_kf_omc'])}, CBKF ≤ OMC in {pct(s['share_cbkf_le_omc'])}.",
            f"- CBKF/OMC over the task-seeds: mean {num(c['mean'])} ± {num(c['sd'])}, median {num(c['median'])}, "
            f"min {num(c['min'])}, max {num(c['max'])}.", ""]


def table2_block(s: dict[str, Any], ev: dict[str, Any] | None, with_paper: bool) -> list[str]:
    t2 = s.get("table2_gbp_b_to_p_mm") or {}
    if not t2:
        return []
    ms = methods_of(t2)
    rows = [[k.removesuffix("_mm")] + [pm(per.get(m)) for m in ms] for k, per in t2.items()]
    paper = ((ev or {}).get("paper") or {}).get("table2_b_to_p_mm") if with_paper else None
    if paper:
        rows += [[f"{k.removesuffix('_mm')}, the paper's Table 2"] + [num(paper[k].get(m)) for m in ms]
                 for k in ("max_mm", "median_mm") if k in paper]
    return [f"Table 2: G-B-P, the B→P segment, error [mm], mean ± sd over {s.get('table2_n', '?')} seeds:", "",
            *table([""] + [label(m) for m in ms], rows)]


def orientation_block(s: dict[str, Any]) -> list[str]:
    out = []
    ori = s.get("table1_orientation_deg")
    if ori:
        ms = methods_of(ori)
        out += ["Orientation MAE [deg] over the whole task (the angle of R_trueᵀ R_est; LOCAL = the raw Vega chain, "
                "only where the Vega sees the tool), mean ± sd over seeds:", "",
                *table(["task"] + [label(m) for m in ms], [[t] + [pm(ori[t].get(m), 3) for m in ms] for t in ori])]
    by_local = s.get("orientation_by_local_deg")
    if by_local:
        ms = methods_of(by_local)
        for part, what in (("seen", "while the Vega sees the tool"), ("unseen", "while it does not")):
            cols = [m for m in ms if any(finite(((by_local[t].get(m) or {}).get(part) or [None])[0]) for t in by_local)]
            rows = [[t] + [pm((by_local[t].get(m) or {}).get(part), 3) for m in cols] for t in by_local]
            out += [f"Orientation MAE [deg] {what} (the same-samples goal's figures), mean ± sd over seeds:", "",
                    *table(["task"] + [label(m) for m in cols], rows)]
    by_region = s.get("orientation_by_region_deg")
    if by_region:
        ms = methods_of(by_region)
        out += ["Orientation MAE [deg] by region of the true path, mean ± sd over task-seeds:", "",
                *table(["region"] + [label(m) for m in ms],
                       [[reg] + [pm(by_region[reg].get(m), 3) for m in ms] for reg in by_region])]
    return out


def nees_cell(v: dict[str, Any] | None, digits: int = 1) -> str:
    if not v or not v.get("n"):
        return "–"
    return f"{pct(v.get('share_95'), digits)} / {v['mean']:.3g}" if finite(v.get("mean")) else "–"


def nees_block(s: dict[str, Any]) -> list[str]:
    nees = s.get("nees")
    if not nees:
        return []
    rows = [[label(m), nees_cell(k.get("position")), nees_cell(k.get("pose")), str((k.get("position") or {}).get("n"))]
            for m, k in nees.items()]
    return ["NEES pooled over every output of every task-seed: share inside the χ² 95 % bound / mean NEES "
            "(an honest covariance gives 95 % and a mean equal to the dof: 3 for position, 6 for the pose):", "",
            *table(["method", "position (dof 3)", "pose (dof 6)", "outputs"], rows)]


def first_local_block(s: dict[str, Any]) -> list[str]:
    split = s.get("before_first_local")
    if not split or not split.get("contribution_mm"):
        return []
    cm = split["contribution_mm"]
    rows = [[k] + [num((cm[m].get(k) or [None])[0]) for m in cm] for k in ("before", "after")]
    best = split.get("best_before_mm")
    sh = split.get("share_before")
    lines = [f"Position MAE [mm] split at the first Vega sample of each run ({pct(sh[0] if sh else None)} of the "
             "outputs come before it), mean over task-seeds; before + after = the whole-task MAE:", "",
             *table([""] + [label(m) for m in cm], rows)]
    if best:
        lines += [f"Before the first Vega sample every method has only the OMC; the best of them per task-seed "
                  f"spends {pm(best)} mm there, the floor of any causal filter that is no better than them before "
                  "that sample.", ""]
    return lines


def goals_block(goals: list[dict[str, Any]]) -> list[str]:
    if not goals:
        return []
    rows = [[f"`{g['goal']}`", GOAL_TEXT.get(g["goal"], ""), num(g.get("value"), 3), g.get("target", ""),
             STATE[g.get("ok")], str(g.get("detail", "")).replace("|", "/")] for g in goals]
    return [f"Goals of the `{goals[0].get('method', 'fullperc')}` filter "
            "(`fullperc_eval/evaluation/accuracy_goals.py`):", "",
            *table(["goal", "asks", "value", "target", "", "from"], rows, left=2)]


def targets_block(s: dict[str, Any], checks: list[dict[str, Any]]) -> list[str]:
    """Every tracked target's MAE by region (Table 1 and NEES too but the tool's, above), then their checks."""
    out = []
    for t, ts in (s.get("targets") or {}).items():
        ms = methods_of(ts["table1_mae_mm"])
        if t != "tool":
            out += [f"`{t}` (truth `/sim/truth/{t}`): position MAE [mm], mean ± sd over seeds:", "",
                    *table(["task"] + [label(m) for m in ms] + ["CBKF/OMC"], table1_rows(ts["table1_mae_mm"], ms)),
                    *nees_block(ts)]
        reg, n = ts["mae_by_region_mm"], ts["region_n"]
        rows = [[f"{r} ({n[r]})"] + [f"{pm(reg[r].get(m))} ({num(ts['region_over_omc'][r].get(m))})" for m in ms]
                for r in reg if n[r]]
        out += [f"`{t}`: position MAE [mm] by region, mean ± sd over the task-seeds in it (their number) and, in "
                "brackets, the method's mean over the OMC's:", "", *table(["region"] + [label(m) for m in ms], rows)]
    if checks:
        rows = [[f"`{c['target']}`", f"`{c['goal']}`", "every filter" if c["method"] == "all" else label(c["method"]),
                 STATE[c.get("ok")], num(c.get("value"), 3), c["bound"],
                 "–" if c.get("margin") is None else f"{c['margin']:+.3f}", str(c.get("detail", "")).replace("|", "/")]
                for c in checks]
        grid = table(["target", "check", "method", "", "value", "bound", "margin", "from"], rows, left=4)
        grid[1] = grid[1].removesuffix("---:|") + "---|"   # the last column is text too
        out += ["Acceptance checks per target (`fullperc_eval/evaluation/target_goals.py`; margin > 0: passed by that "
                "much, < 0: missed by it):", "", *grid]
    return out


def profile_section(p: str, s: dict[str, Any], goals: list[dict[str, Any]], ev: dict[str, Any] | None,
                    checks: list[dict[str, Any]] | None = None) -> list[str]:
    t1 = s["table1_mae_mm"]
    ms = methods_of(t1)
    seeds = s.get("seeds") or []
    out = [f"### Twin profile `{p}`", "",
           f"Table 1: position MAE [mm], mean ± sd over seeds {seeds_text(seeds)} ({s['n_task_seeds']} task-seeds); "
           "CBKF/OMC is the ratio of the two means:", "",
           *table(["task"] + [label(m) for m in ms] + ["CBKF/OMC"], table1_rows(t1, ms))]
    if p == "paper":
        out += paper_reference(ev)
    return (out + ordering_block(s) + table2_block(s, ev, with_paper=p == "paper") + orientation_block(s)
            + nees_block(s) + first_local_block(s) + goals_block(goals) + targets_block(s, checks or []))


def accuracy_section(acc: dict[str, Any], evals: dict[str, dict[str, Any]]) -> list[str]:
    cmd = accuracy_command(acc)
    mode = (acc.get("noise_model") or {}).get("mode", "builtin")
    cfg = acc.get("fusion_config") or "the shipped `fusion.yaml`"
    out = ["## Many seeds (`make accuracy`)", "",
           f"`{cmd}` wrote these figures to `bags/accuracy.json`: every task on seeds {seeds_text(acc['seeds'])} of "
           f"each profile, evaluated with {cfg} and `fullperc`'s {'built-in' if mode == 'builtin' else mode} noise "
           "model. Each seed is a freshly simulated room (its own camera miscalibration and noise draws).", ""]
    for p in acc.get("profiles", []):
        if p in acc.get("summary", {}):
            out += profile_section(p, acc["summary"][p], acc.get("goals", {}).get(p, []), evals.get(p),
                                   acc.get("target_goals", {}).get(p))
    return out


# ------------------------------------------------------------------------------------------- seed-0 tables
def seed_rows(rows: list[dict[str, Any]], key: str, ms: list[str], digits: int, ratio: bool = False) -> list[list[str]]:
    out = []
    for r in rows:
        v = r.get(key) or {}
        cells = [num(v.get(m), digits) for m in ms]
        if ratio:
            cells.append(num(v["cbkf"] / v["omc"]) if finite(v.get("cbkf")) and finite(v.get("omc")) and v["omc"]
                         else "–")
        out.append([r["task"]] + cells)
    return out


def seed_profile(p: str, ev: dict[str, Any]) -> list[str]:
    rows = ev.get("tasks", [])
    if not rows:
        return []
    seed = eval_seed(ev)
    ms = methods_of({r["task"]: r["mae_mm"] for r in rows})
    out = [f"### Twin profile `{p}`, seed {seed if seed is not None else '?'}", "",
           f"`{eval_command(p, ev)}` wrote `bags/{p}/eval.json` from the committed bags in `bags/{p}/` "
           f"(`make dataset PROFILE={p} SEED={seed if seed is not None else 0}`).", "",
           "Table 1: position MAE [mm] over every pose each method outputs:", "",
           *table(["task"] + [label(m) for m in ms] + ["CBKF/OMC"], seed_rows(rows, "mae_mm", ms, 2, ratio=True))]
    ori_ms = methods_of({r["task"]: r.get("orientation_mae_deg") or {} for r in rows})
    if ori_ms:
        out += ["Table 1b: orientation MAE [deg] (LOCAL = the raw Vega chain, only where the Vega sees the tool):", "",
                *table(["task"] + [label(m) for m in ori_ms], seed_rows(rows, "orientation_mae_deg", ori_ms, 3))]
    nees_ms = methods_of({r["task"]: r.get("nees") or {} for r in rows})
    if nees_ms:
        def kind(r: dict[str, Any], m: str, k: str) -> dict[str, Any] | None:
            return ((r.get("nees") or {}).get(m) or {}).get(k)

        pose_ms = [m for m in nees_ms if any((kind(r, m, "pose") or {}).get("n") for r in rows)]
        body = [[r["task"]] + [nees_cell(kind(r, m, "position"), 0) for m in nees_ms]
                + [nees_cell(kind(r, m, "pose"), 0) for m in pose_ms] for r in rows]
        out += ["NEES per task: share inside the χ² 95 % bound / mean (position for every method; the pose for the "
                "methods that fuse the orientation):", "",
                *table(["task"] + [f"{label(m)} position" for m in nees_ms] + [f"{label(m)} pose" for m in pose_ms],
                       body)]
    for r in rows:
        bp = r.get("b_to_p")
        if bp:
            bms = methods_of({"max": bp["max_mm"]})
            out += [f"Table 2: {r['task']}, the B→P segment ({num(bp.get('t0_s'), 1)}–{num(bp.get('t1_s'), 1)} s), "
                    "error [mm]:", "",
                    *table([""] + [label(m) for m in bms], [[k.removesuffix("_mm")] + [num(bp[k].get(m)) for m in bms]
                                                            for k in ("max_mm", "median_mm")])]
    comp = ev.get("comparison") or []
    if comp:
        names = list(comp[0]["checks"])
        yn = {True: "yes", False: "no"}
        body = [[c["task"], num(c["cbkf_over_omc"]), num(c.get("paper_cbkf_over_omc"))]
                + [f"{yn[c['checks'][k]]} / {yn[c['paper_checks'][k]] if 'paper_checks' in c else '–'}" for k in names]
                for c in comp]
        head = {"omc_worst": "OMC worst", "cbkf_le_ckf": "CBKF ≤ CKF", "ckf_lt_kf": "CKF < KF", "bkf_le_kf": "BKF ≤ KF"}
        out += ["The paper's claims per task, here / in the paper's Table 1:", "",
                *table(["task", "CBKF/OMC", "the paper's"] + [head.get(k, k) for k in names], body)]
    return out


def instrument_block(p: str, ev: dict[str, Any]) -> list[str]:
    targets = ev.get("targets") or {}
    out = []
    for target, rows in targets.items():
        ms = methods_of({r["task"]: r["mae_mm"] for r in rows})
        body = []
        for r in rows:
            body.append([f"{r['task']}, whole run"] + [num(r["mae_mm"].get(m)) for m in ms])
            for reg in REGIONS:
                per = (r.get("mae_by_region_mm") or {}).get(reg)
                if per:
                    body.append([f"{r['task']}, {reg}"] + [num(per.get(m)) for m in ms])
        out += [f"`{target}` (against the simulator's truth `/sim/truth/{target}`), `{p}`, position MAE [mm], "
                "whole run and by region:", "", *table(["bag"] + [label(m) for m in ms], body)]
    return out


def seed_section(evals: dict[str, dict[str, Any]]) -> list[str]:
    out = ["## The committed sample bags (`make eval`)", "",
           "One seed is one draw of the room: these tables show what a single run looks like, the many-seed tables "
           "above what the methods do. `src/fullperc_eval/test/test_sample_bags.py` pins every figure of these JSON "
           "files to the committed bags (regenerate with `make dataset` and `make eval`, and commit both).", ""]
    for p, ev in evals.items():
        out += seed_profile(p, ev)
    inst = [line for p, ev in evals.items() for line in instrument_block(p, ev)]
    out += ["### The hand-held instrument", ""]
    if inst:
        out += inst
    else:
        out += ["These `eval.json` files hold the arm-held tool only (`make eval`). The instrument's rows: "
                "`python -m fullperc_eval.evaluation.evaluate_all --bags bags/<profile> --targets all --json F`; "
                "rendered here when the committed JSON has them.", ""]
    return out


# ------------------------------------------------------------------------------------------------- outputs
def load(root: Path) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    acc = json.loads((root / ACCURACY).read_text())
    evals = {}
    for p in ("paper", "spec"):
        f = root / "bags" / p / "eval.json"
        if f.is_file():
            evals[p] = json.loads(f.read_text())
    return acc, evals


def render_page(root: Path = ROOT) -> str:
    acc, evals = load(root)
    lines = ["# Results", "",
             "<!-- Generated by `python scripts/results_page.py` from bags/accuracy.json and bags/<profile>/eval.json. "
             "Do not edit: run the script. -->", "",
             "Every figure on this page is rendered by `python scripts/results_page.py` from the JSON the evaluation "
             "writes, and each table names the command that wrote its JSON. `test/test_docs.py` fails when this page "
             "differs from what the script renders from the committed JSON. What the tasks, regions, methods and "
             "figures are: [evaluation.md](evaluation.md); the twin's two profiles: "
             "[evaluation.md](evaluation.md#the-twins-two-profiles).", "",
             "- [Many seeds (`make accuracy`)](#many-seeds-make-accuracy)",
             "- [The committed sample bags (`make eval`)](#the-committed-sample-bags-make-eval)", ""]
    lines += accuracy_section(acc, evals)
    lines += seed_section(evals)
    while lines and lines[-1] == "":
        lines.pop()
    return "\n".join(lines) + "\n"


def render_readme_block(root: Path = ROOT) -> str:
    """The README's results block (between the markers): the many-seed means and the goals, nothing more."""
    acc, evals = load(root)
    summary = acc.get("summary", {})
    profiles = [p for p in acc.get("profiles", []) if p in summary]
    ms = methods_of(next(iter(summary.values()))["table1_mae_mm"]) if summary else []
    rows = []
    for p in profiles:
        t1 = summary[p]["table1_mae_mm"]
        c = summary[p]["cbkf_over_omc"]
        rows.append([f"twin `{p}`"] + [num(sum(per[m][0] for per in t1.values()) / len(t1)) for m in ms]
                    + [f"{num(c['mean'])} ± {num(c['sd'])}"])
    ref = ((next(iter(evals.values()), {}) or {}).get("paper") or {}).get("table1_mae_mm")
    if ref:
        ratios = [ref[t]["cbkf"] / ref[t]["omc"] for t in ref]
        means = [num(sum(ref[t][m] for t in ref) / len(ref)) if all(m in ref[t] for t in ref) else "–" for m in ms]
        rows.append(["the paper's real OR"] + means + [num(sum(ratios) / len(ratios))])
    goals = {p: {g["goal"]: g for g in acc.get("goals", {}).get(p, [])} for p in profiles}
    order = {n: i for i, n in enumerate(GOAL_TEXT)}
    names = sorted(dict.fromkeys(n for p in profiles for n in goals[p]), key=lambda n: order.get(n, len(order)))
    cell = lambda g: "–" if g is None else f"{num(g.get('value'), 3)} ({g.get('target')}): {STATE[g.get('ok')]}"  # noqa: E731
    grow = [[GOAL_TEXT.get(n, f"`{n}`")] + [cell(goals[p].get(n)) for p in profiles] for n in names]
    lines = [BEGIN,
             f"Position MAE [mm], mean of the six tasks over seeds {seeds_text(acc.get('seeds') or [])} "
             f"(`{accuracy_command(acc)}`; rendered by `python scripts/results_page.py`):", "",
             *table([""] + [label(m) for m in ms] + ["CBKF/OMC per run, mean"], rows),
             "The goals of the `fullperc` filter on the same runs:", "",
             *table(["goal"] + [f"`{p}`" for p in profiles], grow, left=len(profiles) + 1)]
    lines[-1:] = [END]   # table() ends with a blank line: the marker takes its place
    return "\n".join(lines)


def readme_with_block(text: str, block: str) -> str:
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise ValueError(f"README.md must hold one {BEGIN} ... {END} block")
    head, rest = text.split(BEGIN, 1)
    return head + block + rest.split(END, 1)[1]


def outputs(root: Path = ROOT) -> dict[Path, str]:
    """Every file this script writes, with the text it would write."""
    readme = (root / README).read_text()
    return {root / PAGE: render_page(root), root / README: readme_with_block(readme, render_readme_block(root))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python scripts/results_page.py", description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 when docs/results.md or the README's results block is stale")
    ap.add_argument("--root", default=str(ROOT), help="repository root (default: this checkout)")
    args = ap.parse_args(argv)
    root = Path(args.root)
    try:
        want = outputs(root)
    except (OSError, ValueError, KeyError) as e:
        print(f"results_page: {e}", file=sys.stderr)
        return 2
    stale = [p for p, text in want.items() if not p.is_file() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f"results_page: {p.relative_to(root)} differs from what bags/accuracy.json and "
                  "bags/<profile>/eval.json give; run: python scripts/results_page.py", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(want[p])
        print(f"wrote {p.relative_to(root)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
