"""``make twin-report``: the raw-sensor statistics of a twin profile next to its targets (no filter involved).

    python -m fullperc_eval.evaluation.twin_report --profile paper [--seeds 0-1] [--tasks ...] [--json FILE]
                                                   [--store DIR]

A profile (``fullperc_eval/config/profile_<name>.yaml``) is calibrated on these figures only, never on filter
results. Per task and seed the simulator's arrays are compared with its truth:

* **OMC chain** (what Table 1's OMC column measures): the tool in ``base`` as the pass-through gives it,
  inv(T̂_omc_base) · T_omc_tool, with T̂_omc_base the chordal mean of the first ``init_samples`` OMC sightings of the
  base marker (``static_links: average``), against the true path. MAE, by region (true label), the B->P segment
  (last B sample to the end of the following P run: Table 2) median/max, and the frame-to-frame jumps of the error
  vector between consecutive tracked frames (Fig. 4): all, and where the set of rays (cameras x markers) changed.
* **Vega**: per-frame position error RMS of the tool (inside the volume) and of the base marker, the base marker's
  per-frame orientation error, and the error of the static base->OTS link averaged from its first
  ``init_samples`` frames (position, rotation).
* **Local chain** inv(T̂_ots_base) · T_ots_tool (eq. 2 with that averaged link) against the truth: MAE over the
  Vega's tool frames and the median tool--base-marker lever.

Targets (``targets:`` of the profile file) are ``[low, high]`` ranges on the named figures (module constant
:data:`TARGET_FIGURES` says which figure each name checks).

``--store bags`` (what ``make twin-report`` does with its default seeds) writes each profile's rows to
``bags/<profile>/twin_report.json`` with the profile's ``twin_hash`` (the hash of its scene configuration and plans):
the test suite checks the targets on those rows, ties them to the committed bags (seed 0, every figure a bag holds)
and to today's simulator (one task simulated again), instead of simulating two seeds of twelve tasks in every run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_common.runs import runs
from fullperc_common.transforms import inv_T, make_T, mean_T
from fullperc_eval.sim.runner import run_task
from fullperc_eval.sim.scene import PROFILES, load_profile, load_scene_config
from fullperc_eval.sim.tasks import TASKS, default_plans_path, plans_file_of

INIT_SAMPLES = 30   # fusion.yaml's init_samples (static_links: average)
DEFAULT_SEEDS = "0-1"   # the report's default seeds (the Makefile's too); test_twin_profiles pins the profiles on them
# target name -> (figure key in a task row, how rows are combined, what it says)
TARGET_FIGURES = {
    "omc_mae_mm": ("omc_mae_mm", "each", "OMC chain MAE per task (mean over seeds)"),
    "omc_mae_all_mm": ("omc_mae_mm", "mean", "OMC chain MAE, mean over tasks and seeds"),
    "b_to_p_median_mm": ("omc_b_to_p_median_mm", "gbp", "OMC B->P median, G-B-P (mean over seeds)"),
    "b_to_p_max_mm": ("omc_b_to_p_max_mm", "gbp", "OMC B->P max, G-B-P (mean over seeds)"),
    "jump_median_set_change_mm": ("jump_set_change_median_mm", "mean", "OMC jump at a ray-set change, median"),
    "jump_max_mm": ("jump_max_mm", "mean", "largest OMC frame-to-frame jump per task (mean over tasks/seeds)"),
    "vega_tool_rms_mm": ("vega_tool_rms_mm", "mean", "Vega tool position RMS error"),
    "vega_base_rms_mm": ("vega_base_rms_mm", "mean", "Vega base-marker position RMS error"),
}


def _T(p, q) -> np.ndarray:
    return make_T(p, q / np.linalg.norm(q))


def _first_mean(pos: np.ndarray, quat: np.ndarray, ok: np.ndarray, n: int) -> np.ndarray | None:
    idx = np.flatnonzero(ok)[:n]
    if len(idx) < n:
        return None
    return mean_T([_T(pos[i], quat[i]) for i in idx])


def _rot_err_mrad(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    return np.linalg.norm(Rotation.from_matrix(np.einsum("...ji,...jk->...ik", Ra, Rb)).as_rotvec(), axis=-1) * 1e3


def task_stats(run, init_samples: int = INIT_SAMPLES) -> dict[str, Any]:
    """Raw-sensor error figures of one simulated run (see the module docstring)."""
    st = run.static
    out: dict[str, Any] = {"task": run.task, "seed": int(run.seed)}
    # ---- OMC chain in base
    b, tb = run.omc.bodies["tool"], run.omc.bodies["base"]
    T_ob = _first_mean(tb.position, tb.quat_xyzw, tb.tracked, init_samples)
    ok = b.tracked
    if T_ob is not None and ok.any():
        Tbo = inv_T(T_ob)
        p = b.position @ Tbo[:3, :3].T + Tbo[:3, 3]
        ev = p - run.truth.T_base_tool[:, :3, 3]          # (F, 3), NaN where not tracked
        e = np.linalg.norm(ev, axis=1) * 1e3
        out["omc_mae_mm"] = float(np.nanmean(e))
        reg = run.truth.region
        for k, name in ((1, "BVV"), (2, "GVV"), (3, "PVV")):
            sel = ok & (reg == k)
            out[f"omc_mae_{name}_mm"] = float(e[sel].mean()) if sel.any() else None
        r = runs(reg)
        bp = next(((ea, eb) for (la, _, ea), (lb, _, eb) in zip(r, r[1:], strict=False) if la == 1 and lb == 3), None)
        if bp is not None:
            seg = e[bp[0]:bp[1] + 1]
            seg = seg[np.isfinite(seg)]
            out["omc_b_to_p_median_mm"] = float(np.median(seg)) if seg.size else None
            out["omc_b_to_p_max_mm"] = float(seg.max()) if seg.size else None
        pair = ok[1:] & ok[:-1]
        jumps = np.linalg.norm(np.diff(ev, axis=0), axis=1)[pair] * 1e3
        changed = (b.rays[1:] != b.rays[:-1])[pair]
        out["jump_median_mm"] = float(np.median(jumps)) if jumps.size else None
        out["jump_set_change_median_mm"] = float(np.median(jumps[changed])) if changed.any() else None
        out["jump_max_mm"] = float(jumps.max()) if jumps.size else None
        out["jump_share_over_2mm"] = float(np.mean(jumps > 2.0)) if jumps.size else None
        out["omc_tracked_share"] = float(ok.mean())
    # ---- Vega
    T_ots_omc = inv_T(st["T_omc_ots"])
    vt, vb = run.ots.tools["tool"], run.ots.tools["base"]
    true_tool_ots = T_ots_omc @ run.truth_ots.T_omc_tool
    if vt.visible.any():
        d = np.linalg.norm(vt.position[vt.visible] - true_tool_ots[vt.visible, :3, 3], axis=1) * 1e3
        out["vega_tool_rms_mm"] = float(np.sqrt(np.mean(d**2)))
        out["vega_tool_share"] = float(vt.visible.mean())
    T_ots_base_true = T_ots_omc @ st["T_omc_base"]
    if vb.visible.any():
        pv = vb.position[vb.visible]
        out["vega_base_rms_mm"] = float(np.sqrt(np.mean(np.sum((pv - T_ots_base_true[:3, 3]) ** 2, axis=1)))) * 1e3
        Rv = Rotation.from_quat(vb.quat_xyzw[vb.visible]).as_matrix()
        out["vega_base_rot_mrad"] = float(np.median(_rot_err_mrad(Rv, T_ots_base_true[:3, :3])))
        out["vega_base_range_m"] = float(np.linalg.norm(T_ots_base_true[:3, 3]))
    T_vb = _first_mean(vb.position, vb.quat_xyzw, vb.visible, init_samples)
    if T_vb is not None:
        out["link_pos_err_mm"] = float(np.linalg.norm(T_vb[:3, 3] - T_ots_base_true[:3, 3]) * 1e3)
        out["link_rot_err_mrad"] = float(_rot_err_mrad(T_vb[:3, :3], T_ots_base_true[:3, :3]))
        if vt.visible.any():
            Tbv = inv_T(T_vb)
            p = vt.position[vt.visible] @ Tbv[:3, :3].T + Tbv[:3, 3]
            true_b = run.truth_ots.T_base_tool[vt.visible, :3, 3]
            out["local_chain_mae_mm"] = float(np.mean(np.linalg.norm(p - true_b, axis=1)) * 1e3)
            out["lever_m"] = float(np.median(np.linalg.norm(true_b, axis=1)))
    return out


def _combine(rows: list[dict[str, Any]], key: str, how: str) -> list[tuple[str, float]]:
    """(label, value) pairs a target is checked on: per task (mean over seeds), overall mean, or G-B-P only."""
    def mean(rs):
        v = [r[key] for r in rs if r.get(key) is not None]
        return float(np.mean(v)) if v else float("nan")
    if how == "each":
        return [(t, mean([r for r in rows if r["task"] == t])) for t in dict.fromkeys(r["task"] for r in rows)]
    if how == "gbp":
        g = [r for r in rows if r["task"] == "G-B-P"]
        return [("G-B-P", mean(g))] if g else []
    return [("all", mean(rows))]


def check_targets(rows: list[dict[str, Any]], targets: dict[str, list[float]]) -> list[dict[str, Any]]:
    """One entry per checked value: target name, label, value, [low, high], ok."""
    out = []
    for name, (lo, hi) in targets.items():
        key, how, _ = TARGET_FIGURES[name]
        for label, v in _combine(rows, key, how):
            out.append({"target": name, "of": label, "value": v, "range": [lo, hi],
                        "ok": bool(np.isfinite(v) and lo <= v <= hi)})
    return out


COLUMNS = (("omc_mae_mm", "OMC"), ("omc_mae_BVV_mm", "B"), ("omc_mae_GVV_mm", "G"), ("omc_mae_PVV_mm", "P"),
           ("omc_b_to_p_median_mm", "BPmed"), ("omc_b_to_p_max_mm", "BPmax"), ("jump_median_mm", "jmp50"),
           ("jump_set_change_median_mm", "jmpSet"), ("jump_max_mm", "jmpMax"), ("vega_tool_rms_mm", "VgTool"),
           ("vega_base_rms_mm", "VgBase"), ("vega_base_rot_mrad", "VgRot"), ("link_rot_err_mrad", "LnkRot"),
           ("link_pos_err_mm", "LnkPos"), ("local_chain_mae_mm", "Local"), ("lever_m", "lever"))


def format_report(profile: str, rows: list[dict[str, Any]], checks: list[dict[str, Any]]) -> str:
    seeds = sorted({r["seed"] for r in rows})
    lines = [f"twin-report: profile {profile}, seeds {seeds} (raw sensors only; mm, mrad, m; mean over seeds)",
             "  OMC = OMC chain MAE in base (B/G/P by true region); BPmed/BPmax = B->P segment; jmp = frame-to-frame",
             "  error jumps (median, median at a ray-set change, max); Vg = Vega RMS / base orientation (median per",
             "  frame); Lnk = error of the base->OTS link averaged from the first 30 frames; Local = local chain MAE",
             f"{'task':<9}" + "".join(f"{h:>7}" for _, h in COLUMNS)]
    for t in dict.fromkeys(r["task"] for r in rows):
        rs = [r for r in rows if r["task"] == t]
        vals = []
        for k, _ in COLUMNS:
            v = [r[k] for r in rs if r.get(k) is not None]
            vals.append(f"{np.mean(v):7.2f}" if v else f"{'-':>7}")
        lines.append(f"{t:<9}" + "".join(vals))
    lines.append("targets:")
    for c in checks:
        lines.append(f"  {'ok  ' if c['ok'] else 'MISS'} {c['target']:<26} {c['of']:<8} {c['value']:7.2f}  "
                     f"in [{c['range'][0]:g}, {c['range'][1]:g}]  ({TARGET_FIGURES[c['target']][2]})")
    return "\n".join(lines)


def parse_seeds(text: str) -> list[int]:
    """"0-9" -> [0..9]; "0,3,5" -> [0, 3, 5]; "4" -> [4]."""
    out: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-", 1)
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    if not out:
        raise ValueError(f"no seeds in {text!r}")
    return out


def report(profile: str, seeds: list[int], tasks=TASKS, log=None) -> dict[str, Any]:
    rows = []
    for s in seeds:
        t0 = time.monotonic()
        for t in tasks:
            rows.append(task_stats(run_task(t, seed=s, profile=profile)))
        if log:
            log(f"  profile {profile} seed {s}: {len(tasks)} tasks in {time.monotonic() - t0:.1f} s")
    prof = load_profile(profile)
    checks = check_targets(rows, prof.get("targets") or {})
    return {"profile": profile, "seeds": seeds, "rows": rows, "checks": checks,
            "all_ok": all(c["ok"] for c in checks)}


def twin_hash(profile: str) -> str:
    """Hash of what a profile's bags depend on: the merged scene configuration and its plans file."""
    cfg = load_scene_config(profile=profile)
    cfg = {k: v for k, v in cfg.items() if k != "_source"}

    class _S:   # plans_file_of only reads .config
        config = cfg
    plans = default_plans_path(plans_file_of(_S))
    text = plans.read_text() if plans is not None else ""
    return hashlib.sha256(json.dumps([cfg, text], sort_keys=True, default=str).encode()).hexdigest()[:12]


STORE_NAME = "twin_report.json"


def store(path: Path, rep: dict[str, Any]) -> None:
    """Write a report's rows with the profile's twin_hash (what the committed rows were made with)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"profile": rep["profile"], "twin_hash": twin_hash(rep["profile"]), "seeds": rep["seeds"],
           "tasks": list(dict.fromkeys(r["task"] for r in rep["rows"])), "rows": rep["rows"]}
    path.write_text(json.dumps(doc, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.evaluation.twin_report",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--profile", default="both", choices=(*PROFILES, "both"))
    ap.add_argument("--seeds", default=DEFAULT_SEEDS, help=f"e.g. 0-9 or 0,3 (default {DEFAULT_SEEDS})")
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS, metavar="TASK")
    ap.add_argument("--json", default=None, help="also write the figures here")
    ap.add_argument("--store", default=None, metavar="DIR",
                    help="write DIR/<profile>/twin_report.json (rows and twin_hash; default seeds and all tasks only)")
    args = ap.parse_args(argv)
    profiles = PROFILES if args.profile == "both" else (args.profile,)
    if args.store and (parse_seeds(args.seeds) != parse_seeds(DEFAULT_SEEDS) or tuple(args.tasks) != tuple(TASKS)):
        ap.error(f"--store keeps the default seeds ({DEFAULT_SEEDS}) and every task only")
    out = []
    for p in profiles:
        rep = report(p, parse_seeds(args.seeds), args.tasks, log=lambda m: print(m, file=sys.stderr, flush=True))
        print(format_report(p, rep["rows"], rep["checks"]))
        print()
        out.append(rep)
        if args.store:
            store(Path(args.store) / p / STORE_NAME, rep)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0 if all(r["all_ok"] for r in out) else 1


if __name__ == "__main__":
    sys.exit(main())
