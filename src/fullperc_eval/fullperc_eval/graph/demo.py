"""`make demo`: the whole fullperc graph on the simulated OR, then the evaluation of what it recorded.

Runs ``config/demo_graph.yaml`` with the :mod:`.supervisor` -- simulator (NDI Vega emulator on TCP, NOKOV-like
OMC and Diana UDP streams), ``omc_driver``, ``ndi_driver``, ``diana_state``, ``fusion_node`` (CBKF plus CKF,
BKF, KF and the OMC pass-through side by side), ``margin_node`` and ``record`` as separate processes on a
private DDS domain over localhost -- for one task, prints the region changes ``margin_node`` reports live,
shuts everything down, and then evaluates the recorded bag twice:

* **offline**: ``evaluate`` re-runs all five methods over the recorded raw driver topics;
* **live**: the fused poses ``fusion_node`` actually published (``evaluate --live``).

Two targets are fused, labelled and recorded: the arm-held ``tool`` and the twin's hand-held ``instrument`` (a staff
member walks it through the room, :mod:`fullperc_eval.sim.walker`). The tool is compared with the Diana's ground truth
(forward kinematics of the recorded joint states and the simulator's calibration); the instrument, which has no
robot, with the simulator's truth, which the simulator writes to ``<out>/truth`` and the demo merges into the bag
(``/sim/truth/instrument``, a second storage file of the bag). The reports (plots, HTML, JSON) go to
``<out>/report`` (tool) and ``<out>/report/instrument``.

``profile`` picks the twin profile the simulator plays (``paper`` or ``spec``: ``make demo PROFILE=spec``);
``calibration`` a static-link calibration YAML (written by ``calibrate`` or ``~/calibrate``) that ``fusion_node``
loads instead of calibrating itself, and that the offline evaluation uses too, so offline and live stay comparable
(``make demo CALIBRATION=or1.yaml``).

``fusion_node`` also gets ``tf.diana_base``, the arm's base in ``base``, so that in RViz the Diana's link tree
(``diana_state``'s /tf, rooted at ``diana_base``) hangs under ``base`` with the fused targets. In a real OR that
transform comes from a hand-eye calibration; here it is the simulator's own, computed before the graph starts
from the same task plan the simulator makes (:func:`sim_diana_base`; deterministic in task, seed and profile).

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

import yaml

from fullperc_common.ports import free_port
from fullperc_common.transforms import T_to_pq, inv_T
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.evaluation.config import EvaluationError
from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_eval.evaluation.report import write_report
from fullperc_eval.evaluation.tables import format_table1, format_table2, write_json
from fullperc_eval.sim.dataset import TRUTH_PREFIX, merge_bag
from fullperc_eval.sim.scene import build_scene
from fullperc_eval.sim.tasks import TaskPlanningError, plan_task

from .supervisor import execute_graph


def graph_path(root: Path) -> Path:
    for cand in (root / "install/fullperc_eval/share/fullperc_eval/config/demo_graph.yaml",
                 root / "src/fullperc_eval/config/demo_graph.yaml"):
        if cand.exists():
            return cand
    raise FileNotFoundError("demo_graph.yaml not found (is the workspace built?)")


# [s] the demo's fusion_node keeps this much history (``history``, demo_graph.yaml): a sample up to this late is
# still fused in order.
LIVE_HISTORY_S = 3.0
# [s] ``reorder_delay`` of the demo's fusion_node *and* of the offline evaluation of its recording. The offline replay
# reads the bag in the recorder's receive order and waits this long for a late sample: on a busy 2-core machine the
# recorder falls behind more than the node (a CI run: 157 instrument OMC samples received up to 1.7 s behind the
# newest stamp, dropped as late at 1.0 s, live and offline MAE 0.09 mm apart). On arrival the node fuses at once and
# this delay only says when an item's static links are settled (pipeline/arrival.py); the two must be equal, or the
# items of the first second and around the end of the link calibration are mapped with different links (a run with
# the node's default 0.05 s: the node never output the first 22 OMC items, and its bias states drifted 0.05-0.1 mm
# in MAE from the offline ones). Below LIVE_HISTORY_S: an item's links are settled before it leaves the history.
DEMO_REORDER_S = 2.5
# The demo runs the paper's filters side by side, which have one motion model each: the hand-held instrument gets
# the `hand` preset (fullperc would weigh its own: motion auto). demo_graph.yaml and demo.launch.py pass it with -p,
# fusion_params_with writes it for the offline evaluation (test_launch_matches_graph keeps the three equal).
DEMO_TARGET_PARAMS = {"instrument.motion": "hand"}


def fusion_params_with(calibration: Path | None, out: Path) -> Path:
    """fusion_node's installed params file for the offline evaluation of the demo's recording, written to
    ``out/fusion.yaml``: ``reorder_delay`` = :data:`DEMO_REORDER_S` (the node's), :data:`DEMO_TARGET_PARAMS`, and
    with ``calibration`` its
    ``calibration_file`` (the evaluation must run with the links the live node loaded)."""
    from fullperc_fusion.fusion_config import default_fusion_config_path, node_key

    doc = yaml.safe_load(default_fusion_config_path().read_text()) or {}
    params = doc.setdefault(node_key(doc), {}).setdefault("ros__parameters", {})
    params["reorder_delay"] = DEMO_REORDER_S
    for name, value in DEMO_TARGET_PARAMS.items():
        target, key = name.split(".")
        params.setdefault(target, {})[key] = value
    if calibration is not None:
        params["calibration_file"] = str(calibration)
    path = out / "fusion.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def sim_diana_base(task: str, seed: str | int, profile: str) -> list[float]:
    """T_base_diana_base [x y z qx qy qz qw] of the simulated run (task, seed, profile): the arm's base as the
    simulator's task plan places it, relative to the base marker (what ``sim --calibration-out`` writes)."""
    scene = build_scene(int(seed), profile=profile)
    T = inv_T(scene.T_omc_base) @ plan_task(task, scene).T_omc_diana_base
    p, q = T_to_pq(T)
    return [float(v) for v in (*p, *q)]


def run_demo(task: str, seed: str, out: Path, root: Path, speed: str = "1.0",
             extra: dict[str, str] | None = None, graph: Path | None = None, profile: str = "paper",
             calibration: Path | None = None) -> int:
    if calibration is not None and not Path(calibration).is_file():
        print(f"demo: calibration file {calibration} does not exist", file=sys.stderr)
        return 2
    out = out / f"{task}-{time.strftime('%Y%m%d-%H%M%S')}"
    out.mkdir(parents=True, exist_ok=False)
    extra = dict(extra or {})
    if calibration is not None:
        calibration = Path(calibration).resolve()
        extra["calibration_file"] = str(calibration)
    fusion_config = fusion_params_with(calibration, out)
    os.environ.setdefault("ROS_DOMAIN_ID", str(101 + os.getpid() % 100))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    values = {"task": task, "seed": str(seed), "out": str(out.resolve()), "speed": str(speed),
              "omc_port": str(free_port(socket.SOCK_DGRAM)), "diana_port": str(free_port(socket.SOCK_DGRAM)),
              "vega_port": str(free_port(socket.SOCK_STREAM)), "profile": profile}
    try:
        values["diana_base"] = "[" + ", ".join(repr(v) for v in sim_diana_base(task, seed, profile)) + "]"
    except (ValueError, KeyError, TaskPlanningError) as e:   # the simulator will say the same, in its own log
        print(f"demo: no arm base for /tf_static: {e}", file=sys.stderr, flush=True)
    values.update(extra)
    print(f"demo: task {task}, seed {seed}, profile {profile}, output {out}, "
          f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}"
          + (f", static links from {calibration}" if calibration else ""), flush=True)
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
    truth = out / "truth"
    targets = ["tool"]
    if (truth / "metadata.yaml").exists():   # the hand-held instrument's simulator truth: into the bag
        try:
            merge_bag(bag, truth)
            topics = BagReader(bag).topics   # a twin target the graph did not fuse (the patient reference): no OMC
            targets += sorted(t.rsplit("/", 1)[1] for t in topics if t.startswith(TRUTH_PREFIX + "/")
                              and f"/fullperc/{t.rsplit('/', 1)[1]}/pose" in topics)
        except (BagError, OSError) as e:
            print(f"demo: the second target's truth stays in {truth} ({e}); evaluating the tool only", file=sys.stderr)
    print(f"\ndemo: graph finished in {time.monotonic() - t0:.0f} s; evaluating {bag} (targets {', '.join(targets)})",
          flush=True)
    results = {}
    try:
        for target in targets:
            results[target] = (evaluate_bag(bag, progress=False, fusion_config=fusion_config, target=target),
                               evaluate_bag(bag, progress=False, live=True, fusion_config=fusion_config,
                                            target=target))
    except EvaluationError as e:
        print(f"demo: evaluation failed: {e}", file=sys.stderr)
        return 1
    rows = []
    for target, (offline, live) in results.items():
        off, liv = offline.result, live.result
        name = task if target == "tool" else f"{task} {target}"
        off["task"], liv["task"] = f"{name} offline", f"{name} live"
        rows += [off, liv]
    print("\nMAE [mm] against the ground truth (tool: the Diana's joints; instrument: the simulator's truth; offline = "
          "evaluate over the recorded raw topics; live = the poses fusion_node published):")
    print(format_table1(rows))
    off = results["tool"][0].result
    if off.get("b_to_p"):
        print()
        print(format_table2(off))
    for target, (offline, live) in results.items():
        for w in offline.result["warnings"]:
            print(f"warning: {target}: {w}")
        sub = out / "report" if target == "tool" else out / "report" / target
        index = write_report(offline, sub)
        write_json(sub / "eval.json", offline.result)
        write_json(sub / "eval_live.json", live.result)
        print(f"\nreport: {index}" if target == "tool" else f"report ({target}): {index}")
    print(f"bag:    {bag}  (evaluate again: evaluate {bag} [--target instrument])")
    return rc
