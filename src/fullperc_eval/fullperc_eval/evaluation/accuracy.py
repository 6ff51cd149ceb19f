"""``make accuracy``: the six tasks on many seeds and twin profiles, Table 1 as mean ± sd over seeds.

    python -m fullperc_eval.evaluation.accuracy --seeds 0-9 --profile paper|spec|both [--fusion-config FILE]
        [--jobs 2] [--json bags/accuracy.json] [--cache DIR] [--noise-model calibrated|builtin|FILE]
        [--calibration-seeds 100-102] [--no-presets]

Per (profile, seed): the six bags are generated with :func:`fullperc_eval.sim.dataset.generate` into
``<cache>/<profile>-<twin hash>/seed<k>/`` (reused when present: the hash covers the merged scene configuration and
the plans file, so a changed profile never reuses old bags) and evaluated with
:func:`fullperc_eval.evaluation.metrics.evaluate_bag` (the fusion config given, else ``fusion.yaml``). One progress
line per seed on stderr. Then, per profile:

* Table 1: MAE per task and method, mean ± sd over seeds;
* the share of task-seeds where the paper's ordering CBKF <= CKF <= BKF <= KF <= OMC holds, and where
  CBKF <= KF <= OMC holds;
* the CBKF/OMC ratio over every task-seed: mean, sd, median, min, max;
* Table 2 (G-B-P, B->P segment): max and median per method, mean ± sd over seeds;
* orientation MAE [deg] per task and method (and of the raw local chain ``local``), mean ± sd over seeds;
* NEES per method, pooled over every output of every task-seed: share inside the chi2 95 % bound and mean
  (position, dof 3; full pose, dof 6, for methods that fuse the orientation);
* the goal checks of issue 18 for :data:`GOAL_METHOD` (:func:`goal_checks`).

These are the arm-held ``tool``'s (the paper's target), exactly as before. Every bag is evaluated for every target it
holds (the tool and each target with simulator truth ``/sim/truth/<target>``, e.g. the hand-held ``instrument``;
:mod:`.accuracy_targets`); each row of ``task_seeds`` names its ``target``. Then, per profile and target, the tool
too: Table 1 (MAE per task and method, mean ± sd over seeds), the MAE by region per method against the OMC's, the
NEES pooled per method (``summary[profile]["targets"][target]``), and issue 41's acceptance checks
(:mod:`.target_goals`, ``target_goals[profile]``) with pass/fail and the margin; for its check of ``motion: auto``
each bag is also evaluated with fullperc alone under each motion preset (``motion_presets_mae_mm`` of a row;
``--no-presets`` skips it).

The noise model of ``fullperc`` (``fullperc.noise_model_file``, :mod:`fullperc_fusion.filters.noise_model_file`), per
profile: ``builtin`` (default) keeps the built-in model (the ``spec`` bags' statistics: what fusion_node runs
without ``fullperc.noise_model_file``); ``calibrated`` fits it with ``fit_noise_model`` (:mod:`.sensor_stats`:
raw OMC against the arm's forward kinematics, no filter) on the bags of the calibration seeds -- never an
evaluated seed (refused) -- as a user fits it on a calibration recording of their OR (each twin seed draws its own
camera miscalibration: a calibration seed is another room of the same kind, not the one evaluated); a file path
uses that file for every profile. The paper's four filters do not read it.

Stdout: one JSON line per figure (``{"name", "value", "unit", "profile", ...}``, like ``bench/benchlib.py``): the
paper's five methods' lines first, exactly as before, then the further methods', the orientation, NEES and goal
lines; after every profile's, the per-target lines (``<target>_...`` and ``goal41_...``, each with ``target``); then
the human tables. ``--json`` writes every per-task-seed figure and the summary (the former keys unchanged; ``goals``,
``targets``, ``target_goals`` and ``summary[profile]["targets"]`` added).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from fullperc_eval.sim.dataset import generate
from fullperc_eval.sim.scene import PROFILES
from fullperc_eval.sim.tasks import TASKS

from .accuracy_goals import GOAL_METHOD, format_goals, goal_checks, goal_lines
from .accuracy_targets import (
    _methods,
    _ms,
    _ms_table,
    format_nees,
    format_target,
    pooled_nees,
    preset_maes,
    split_targets,
    target_json_lines,
    target_of,
    target_summary,
    task_row,
    task_targets,
)
from .config import PAPER_METHODS
from .evaluate_all import TASK_ORDER
from .ground_truth import ARM_TARGET
from .tables import _grid
from .target_goals import target_goal_checks, target_goal_lines
from .twin_report import parse_seeds, twin_hash

ORDER_FULL = ("cbkf", "ckf", "bkf", "kf", "omc")   # CBKF <= CKF <= BKF <= KF <= OMC
ORDER_MAIN = ("cbkf", "kf", "omc")                 # CBKF <= KF <= OMC


CALIBRATION_SEEDS = "100-102"


def calibrated_fusion_config(profile: str, key: str, cache: str, fusion_config: str | None,
                             seeds: list[int]) -> dict[str, Any]:
    """Fit ``profile``'s noise model on the six bags of each calibration seed (generated when missing) as
    ``fit_noise_model --write`` does -- the raw OMC against the arm's kinematics and the raw (OMC - local chain)
    differences' semivariogram over distance -- and write it with a fusion config that reads it
    (:func:`fusion_config_reading`) into ``<cache>/<profile>-<key>/``."""
    from fullperc_fusion.margin.layout import default_layout_path, load_layout

    from .sensor_stats import fitted, pool_rows, profile_differences, profile_rows, write_noise_model

    root = Path(cache) / f"{profile}-{key}"
    layout = load_layout(default_layout_path())
    parts, diffs = [], []
    for seed in seeds:
        ensure_bags(root / f"seed{seed}", seed, profile)
        parts.append(profile_rows(root / f"seed{seed}", layout))
        diffs += profile_differences(root / f"seed{seed}")
    tag = "-".join(str(s) for s in seeds)
    nm = root / f"noise_model_seeds{tag}.yaml"
    f = fitted(*pool_rows(parts), diffs)
    text = write_noise_model(nm, f, f"raw-sensor statistics of twin profile {profile}, calibration seed(s) {tag}")
    return fusion_config_reading(fusion_config, nm, text, root / f"fusion_noise_model_seeds{tag}.yaml")


def fusion_config_reading(fusion_config: str | None, noise_model_file: Path, noise_model_text: str,
                          out: Path) -> dict[str, Any]:
    """Write to ``out`` a fusion config with ``fusion_config``'s parameters (else fusion_node's defaults) plus
    ``fullperc.noise_model_file``; returns {"fusion_config", "noise_model_file", "noise_model": the file's
    content, parsed from ``noise_model_text``}."""
    import yaml

    from fullperc_fusion.fusion_config import default_fusion_config_path, read_params_file

    flat = read_params_file(fusion_config if fusion_config else default_fusion_config_path())
    flat["fullperc.noise_model_file"] = str(noise_model_file)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": flat}}, sort_keys=False))
    return {"fusion_config": str(out), "noise_model_file": str(noise_model_file),
            "noise_model": yaml.safe_load(noise_model_text)}


def noise_model_configs(mode: str, profiles: tuple[str, ...], keys: dict[str, str], cache: str,
                        fusion_config: str | None, cal_seeds: list[int], eval_seeds: list[int],
                        jobs: int = 2) -> dict[str, dict[str, Any]]:
    """Per profile: the fusion config to evaluate with and the noise model it reads (``--noise-model``)."""
    if mode == "builtin":
        return {p: {"fusion_config": fusion_config, "noise_model_file": "", "noise_model": None} for p in profiles}
    if mode != "calibrated":
        from fullperc_fusion.filters.noise_model_file import load_noise_model

        load_noise_model(mode)   # a bad file: a clear error before any work
        path = Path(mode).resolve()
        text = path.read_text()
        return {p: fusion_config_reading(fusion_config, path, text,
                                         Path(cache) / f"{p}-{keys[p]}" / "fusion_noise_model_given.yaml")
                for p in profiles}
    overlap = sorted(set(cal_seeds) & set(eval_seeds))
    if overlap:
        raise ValueError(f"calibration seeds {overlap} are also evaluated: the noise model must be fitted on other "
                         "installations than the ones it is judged on")
    with ProcessPoolExecutor(max_workers=max(1, min(jobs, len(profiles)))) as ex:
        futs = {p: ex.submit(calibrated_fusion_config, p, keys[p], cache, fusion_config, cal_seeds)
                for p in profiles}
        return {p: f.result() for p, f in futs.items()}


def default_cache() -> Path:
    return Path(os.environ.get("FULLPERC_CACHE", Path.home() / ".cache" / "fullperc")) / "accuracy"


def holds(mae: dict[str, float], order=ORDER_FULL) -> bool:
    return all(mae[a] <= mae[b] + 1e-9 for a, b in zip(order, order[1:], strict=False))


def ensure_bags(d: Path, seed: int, profile: str) -> list[str]:
    """Generate into ``d`` the tasks of ``seed`` whose bag (metadata.yaml and calibration.yaml) is not there yet;
    returns them (the cached ones are reused)."""
    missing = [t for t in TASKS if not ((d / t / "metadata.yaml").is_file() and (d / t / "calibration.yaml").is_file())]
    if missing:
        generate(d, missing, seed, log=lambda _m: None, profile=profile)
    return missing


def run_seed(profile: str, seed: int, cache: str, fusion_config: str | None, key: str,
             presets: bool = True) -> dict[str, Any]:
    """Generate (or reuse) and evaluate the six bags of one seed, every target each bag holds
    (:func:`.accuracy_targets.task_targets`: the tool and each one with simulator truth); returns per-task rows,
    per task the tool's first, each with its ``target``."""
    from .metrics import evaluate_bag  # in the worker: keeps the parent light
    t0 = time.monotonic()
    d = Path(cache) / f"{profile}-{key}" / f"seed{seed}"
    missing = ensure_bags(d, seed, profile)
    t1 = time.monotonic()
    rows = []
    for t in TASK_ORDER:
        for target in task_targets(d / t):
            r = evaluate_bag(d / t, fusion_config=fusion_config, target=target, progress=False).result
            rows.append(task_row(t, seed, profile, target, r))
            if presets:   # issue 41's motion: auto against each preset (target_goals e)
                rows[-1]["motion_presets_mae_mm"] = preset_maes(d / t, fusion_config, target, evaluate_bag)
    return {"profile": profile, "seed": seed, "rows": rows, "generated": len(missing),
            "sim_s": t1 - t0, "eval_s": time.monotonic() - t1}


def first_local_summary(rows: list[dict[str, Any]], methods: list[str]) -> dict[str, Any] | None:
    """Mean over task-seeds of each method's MAE contribution before / after the first local sample
    (:func:`.metrics.first_local_split`), and ``best_before_mm``: per task-seed the smallest contribution before it
    of any method, averaged. A filter no better than the best method before the first local sample and with no
    error at all after it would have a mean MAE of ``best_before_mm``: the floor of the ``position_vs_cbkf`` goal
    under that assumption (it is not a theorem: a filter could beat every method on the OMC alone)."""
    have = [r for r in rows if r.get("before_first_local")]
    if not have:
        return None
    ms = [m for m in methods if all(m in r["before_first_local"]["contribution_mm"] for r in have)]
    return {"n": len(have),
            "contribution_mm": {m: {k: _ms([r["before_first_local"]["contribution_mm"][m][k] for r in have])
                                    for k in ("before", "after")} for m in ms},
            "share_before": _ms([r["before_first_local"]["share"][ms[0]] for r in have]) if ms else None,
            "best_before_mm": _ms([min(r["before_first_local"]["contribution_mm"][m]["before"] for m in ms)
                                   for r in have]) if ms else None}


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Table 1 mean ± sd, ordering shares, CBKF/OMC distribution and Table 2 of one profile's task-seeds; the
    orientation table, the pooled NEES and the goal checks (:func:`goal_checks`) when the rows carry them."""
    ms = _methods(rows)
    t1 = {t: {m: _ms([r["mae_mm"].get(m) for r in rows if r["task"] == t]) for m in ms} for t in TASK_ORDER}
    ratio = np.array([r["mae_mm"]["cbkf"] / r["mae_mm"]["omc"] for r in rows])
    gbp = [r for r in rows if r["task"] == "G-B-P" and r.get("b_to_p")]
    t2 = {k: {m: _ms([r["b_to_p"][k].get(m) for r in gbp]) for m in ms} for k in ("max_mm", "median_mm")}
    extra: dict[str, Any] = {}
    oms = _methods(rows, "orientation_mae_deg")
    if oms:
        extra["table1_orientation_deg"] = {t: {m: _ms([(r.get("orientation_mae_deg") or {}).get(m)
                                                       for r in rows if r["task"] == t]) for m in oms}
                                           for t in TASK_ORDER}
        extra["orientation_by_region_deg"] = {
            reg: {m: _ms([((r.get("orientation_by_region_deg") or {}).get(reg) or {}).get(m) for r in rows])
                  for m in oms} for reg in ("BVV", "GVV", "PVV")}
        if any(r.get("orientation_by_local_deg") for r in rows):
            extra["orientation_by_local_deg"] = {
                t: {m: {part: _ms([(((r.get("orientation_by_local_deg") or {}).get(m)) or {}).get(part)
                                   for r in rows if r["task"] == t]) for part in ("seen", "unseen")}
                    for m in oms} for t in TASK_ORDER}
    if any(r.get("nees") for r in rows):
        extra["nees"] = pooled_nees(rows)
    split = first_local_summary(rows, ms)
    if split:
        extra["before_first_local"] = split
    return {"n_task_seeds": len(rows), "seeds": sorted({r["seed"] for r in rows}), "table1_mae_mm": t1,
            "share_full_order": float(np.mean([holds(r["mae_mm"], ORDER_FULL) for r in rows])),
            "share_cbkf_kf_omc": float(np.mean([holds(r["mae_mm"], ORDER_MAIN) for r in rows])),
            "share_cbkf_le_omc": float(np.mean(ratio <= 1.0)),
            "cbkf_over_omc": {"mean": float(ratio.mean()), "sd": float(ratio.std(ddof=1)) if ratio.size > 1 else 0.0,
                              "median": float(np.median(ratio)), "min": float(ratio.min()),
                              "max": float(ratio.max())},
            "table2_gbp_b_to_p_mm": t2, "table2_n": len(gbp), **extra}


def _r4(v: float | None) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), 4)


def json_lines(profile: str, s: dict[str, Any], goals: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """The JSON lines of one profile: the paper's five methods' lines first, in the order and form they always had,
    then those of every further method, the orientation, the NEES and the ``goals`` given."""
    out = []
    for t, per in s["table1_mae_mm"].items():
        for m, (mu, sd) in per.items():
            if m in PAPER_METHODS:
                out.append({"name": f"mae_{m}_{t}", "value": round(mu, 4), "sd": round(sd, 4), "unit": "mm"})
    out.append({"name": "share_full_order", "value": round(s["share_full_order"], 4), "unit": "fraction"})
    out.append({"name": "share_cbkf_kf_omc", "value": round(s["share_cbkf_kf_omc"], 4), "unit": "fraction"})
    out.append({"name": "share_cbkf_le_omc", "value": round(s["share_cbkf_le_omc"], 4), "unit": "fraction"})
    for k, v in s["cbkf_over_omc"].items():
        out.append({"name": f"cbkf_over_omc_{k}", "value": round(v, 4), "unit": "ratio"})
    for k, per in s["table2_gbp_b_to_p_mm"].items():
        for m, (mu, sd) in per.items():
            if m in PAPER_METHODS:
                out.append({"name": f"b_to_p_{k.removesuffix('_mm')}_{m}", "value": round(mu, 4), "sd": round(sd, 4),
                            "unit": "mm"})
    # added lines (issue 18): further methods, orientation, NEES, goals -- after every line of the paper's five
    for t, per in s["table1_mae_mm"].items():
        for m, (mu, sd) in per.items():
            if m not in PAPER_METHODS:
                out.append({"name": f"mae_{m}_{t}", "value": _r4(mu), "sd": _r4(sd), "unit": "mm"})
    for k, per in s["table2_gbp_b_to_p_mm"].items():
        for m, (mu, sd) in per.items():
            if m not in PAPER_METHODS:
                out.append({"name": f"b_to_p_{k.removesuffix('_mm')}_{m}", "value": _r4(mu), "sd": _r4(sd),
                            "unit": "mm"})
    for t, per in (s.get("table1_orientation_deg") or {}).items():
        for m, (mu, sd) in per.items():
            out.append({"name": f"orientation_mae_{m}_{t}", "value": _r4(mu), "sd": _r4(sd), "unit": "deg"})
    for m, kinds in (s.get("nees") or {}).items():
        for kind, v in kinds.items():
            if v["n"]:
                out.append({"name": f"nees_{kind}_share95_{m}", "value": _r4(v["share_95"]), "unit": "fraction",
                            "n": v["n"]})
                out.append({"name": f"nees_{kind}_mean_{m}", "value": _r4(v["mean"]), "unit": "nees", "n": v["n"]})
    split = s.get("before_first_local")
    if split:
        for m, parts in split["contribution_mm"].items():
            for k, (mu, sd) in parts.items():
                out.append({"name": f"mae_{k}_first_local_{m}", "value": _r4(mu), "sd": _r4(sd), "unit": "mm"})
        if split["best_before_mm"]:
            mu, sd = split["best_before_mm"]
            out.append({"name": "mae_before_first_local_best", "value": _r4(mu), "sd": _r4(sd), "unit": "mm"})
    out += goal_lines(goals or [])
    for rec in out:
        rec.update(profile=profile, seeds=len(s["seeds"]))
    return out


def format_summary(profile: str, s: dict[str, Any], goals: list[dict[str, Any]] | None = None) -> str:
    seeds = s["seeds"]
    ms = list(next(iter(s["table1_mae_mm"].values())))
    lines = [f"profile {profile}: Table 1, MAE [mm] mean ± sd over {len(seeds)} seeds "
             f"({seeds[0]}-{seeds[-1]}), {s['n_task_seeds']} task-seeds",
             f"{'task':<9}" + "".join(f"{m.upper():>14}" for m in ms) + "   CBKF/OMC"]
    for t, per in s["table1_mae_mm"].items():
        r = per["cbkf"][0] / per["omc"][0] if per["omc"][0] else float("nan")
        lines.append(f"{t:<9}" + "".join(f"{mu:8.2f} ± {sd:4.2f}" for mu, sd in per.values()) + f"   {r:8.2f}")
    c = s["cbkf_over_omc"]
    lines += [f"CBKF <= CKF <= BKF <= KF <= OMC in {100 * s['share_full_order']:.0f} % of task-seeds; "
              f"CBKF <= KF <= OMC in {100 * s['share_cbkf_kf_omc']:.0f} %; CBKF <= OMC in "
              f"{100 * s['share_cbkf_le_omc']:.0f} %",
              f"CBKF/OMC over task-seeds: mean {c['mean']:.2f} ± {c['sd']:.2f}, median {c['median']:.2f}, "
              f"min {c['min']:.2f}, max {c['max']:.2f} (paper: mean 0.51, 0.46-0.66)",
              f"Table 2 (G-B-P, B->P segment, {s['table2_n']} seeds), error [mm] mean ± sd:",
              f"{'':<9}" + "".join(f"{m.upper():>14}" for m in ms)]
    for k, per in s["table2_gbp_b_to_p_mm"].items():
        lines.append(f"{k.removesuffix('_mm'):<9}" + "".join(f"{mu:8.2f} ± {sd:4.2f}" for mu, sd in per.values()))
    lines.append(f"{'paper':<9}max 6.36 8.32 6.76 2.02 2.02 | median 5.81 5.77 5.56 0.25 0.25")
    if s.get("table1_orientation_deg"):
        lines += ["", *_ms_table("Orientation MAE [deg] mean ± sd over seeds (LOCAL = raw Vega chain in base):",
                                 s["table1_orientation_deg"], 3)]
    by_local = s.get("orientation_by_local_deg")
    if by_local:   # the same-samples goal's figures: each task's outputs split by whether the Vega sees the tool
        for part, what in (("seen", "while the Vega sees the tool"), ("unseen", "while it does not")):
            table = {t: {m: v[part] for m, v in per.items() if np.isfinite(v[part][0])} for t, per in by_local.items()}
            lines += ["", *_ms_table(f"Orientation MAE [deg] {what}, mean ± sd over seeds:", table, 3)]
    nees = format_nees(s)
    if nees:
        lines += ["", *nees]
    split = s.get("before_first_local")
    if split and split["contribution_mm"]:
        cm = split["contribution_mm"]
        sh, best = split["share_before"], split["best_before_mm"]
        lines += ["", f"MAE [mm] split at the first Vega sample ({100 * sh[0]:.0f} % of the outputs before it), "
                      "mean over task-seeds; before + after = the whole-task MAE:",
                  *_grid([""] + [m.upper() for m in cm],
                         [[k] + [f"{cm[m][k][0]:.2f}" for m in cm] for k in ("before", "after")]),
                  f"best method before it, per task-seed: {best[0]:.2f} ± {best[1]:.2f} mm (a filter perfect after "
                  "the first Vega sample and no better than that before it would reach this MAE)"]
    if goals:
        lines += ["", *format_goals(goals)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.evaluation.accuracy", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0-9", help="e.g. 0-9 or 0,4 (default 0-9)")
    ap.add_argument("--profile", default="paper", choices=(*PROFILES, "both"))
    ap.add_argument("--fusion-config", default=None, help="fusion.yaml to evaluate with (default: fusion_node's)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--cache", default=None, help=f"bag cache (default {default_cache()})")
    ap.add_argument("--json", default="bags/accuracy.json", help="write all figures here ('' = no file)")
    ap.add_argument("--noise-model", default="builtin",
                    help="fullperc's noise model: builtin, calibrated (fitted per profile on --calibration-seeds) "
                         "or a noise-model file (default builtin)")
    ap.add_argument("--no-presets", action="store_true",
                    help="skip fullperc's runs with each motion preset (issue 41's auto-vs-preset check)")
    ap.add_argument("--calibration-seeds", default=CALIBRATION_SEEDS,
                    help=f"seeds whose bags the calibrated noise model is fitted on (default {CALIBRATION_SEEDS})")
    args = ap.parse_args(argv)
    seeds = parse_seeds(args.seeds)
    profiles = PROFILES if args.profile == "both" else (args.profile,)
    cache = str(Path(args.cache) if args.cache else default_cache())
    keys = {p: twin_hash(p) for p in profiles}
    t0 = time.monotonic()
    cal_seeds = parse_seeds(args.calibration_seeds)
    try:
        noise = noise_model_configs(args.noise_model, profiles, keys, cache, args.fusion_config, cal_seeds, seeds,
                                    args.jobs)
    except (ValueError, OSError) as e:
        print(f"accuracy: --noise-model {args.noise_model}: {e}", file=sys.stderr)
        return 2
    if args.noise_model != "builtin":
        print(f"noise model ({args.noise_model}): "
              + "; ".join(f"{p} {noise[p]['noise_model_file']}" for p in profiles)
              + f", {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
    results: list[dict[str, Any]] = []
    jobs = [(p, s) for p in profiles for s in seeds]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        futs = {ex.submit(run_seed, p, s, cache, noise[p]["fusion_config"], keys[p], not args.no_presets): (p, s)
                for p, s in jobs}
        for f in as_completed(futs):
            r = f.result()
            results.append(r)
            tool = [x for x in r["rows"] if target_of(x) == ARM_TARGET]
            ratio = [x["mae_mm"]["cbkf"] / x["mae_mm"]["omc"] for x in tool]
            extra = [x["mae_mm"][GOAL_METHOD] / x["mae_mm"]["cbkf"] for x in tool
                     if x["mae_mm"].get(GOAL_METHOD) is not None]
            others = sorted({target_of(x) for x in r["rows"]} - {ARM_TARGET})
            print(f"[{len(results)}/{len(jobs)}] profile {r['profile']} seed {r['seed']}: "
                  f"{'generated ' + str(r['generated']) + ' bags' if r['generated'] else 'cached bags'} "
                  f"{r['sim_s']:.0f} s, evaluated {r['eval_s']:.0f} s; CBKF/OMC mean {np.mean(ratio):.2f}, "
                  + (f"{GOAL_METHOD.upper()}/CBKF mean {np.mean(extra):.2f}, " if extra else "")
                  + (f"also {', '.join(others)}, " if others else "")
                  + f"{time.monotonic() - t0:.0f} s so far", file=sys.stderr, flush=True)
    summary, text, goals, checks = {}, [], {}, {}
    every_of = {p: [x for r in sorted(results, key=lambda r: r["seed"]) if r["profile"] == p for x in r["rows"]]
                for p in profiles}   # in seed order, whatever order the workers finished in
    by_target = {p: split_targets(every_of[p]) for p in profiles}
    rows_of = {p: by_target[p].get(ARM_TARGET, []) for p in profiles}   # the tool's: its tables as they always were
    for p in profiles:
        summary[p] = summarize(rows_of[p])
        goals[p] = goal_checks(p, summary[p])
        for rec in json_lines(p, summary[p], goals[p]):
            print(json.dumps(rec))
        text.append(format_summary(p, summary[p], goals[p]))
    for p in profiles:   # every target's figures and checks (the tool's too), after all the tool's former lines
        summary[p]["targets"] = {t: target_summary(rs) for t, rs in by_target[p].items()}
        checks[p] = [c for t, rs in by_target[p].items()
                     for c in target_goal_checks(p, t, rs, summary[p]["targets"][t]["nees"])]
        for t, ts in summary[p]["targets"].items():
            mine = [c for c in checks[p] if c["target"] == t]
            for rec in target_json_lines(p, t, ts) + target_goal_lines(mine):
                print(json.dumps({**rec, "profile": p, "seeds": len(ts["seeds"])}))
            text.append(format_target(p, t, ts, mine))
    print()
    print("\n\n".join(text))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"profiles": list(profiles), "seeds": seeds, "fusion_config": args.fusion_config,
                       "noise_model": {"mode": args.noise_model,
                                       **({"calibration_seeds": cal_seeds} if args.noise_model == "calibrated" else {}),
                           **{p: noise[p]["noise_model"] for p in profiles}},
                       "twin_hash": keys, "summary": summary, "goals": goals,
                       "targets": {p: list(by_target[p]) for p in profiles}, "target_goals": checks,
                       "task_seeds": [x for p in profiles for x in every_of[p]]}, f, indent=1, default=float)
            f.write("\n")
        print(f"wrote {args.json}")
    print(f"accuracy: {len(jobs)} profile-seeds in {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
