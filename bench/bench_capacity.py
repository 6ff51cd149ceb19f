"""Capacity: the most targets fusion_node sustains at OMC 240 Hz + OTS 400 Hz each (issue 16 item 4).

A step with N targets (``t0`` .. ``tN-1``, each its own OMC body and OTS tool, the default primary filter only)
passes when no target sample is lost (``live_fusion``: every sample after the first second is covered by a fused
pose of its target) and the p99 of publish -> fused pose over all targets is <= 5 ms. The search goes upward
through STEPS (from 2 targets for two processes) and stops at the first failing step (a busy machine fails early
rather than late).

Figures:
  capacity_targets        one fusion_node process
  capacity_targets_2proc  the targets partitioned over two processes (alternately: t0, t2, ... | t1, t3, ...)
Also ``cpu_share_per_target``: the node processes' CPU time while data flowed per second and target (median over
the steps), and ``targets_per_core_by_cpu`` = 1 / that share: how many targets one core could take on CPU time
alone, without the scheduling delays a shared machine adds.
Raw baseline (same run): ``raw_dds_p99_ms``, the p99 of the publisher's /omc/t0/pose received here directly (the
median over the steps) -- a count has no ratio to a latency, so it is a field, not ``baseline``.
each with the per-step results (lost, p99, publisher's achieved rates, the node's drop counters) in ``steps``.

Input dimension: ``capacity_targets[inputs=frames]`` (and ``_2proc``) the same searches with the nodes on
``inputs: frames`` and the publisher sending each device frame as one TrackedBodies besides (``e2e_publisher.py
--frames``: one OMC message carries the base and every target), events executor only.
Executor dimension: each figure is printed once per executor of the nodes (``executor``: ``events`` = the
EventsExecutor, fusion_node's default; ``single`` = rclpy's SingleThreadedExecutor, the baseline;
fullperc_common.executor_choice). The searches run REPEATS times, the executors alternating within a repeat
(their order swapped every repeat, so neither always runs on the busier moment); ``value`` is the median of the
repeats' capacities, ``runs`` lists each, every step carries the load averages of its run.
Run: python bench/bench_capacity.py   (FULLPERC_BENCH_CAP_S: seconds per step, default 6;
FULLPERC_BENCH_CAP_STEPS: e.g. "1,2,4,8,12,16"; FULLPERC_BENCH_EXECUTORS: default "events,single";
FULLPERC_BENCH_REPEATS: default 3; FULLPERC_BENCH_CAP_FRAMES=0: no frames searches)
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import emit  # noqa: E402
from live_fusion import run_live, target_params  # noqa: E402

DURATION = float(os.environ.get("FULLPERC_BENCH_CAP_S", "6"))
STEPS = [int(s) for s in os.environ.get("FULLPERC_BENCH_CAP_STEPS", "1,2,4,8,12,16").split(",") if s]
P99_MAX_MS = 5.0
MIN_RATE = 0.95      # the publisher must reach this share of the device rates, else the step says so
EXECUTORS = [e for e in os.environ.get("FULLPERC_BENCH_EXECUTORS", "events,single").split(",") if e]
REPEATS = int(os.environ.get("FULLPERC_BENCH_REPEATS", "3"))
FRAMES = int(os.environ.get("FULLPERC_BENCH_CAP_FRAMES", "1"))   # 0: no frames searches


def step(n: int, procs: int, executor: str, frames: bool = False) -> dict:
    targets = [f"t{k}" for k in range(n)]
    parts = [targets[i::procs] for i in range(procs) if targets[i::procs]]
    extra = ["-p", "inputs:=frames"] if frames else []
    try:
        res = run_live([target_params(p) + extra for p in parts], targets, None, DURATION, executor=executor,
                       frames=frames)
    except (RuntimeError, subprocess.TimeoutExpired) as e:     # e.g. nodes never subscribed: the step failed
        return {"targets": n, "processes": len(parts), "ok": False, "error": f"{type(e).__name__}: {e}"[:300],
                "lost": None, "samples": None, "p99_ms": None, "raw_p99_ms": None, "publisher_ok": True,
                "nodes_alive": False}
    lat = res.all_latency_ms
    p99 = float(np.percentile(lat, 99)) if len(lat) else float("inf")
    lost = int(sum(res.lost.values()))
    rates = [round(res.publisher["omc_hz"], 1), round(res.publisher["ots_hz"], 1)]
    publisher_ok = rates[0] >= MIN_RATE * 240 and rates[1] >= MIN_RATE * 400
    return {"targets": n, "processes": len(parts), "lost": lost, "samples": int(sum(res.sent.values())),
            "p50_ms": round(float(np.median(lat)), 3) if len(lat) else None,
            "p99_ms": round(p99, 3) if np.isfinite(p99) else None,
            "raw_p99_ms": round(float(np.percentile(res.raw_latency_ms, 99)), 3) if len(res.raw_latency_ms) else None,
            "publisher_rates_hz": rates, "publisher_ok": publisher_ok, "node_counters": res.node_counters,
            "node_load": res.node_load(), "nodes_alive": res.nodes_alive,
            "node_cpu_s": [round(c, 2) for c in res.node_cpu_s], "seconds": DURATION,
            "cpu_us_per_fused_pose": round(1e6 * sum(res.node_cpu_s) / res.fused_total, 1) if res.fused_total else None,
            "load": res.load, "ok": lost == 0 and p99 <= P99_MAX_MS and res.nodes_alive}


def search(procs: int, executor: str, frames: bool = False) -> tuple[int, list[dict]]:
    best, steps = 0, []
    for n in [n for n in STEPS if n >= procs]:   # two processes need two targets
        s = step(n, procs, executor, frames)
        steps.append(s)
        print(f"# capacity procs={procs} executor={executor} frames={frames} {s}", file=sys.stderr, flush=True)
        if not s["ok"]:
            break
        best = n
    return best, steps


def why_failed(steps: list[dict]) -> str | None:
    """The first failing step of a search, in one line (the measured reason the capacity is not higher)."""
    failed = next((s for s in steps if not s["ok"]), None)
    if failed is None:
        return None
    if "error" in failed:
        return f"{failed['targets']} targets: {failed['error']}"
    return (f"{failed['targets']} targets: lost {failed['lost']} of {failed['samples']}, p99 "
            f"{failed['p99_ms']} ms (limit {P99_MAX_MS} ms)"
            + ("" if failed["publisher_ok"] else "; the stand-in publisher fell behind the device rates")
            + ("" if failed["nodes_alive"] else "; a fusion_node process died"))


def main() -> None:
    for name, procs in (("capacity_targets", 1), ("capacity_targets_2proc", 2)):
        # the per-body inputs with each executor; the frames (inputs: frames) with the node's default executor
        keys = [(ex, False) for ex in EXECUTORS] + [("events", True)] * FRAMES
        runs: dict[tuple[str, bool], list[tuple[int, list[dict]]]] = {k: [] for k in keys}
        for r in range(REPEATS):
            for k in keys[r % len(keys):] + keys[:r % len(keys)]:
                runs[k].append(search(procs, *k))
        for k in keys:
            ex = k[0]
            steps = [s for _, st in runs[k] for s in st]
            raw = [s["raw_p99_ms"] for s in steps if s["raw_p99_ms"] is not None]
            # CPU a target costs one process (CPU time, not wall time: less sensitive to other load than latency)
            shares = [sum(s["node_cpu_s"]) / s["seconds"] / s["targets"] for s in steps if s.get("node_cpu_s")]
            share = float(np.median(shares)) if shares else None
            per_pose = [s["cpu_us_per_fused_pose"] for s in steps if s.get("cpu_us_per_fused_pose")]
            emit(name + ("[inputs=frames]" if k[1] else ""), float(np.median([b for b, _ in runs[k]])), "targets",
                 executor=ex, runs=[b for b, _ in runs[k]], raw_dds_p99_ms=float(np.median(raw)) if raw else None,
                 cpu_share_per_target=round(share, 3) if share else None,
                 targets_per_core_by_cpu=int(1 / share) if share else None,
                 cpu_us_per_fused_pose=float(np.median(per_pose)) if per_pose else None,
                 criterion=f"0 lost and p99 <= {P99_MAX_MS} ms at 240 + 400 Hz per target",
                 first_failure=[why_failed(st) for _, st in runs[k]], steps=steps)


if __name__ == "__main__":
    main()
