"""End-to-end latency across processes: driver publish -> fused pose, at OMC 240 Hz + OTS 400 Hz (issue 16).

Three processes on one DDS domain (LOCALHOST discovery, own domain id): ``e2e_publisher.py`` (stand-in drivers,
stamping each pose with its publish time), the installed ``fusion_node`` with its default settings and every
registered filter enabled (``filter_registry.FILTERS``: the paper's four, ``omc``, and any filter added since;
the default primary first), and this script, which subscribes to the fused pose and takes ``receive - stamp``
(harness: ``live_fusion.py``).

Figures:
  fused_latency_p50, fused_latency_p99 [ms]   baseline: the raw DDS latency of the publisher's
                                              /omc/tool/pose received here directly (ratio = fused / raw)
  fused_dropped [count]                        target samples (after the first second) that no fused pose covers
                                              (``live_fusion``: a fused stamp within [s, s + slop]); the node's
                                              own drop counters from /diagnostics beside it
Run: python bench/bench_e2e_latency.py   (FULLPERC_BENCH_E2E_S: seconds of data, default 10)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import emit  # noqa: E402
from live_fusion import run_live  # noqa: E402

DURATION = float(os.environ.get("FULLPERC_BENCH_E2E_S", "10"))


def every_filter() -> tuple[str, list[str]]:
    """The node's default primary filter and every other registered one (side by side)."""
    from fullperc_fusion.filter_registry import FILTERS
    from fullperc_fusion.fusion_config import PARAMS

    primary = str(next(p.default for p in PARAMS if p.name == "filter"))
    return primary, [f for f in FILTERS if f != primary]


def main() -> None:
    primary, extra = every_filter()
    domain = 40 + os.getpid() % 50
    res = run_live([["-p", f"filter:={primary}", "-p", f"filters:=[{', '.join(extra)}]"]], ["tool"], domain,
                   DURATION)
    lat, raw = res.latency_ms["tool"], res.raw_latency_ms
    common = {"filters": [primary, *extra], "setting": "node defaults", "omc_hz": 240, "ots_hz": 400,
              "publisher_rates_hz": [round(res.publisher["omc_hz"], 1), round(res.publisher["ots_hz"], 1)],
              "fused_poses": int(len(lat))}
    if not len(lat):
        for name in ("fused_latency_p50", "fused_latency_p99"):
            print(f'{{"name": "{name}", "value": null, "unit": "ms", "error": "no fused pose received '
                  f'(node alive: {res.nodes_alive})"}}', flush=True)
    else:
        emit("fused_latency_p50", np.median(lat), "ms", baseline=np.median(raw), **common)
        emit("fused_latency_p99", np.percentile(lat, 99), "ms", baseline=np.percentile(raw, 99), **common)
    emit("fused_dropped", res.lost["tool"], "count", target_samples=res.sent["tool"],
         node_counters=res.node_counters, node_load=res.node_load(),
         node_cpu_share=round(res.node_cpu_s[0] / DURATION, 3) if res.node_cpu_s else None,
         cpu_us_per_fused_pose=round(1e6 * res.node_cpu_s[0] / res.fused_total, 1) if res.fused_total else None,
         **common)


if __name__ == "__main__":
    main()
