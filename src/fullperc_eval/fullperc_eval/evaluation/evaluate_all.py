"""``make eval``: evaluate every bag in a directory, print the six-row Table 1 (+ Table 2), write one JSON.

    python -m fullperc_eval.evaluation.evaluate_all --bags bags --json bags/eval.json [--reports DIR] [--quiet]
                                                    [--targets tool instrument | --targets all] [--per-sample]

A bag is any sub-directory with a ``metadata.yaml``; rows come in the paper's task order (G-B-P, P-G-B,
P-G-B-P, P-B-G, B-G-P, P-B-G-P), other bags after them by name. The JSON is::

    {"tasks": [{"task": "G-B-P", "bag": "bags/G-B-P", "mae_mm": {"omc": .., "kf": .., "bkf": .., "ckf": ..,
                "cbkf": ..}, "b_to_p": {"max_mm": {...}, "median_mm": {...}, ...} | null, ...}, ...],
     "paper": {...the paper's Table 1 and 2, for comparison...}}

with every figure of :func:`fullperc_eval.evaluation.metrics.evaluate_bag` per task (MAE on common stamps, by region,
segments, ...). After the tables it compares with the paper: the CBKF/OMC MAE ratio per task, and whether the
method ordering of the paper (OMC worst, CBKF <= CKF, CKF < KF, BKF <= KF) holds.

Targets: by default only the arm-held ``tool`` -- the paper's target, the one the tables and the comparison above are
about. ``--targets`` adds others (``all``: every target with simulator truth ``/sim/truth/<target>`` in a bag, e.g. the
twin's hand-held ``instrument``): their rows follow in Table 1 as ``<task> <target>`` and go to the JSON under
``"targets": {"<target>": [rows]}``; ``"tasks"`` and ``"comparison"`` stay the tool's.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.reader import BagReader

from .config import EvaluationError
from .ground_truth import ARM_TARGET, TRUTH_PREFIX
from .metrics import evaluate_bag
from .report import write_report
from .tables import format_table1, format_table2, write_json

TASK_ORDER = ("G-B-P", "P-G-B", "P-G-B-P", "P-B-G", "B-G-P", "P-B-G-P")
PAPER_TABLE1 = {  # Sensors 2023, 23(20), 8637, Table 1: MAE [mm], columns OMC KF BKF CKF CBKF
    "G-B-P": (3.39, 1.84, 1.82, 1.64, 1.63), "P-G-B": (3.00, 1.99, 1.98, 1.99, 1.98),
    "P-G-B-P": (3.94, 2.61, 2.59, 1.85, 1.85), "P-B-G": (3.79, 2.02, 2.02, 2.02, 2.02),
    "B-G-P": (3.79, 2.14, 2.13, 1.82, 1.82), "P-B-G-P": (3.81, 2.21, 2.20, 1.77, 1.76)}
PAPER_METHODS = ("omc", "kf", "bkf", "ckf", "cbkf")   # the paper's columns: its tables and checks use these only
PAPER_TABLE2 = {"task": "G-B-P", "max_mm": (6.36, 8.32, 6.76, 2.02, 2.02), "median_mm": (5.81, 5.77, 5.56, 0.25, 0.25)}


def portable_path(path: str) -> str:
    """A config file as the JSON records it, the same on every machine: ``package://<pkg>/<file>`` for a file in
    an installed package's share directory (``.../share/<pkg>/<file>``, e.g. fusion_node's default params file),
    else relative to the current directory (the repository root under ``make eval``) when it lies below it, else
    as given."""
    m = re.search(r"(?:^|/)share/([^/]+)/(.+)$", path.replace(os.sep, "/"))
    if m and os.path.isabs(path):
        return f"package://{m.group(1)}/{m.group(2)}"
    rel = os.path.relpath(path) if os.path.isabs(path) else path
    return path if rel.startswith("..") else rel


def find_bags(root: str | Path) -> list[Path]:
    root = Path(root)
    if not root.is_dir():
        raise EvaluationError(f"bag directory {str(root)!r} does not exist (run `make dataset` first)")
    bags = [p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / "metadata.yaml").is_file()]
    rank = {t: i for i, t in enumerate(TASK_ORDER)}
    return sorted(bags, key=lambda p: (rank.get(p.name, len(rank)), p.name))


def bag_targets(bag: Path, wanted: list[str]) -> list[str]:
    """The targets to evaluate in ``bag``: ``wanted`` as given, or for ``all`` the arm-held tool plus every target
    whose simulator truth (``/sim/truth/<target>``) the bag holds."""
    if wanted != ["all"]:
        return wanted
    topics = BagReader(bag).topics
    prefix = TRUTH_PREFIX + "/"
    return [ARM_TARGET] + sorted(t[len(prefix):] for t in topics if t.startswith(prefix) and topics[t].count)


def ordering_checks(mae: dict[str, float]) -> dict[str, bool]:
    """The qualitative claims of the paper's Table 1, checked on one row."""
    return {"omc_worst": all(mae["omc"] > mae[m] for m in PAPER_METHODS if m != "omc"),
            "cbkf_le_ckf": mae["cbkf"] <= mae["ckf"] + 1e-9,
            "ckf_lt_kf": mae["ckf"] < mae["kf"],
            "bkf_le_kf": mae["bkf"] <= mae["kf"] + 1e-9}


def paper_comparison(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for r in rows:
        mae = r["mae_mm"]
        if any(mae.get(m) is None for m in PAPER_METHODS):
            continue
        c = {"task": r["task"], "cbkf_over_omc": mae["cbkf"] / mae["omc"], "checks": ordering_checks(mae)}
        if r["task"] in PAPER_TABLE1:
            p = dict(zip(PAPER_METHODS, PAPER_TABLE1[r["task"]], strict=True))
            c["paper_cbkf_over_omc"] = p["cbkf"] / p["omc"]
            c["paper_checks"] = ordering_checks(p)
        out.append(c)
    return out


def format_comparison(comp: list[dict[str, Any]]) -> str:
    lines = ["Comparison with the paper (Table 1): CBKF/OMC MAE ratio; ordering checks "
             "(OMC worst | CBKF<=CKF | CKF<KF | BKF<=KF), ours vs paper",
             f"{'task':<10}{'ours':>7}{'paper':>7}   checks ours      checks paper"]
    yn = lambda d: " ".join("y" if v else "n" for v in d.values())  # noqa: E731
    for c in comp:
        lines.append(f"{c['task']:<10}{c['cbkf_over_omc']:7.2f}{c.get('paper_cbkf_over_omc', float('nan')):7.2f}"
                     f"   {yn(c['checks']):<16} {yn(c['paper_checks']) if 'paper_checks' in c else '-'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.evaluation.evaluate_all",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--bags", default="bags", help="directory holding one bag per task (default: bags)")
    ap.add_argument("--json", default=None, help="write all figures to this JSON file (make eval: bags/eval.json)")
    ap.add_argument("--reports", default=None, help="also write a report (plots, HTML) per bag into DIR/<task>/")
    ap.add_argument("--quiet", action="store_true", help="no progress output")
    ap.add_argument("--targets", nargs="+", default=[ARM_TARGET], metavar="TARGET",
                    help=f"targets to evaluate in each bag (default: {ARM_TARGET}; 'all': the tool and every target "
                         f"with {TRUTH_PREFIX}/<target> in the bag)")
    ap.add_argument("--per-sample", action="store_true",
                    help="replay one message at a time (the reference) instead of the batched replay (same result)")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    rows: list[dict[str, Any]] = []
    others: dict[str, list[dict[str, Any]]] = {}
    try:
        bags = find_bags(args.bags)
        if not bags:
            raise EvaluationError(f"no bags (directories with metadata.yaml) in {args.bags!r}; run `make dataset`")
        for bag in bags:
            for target in bag_targets(bag, args.targets):
                t1 = time.monotonic()
                ev = evaluate_bag(bag, progress=not args.quiet, target=target, per_sample=args.per_sample)
                r = ev.result
                r["bag"] = os.path.relpath(bag)
                (rows if target == ARM_TARGET else others.setdefault(target, [])).append(r)
                if args.reports:
                    sub = bag.name if target == ARM_TARGET else f"{bag.name}-{target}"
                    write_report(ev, Path(args.reports) / sub)
                if not args.quiet:
                    print(f"  {bag.name} {target}: {r['messages']} messages in {time.monotonic() - t1:.1f} s",
                          file=sys.stderr)
    except (EvaluationError, BagError) as e:
        print("error: " + " ".join(str(e).split()), file=sys.stderr)
        return 1
    print(format_table1(rows + [r for rs in others.values() for r in rs]))
    print()
    for r in rows:
        if r.get("b_to_p"):
            print(format_table2(r))
            print()
    comp = paper_comparison(rows)
    print(format_comparison(comp))
    every = rows + [r for rs in others.values() for r in rs]
    for r in every:
        for w in r["warnings"]:
            print(f"warning: {r['task']}: {w}", file=sys.stderr)
    if args.json:
        config = next((r["config"] for r in every if "config" in r), None)   # the same for every bag: kept once
        for key in ("fusion_config", "layout"):
            if config and isinstance(config.get(key), str) and config[key] != "<given>":
                config[key] = portable_path(config[key])
        for r in every:
            r.pop("config", None)
        extra = {"targets": others} if others else {}
        paper = {"table1_mae_mm": {t: dict(zip(PAPER_METHODS, v, strict=True)) for t, v in PAPER_TABLE1.items()},
                 "table2_b_to_p_mm": {"task": PAPER_TABLE2["task"],
                                      **{k: dict(zip(PAPER_METHODS, PAPER_TABLE2[k], strict=True))
                                         for k in ("max_mm", "median_mm")}}}
        write_json(args.json, {"tasks": rows, **extra, "config": config, "comparison": comp, "paper": paper})
        print(f"wrote {args.json}")
    print(f"evaluated {len(bags)} bags ({len(every)} target rows) in {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
