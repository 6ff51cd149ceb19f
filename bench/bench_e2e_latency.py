"""End-to-end latency across processes: driver publish -> fused pose, at OMC 240 Hz + OTS 400 Hz (issue 16).

Three processes on one DDS domain (LOCALHOST discovery, own domain id): ``e2e_publisher.py`` (stand-in drivers,
stamping each pose with its publish time), the installed ``fusion_node`` with its default settings and every
registered filter enabled (``filters.registry.FILTERS``: the paper's four, ``omc``, and any filter added since;
the default primary first), and this script, which subscribes to the fused pose and takes ``receive - stamp``
(harness: ``live_fusion.py``).

Figures:
  fused_latency_p50, fused_latency_p99 [ms]   baseline: the raw DDS latency of the publisher's
                                              /omc/tool/pose received here directly (ratio = fused / raw)
  fused_dropped [count]                        target samples (after the first second) that no fused pose covers
                                              (``live_fusion``: a fused stamp within [s, s + slop]); the node's
                                              own drop counters from /diagnostics beside it
Executor dimension: every figure once per executor of the node (``executor``: ``events``, fusion_node's default,
or ``single``, rclpy's SingleThreadedExecutor, the baseline; fullperc_common.executor_choice). Each executor runs
REPEATS times, alternating (order swapped every repeat); ``value`` and ``baseline`` are medians over the repeats
(``runs``: each repeat's value, raw baseline and load averages).
Run: python bench/bench_e2e_latency.py   (FULLPERC_BENCH_E2E_S: seconds of data, default 10;
FULLPERC_BENCH_EXECUTORS: default "events,single"; FULLPERC_BENCH_REPEATS: default 3)
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import emit, load  # noqa: E402
from live_fusion import every_filter, run_live  # noqa: E402

DURATION = float(os.environ.get("FULLPERC_BENCH_E2E_S", "10"))
EXECUTORS = [e for e in os.environ.get("FULLPERC_BENCH_EXECUTORS", "events,single").split(",") if e]
REPEATS = int(os.environ.get("FULLPERC_BENCH_REPEATS", "3"))


def one_run(primary: str, extra: list[str], executor: str) -> dict:
    """One run of the node with every filter: its latencies, raw baseline, loss, CPU and load."""
    res = run_live([["-p", f"filter:={primary}", "-p", f"filters:=[{', '.join(extra)}]"]], ["tool"], None,
                   DURATION, executor=executor)
    lat, raw = res.latency_ms["tool"], res.raw_latency_ms
    r = {"p50": float(np.median(lat)) if len(lat) else None, "p99": float(np.percentile(lat, 99)) if len(lat) else None,
         "raw_p50": float(np.median(raw)) if len(raw) else None,
         "raw_p99": float(np.percentile(raw, 99)) if len(raw) else None,
         "dropped": res.lost["tool"], "target_samples": res.sent["tool"], "fused_poses": int(len(lat)),
         "node_counters": res.node_counters, "node_load": res.node_load(), "alive": res.nodes_alive,
         "node_cpu_share": round(res.node_cpu_s[0] / DURATION, 3) if res.node_cpu_s else None,
         "cpu_us_per_fused_pose": round(1e6 * res.node_cpu_s[0] / res.fused_total, 1) if res.fused_total else None,
         "publisher_rates_hz": [round(res.publisher["omc_hz"], 1), round(res.publisher["ots_hz"], 1)],
         "load": res.load}
    print(f"# e2e executor={executor} {r}", file=sys.stderr, flush=True)
    return r


def _med(runs: list[dict], key: str) -> float | None:
    vals = [r[key] for r in runs if r[key] is not None]
    return float(np.median(vals)) if vals else None


def main() -> None:
    primary, extra = every_filter()
    runs: dict[str, list[dict]] = {e: [] for e in EXECUTORS}
    for k in range(REPEATS):
        for ex in EXECUTORS if k % 2 == 0 else EXECUTORS[::-1]:
            runs[ex].append(one_run(primary, extra, ex))
    for ex, rs in runs.items():
        common = {"executor": ex, "filters": [primary, *extra], "setting": "node defaults", "omc_hz": 240,
                  "ots_hz": 400, "repeats": len(rs)}
        for name, key in (("fused_latency_p50", "p50"), ("fused_latency_p99", "p99")):
            value, base = _med(rs, key), _med(rs, "raw_" + key)
            per_run = [{"value": r[key], "baseline": r["raw_" + key], "load": r["load"]} for r in rs]
            if value is None:
                print(json.dumps({"name": name, "value": None, "unit": "ms", "load": load(), **common,
                                  "error": f"no fused pose received (nodes alive: {[r['alive'] for r in rs]})"}),
                      flush=True)
            else:
                emit(name, value, "ms", baseline=base, runs=per_run, **common)
        emit("fused_dropped", _med(rs, "dropped"), "count", runs=[r["dropped"] for r in rs],
             target_samples=[r["target_samples"] for r in rs], node_counters=[r["node_counters"] for r in rs],
             node_load=[r["node_load"] for r in rs], node_cpu_share=_med(rs, "node_cpu_share"),
             cpu_us_per_fused_pose=_med(rs, "cpu_us_per_fused_pose"),
             publisher_rates_hz=[r["publisher_rates_hz"] for r in rs], **common)


if __name__ == "__main__":
    main()
