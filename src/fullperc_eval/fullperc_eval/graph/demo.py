"""`make demo`: the whole fullperc graph on the simulated OR, then the evaluation of what it recorded.

Runs ``config/demo_graph.yaml`` with the :mod:`.supervisor` -- simulator (NDI Vega emulator on TCP, NOKOV-like
OMC and Diana UDP streams), ``omc_driver``, ``ndi_driver``, ``diana_state``, ``fusion_node`` (CBKF plus CKF,
BKF, KF and the OMC pass-through side by side), ``margin_node`` and ``record`` as separate processes on a
private DDS domain over localhost -- for one task, prints the region changes ``margin_node`` reports live,
shuts everything down, and then evaluates the recorded bag twice:

* **offline**: ``evaluate`` re-runs all five methods over the recorded raw driver topics;
* **live**: the fused poses ``fusion_node`` actually published (``evaluate --live``).

Both are compared with the Diana's ground truth (forward kinematics of the recorded joint states and the
simulator's calibration). The report (plots, HTML, JSON) goes to ``<out>/report``.

Only a bag of a task that ran to its end is evaluated: after Ctrl-C (or when a process failed) the bag holds part
of the task, and MAE figures of a part would look like the task's. The demo then says so, names the bag and the
command that evaluates it anyway, and exits non-zero (130 after Ctrl-C).
"""

from __future__ import annotations

import os
import shutil
import socket
import sys
import time
from pathlib import Path

from fullperc_eval.evaluation.config import EvaluationError
from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_eval.evaluation.report import write_report
from fullperc_eval.evaluation.tables import format_table1, format_table2, write_json

from .supervisor import execute_graph


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def graph_path(root: Path) -> Path:
    for cand in (root / "install/fullperc_eval/share/fullperc_eval/config/demo_graph.yaml",
                 root / "src/fullperc_eval/config/demo_graph.yaml"):
        if cand.exists():
            return cand
    raise FileNotFoundError("demo_graph.yaml not found (is the workspace built?)")


def run_demo(task: str, seed: str, out: Path, root: Path, speed: str = "1.0",
             extra: dict[str, str] | None = None, graph: Path | None = None) -> int:
    out = out / f"{task}-{time.strftime('%Y%m%d-%H%M%S')}"
    out.mkdir(parents=True, exist_ok=False)
    os.environ.setdefault("ROS_DOMAIN_ID", str(101 + os.getpid() % 100))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    values = {"task": task, "seed": str(seed), "out": str(out.resolve()), "speed": str(speed),
              "omc_port": str(_free_port(socket.SOCK_DGRAM)), "diana_port": str(_free_port(socket.SOCK_DGRAM)),
              "vega_port": str(_free_port(socket.SOCK_STREAM)), **(extra or {})}
    print(f"demo: task {task}, seed {seed}, output {out}, ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}", flush=True)
    t0 = time.monotonic()
    outcome = execute_graph(graph or graph_path(root), values, out / "logs", root)
    rc = outcome.rc
    bag = out / "bag"
    if not (bag / "metadata.yaml").exists():
        print(f"demo: no bag was recorded (graph exit {rc}); logs in {out / 'logs'}", file=sys.stderr)
        return 128 + outcome.interrupted if outcome.interrupted else 1
    if outcome.interrupted or not outcome.completed:
        state = "ran to its end" if outcome.completed else f"did not finish: {outcome.reason}"
        print(f"\ndemo: not evaluating: the task {state}; the bag {bag} is "
              f"{'complete' if outcome.completed else 'PARTIAL (only part of the task)'}. "
              f"Evaluate it anyway with: evaluate {bag}\n(logs in {out / 'logs'})", file=sys.stderr)
        return 128 + outcome.interrupted if outcome.interrupted else (rc or 1)
    cal = out / "calibration.yaml"
    if cal.exists():
        shutil.copy(cal, bag / "calibration.yaml")
    print(f"\ndemo: graph finished in {time.monotonic() - t0:.0f} s; evaluating {bag}", flush=True)
    try:
        offline = evaluate_bag(bag, progress=False)
        live = evaluate_bag(bag, progress=False, live=True)
    except EvaluationError as e:
        print(f"demo: evaluation failed: {e}", file=sys.stderr)
        return 1
    off, liv = offline.result, live.result
    off["task"] = f"{task} offline"
    liv["task"] = f"{task} live"
    print("\nMAE [mm] against the Diana ground truth (offline = evaluate over the recorded raw topics; "
          "live = the poses fusion_node published):")
    print(format_table1([off, liv]))
    if off.get("b_to_p"):
        print()
        print(format_table2(off))
    for w in off["warnings"]:
        print(f"warning: {w}")
    index = write_report(offline, out / "report")
    write_json(out / "report" / "eval.json", off)
    write_json(out / "report" / "eval_live.json", liv)
    print(f"\nreport: {index}")
    print(f"bag:    {bag}  (evaluate again: evaluate {bag})")
    return rc
