"""What one target costs fusion_node, against the echo floor in the same run (issue 38 items 1 and 6).

One target at OMC 240 Hz + OTS 400 Hz with base bodies (``e2e_publisher.py``: 1,280 messages/s in), fusion_node at
its defaults (``static_links: average``, the steady state of a calibrated OR; ``live_fusion.run_live``), and
``echo_floor.py`` -- a bare rclpy node with the same inputs and QoS that publishes pose, pose_cov, status and /tf for
every target sample and does no maths: the CPU floor of any Python node doing this I/O. Each is run with two
consumers: the fused pose only, and every output (pose, pose_cov, status, /tf); fusion_node also with a third, the
poses array only (``/fullperc/poses``, FusedPoseArray: what a consumer of many targets reads instead of a pose_cov per
target). fusion_node publishes a topic only while it has a reader; the echo publishes everything always, as a first
node would.

Figures (CPU seconds of the node process while data flowed, per second of data and per target = cores):
  echo_floor_cpu[pose|every]       the echo floor with that consumer
  node_cpu_per_target[pose|every]  fusion_node; baseline: the echo floor with the same consumer, ratio = node / floor
                                   (goals: <= 0.8 with the pose only, <= 1.1 with every output)
  node_cpu_per_target[array]       fusion_node with the poses array's consumer only; baseline: the echo floor with the
                                   pose consumer (the echo has no array; both consumers read one topic), no goal: set
                                   beside [pose] it shows what reading every target from one message costs
                                   (``lost`` also counts samples folded into a newer entry of the same wake-up)
  node_cpu_per_target[pose,partner_wait=0]  fusion_node with the pose consumer and ``partner_wait: 0`` (every sample
                                   fused on arrival, a pair's first sample fused alone and again with its partner:
                                   docs/nodes.md "Processing on arrival"); baseline: the echo floor [pose]; set beside
                                   [pose] it shows what waiting for a due partner saves
  node_cpu_per_target[pose,inputs=frames]  fusion_node with the pose consumer and ``inputs: frames``: it reads
                                   /omc/bodies and /ots/bodies (TrackedBodies, every body of a device frame in one
                                   message, as fullperc's drivers publish beside the per-body topics): 640 messages/s
                                   in instead of 1,280; baseline: the echo floor [pose] (the naive node's per-body
                                   inputs); the goal of [pose] (<= 0.8) is met on this input path or not at all
  node_core_cpu_per_target         the node's own work without ROS: fusion_core + fusion_publish in this process on
                                   the same streams (OMC 240 Hz + OTS 400 Hz, base bodies, a pose reader), stubs for
                                   the publishers; baseline: node_cpu_per_target[pose], ratio = the share of the
                                   node's CPU that is its own work (the rest is rclpy's and DDS's per-message path)
  echo_floor_cpu[pose,outputs=pose|none]  the echo floor's split (``echo_floor.py --outputs``): the same inputs, and
                                   the fused pose only (``pose``: fusion_node's I/O with a pose consumer, without its
                                   maths) or nothing (``none``: the input path alone); baseline: echo_floor_cpu[pose].
                                   ``[outputs=pose]`` + node_core_cpu_per_target is what fusion_node[pose] would cost
                                   with rclpy's per-message path as the naive node pays it
  gc_full_collection_ms            one full garbage collection with fusion_node's modules loaded, after
                                   ``node_main.settle_heap`` (what every node does once built); baseline: the same
                                   collection without it (a callback stalls that long when the collector runs one)
the node figures each the median over REPEATS runs of every configuration, the configurations rotating within a
repeat (so none always runs on the busier moment); ``runs`` lists each run's share, samples lost and messages consumed.
Run: python bench/bench_node_cost.py   (FULLPERC_BENCH_NODE_S: seconds of data per run, default 8;
FULLPERC_BENCH_REPEATS: default 3)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import emit  # noqa: E402
from live_fusion import run_live, target_params  # noqa: E402

HERE = Path(__file__).resolve().parent
DURATION = float(os.environ.get("FULLPERC_BENCH_NODE_S", "8"))
REPEATS = int(os.environ.get("FULLPERC_BENCH_REPEATS", "3"))
TARGETS = ["tool"]
CONSUMERS = {"pose": (), "every": ("pose_cov", "status", "/tf"), "array": ()}
ECHO = [sys.executable, str(HERE / "echo_floor.py"), "--targets", ",".join(TARGETS)]
NODES = {"fusion": None, "echo": ECHO}
SPLITS = {"pose": ECHO + ["--outputs", "pose"], "none": ECHO + ["--outputs", "none"]}   # the echo floor split
VARIANTS = {"partner_wait=0": ["-p", "partner_wait:=0.0"],   # fusion_node with one setting changed, pose consumer
            "inputs=frames": ["-p", "inputs:=frames"]}
GOAL_VARIANTS = ("inputs=frames",)   # the pose consumer's goal applies to these too


def run(node: str, consumer: str) -> dict:
    extra = VARIANTS[node.split(":", 1)[1]] if node.startswith("fusion:") else []
    command = SPLITS[node.split(":", 1)[1]] if node.startswith("echo:") else NODES.get(node)
    res = run_live([target_params(TARGETS) + extra], TARGETS, None, DURATION, command=command,
                   consumers=CONSUMERS[consumer], array=consumer == "array", frames="inputs:=frames" in extra)
    return {"share": sum(res.node_cpu_s) / DURATION / len(TARGETS), "lost": sum(res.lost.values()),
            "sent": sum(res.sent.values()), "fused": res.fused_total, "consumed": res.consumed,
            "alive": res.nodes_alive, "load": res.load}


def core_cost(seconds: float = 20.0) -> float:
    """Cores that fusion_core and fusion_publish take for one target at OMC 240 Hz + OTS 400 Hz, in this process
    (``node_core_cpu_per_target``): what FusionNode._on_input calls per sample, minus rclpy. Process CPU time over
    the last three quarters of ``seconds`` of samples (the first quarter: links averaged, filters settled)."""
    import time

    from fullperc_fusion.fusion_config import read_values
    from fullperc_fusion.fusion_core import FusionCore
    from fullperc_fusion.fusion_publish import OutputPublisher, publish_outputs

    class Pub:   # a publisher stub: subscribers as given, publish does nothing
        def __init__(self, subs: int) -> None:
            self.subs = subs

        def get_subscription_count(self) -> int:
            return self.subs

        def publish(self, msg) -> None:
            pass

    over = {"static_links": "average", "init_samples": 20, "targets": TARGETS, "tool.omc_body": "tool",
            "tool.ots_tool": "tool"}
    core = FusionCore(read_values(lambda n, d: over.get(n, d)), now=0.0)
    sets = {("tool", ""): OutputPublisher(Pub(1), Pub(0), Pub(0))}   # the pose consumer only
    s, t0 = 1_000_000_000, 1_700_000_000_000_000_000
    events = sorted([(t0 + round(k * s / 240), "omc") for k in range(int(seconds * 240))]
                    + [(t0 + round(k * s / 400) + 300_000, "ots") for k in range(int(seconds * 400))])
    q, base = np.array([0.0, 0.0, 0.0, 1.0]), np.array([1.0, 0.5, 0.8])

    def feed(evs) -> None:
        for t, dev in evs:
            now = (t - t0) * 1e-9
            touched = [*core.on_pose(dev, "base", t, base, q, now, t)]   # a copy: on_pose returns the core's list
            touched += core.on_pose(dev, "tool", t, np.array([0.1 + 0.01 * np.sin(now), 0.2, 0.3]), q, now, t)
            for tg in set(touched):
                publish_outputs(sets, tg, core.poll(tg, None), core.primary, core.extra, 0,
                                on_primary=lambda o, tg=tg, now=now: core.primary_output(tg, now, o),
                                on_error=lambda o, why: None, tf_of=None)

    k = len(events) // 4
    feed(events[:k])
    c = time.process_time()
    feed(events[k:])
    return (time.process_time() - c) / (events[-1][0] - events[k][0]) * 1e9 / len(TARGETS)


def gc_pause() -> None:
    import gc
    import statistics
    import time

    import fullperc_fusion.fusion_node  # noqa: F401 - the modules a built fusion_node holds
    from fullperc_common.node_main import settle_heap

    def full_ms() -> float:
        times = []
        for _ in range(7):
            t = time.perf_counter()
            gc.collect()
            times.append((time.perf_counter() - t) * 1e3)
        return statistics.median(times)

    gc.unfreeze()
    before, tracked = full_ms(), len(gc.get_objects())
    settle_heap()
    after = full_ms()
    gc.unfreeze()
    emit("gc_full_collection_ms", after, "ms", baseline=before, tracked_objects=tracked)


def main() -> None:
    gc_pause()
    configs = [(n, c) for n in NODES for c in CONSUMERS if (n, c) != ("echo", "array")]   # the echo has no array
    configs += [(f"fusion:{v}", "pose") for v in VARIANTS] + [(f"echo:{o}", "pose") for o in SPLITS]
    runs: dict[tuple[str, str], list[dict]] = {k: [] for k in configs}
    for r in range(REPEATS):
        for k in configs[r % len(configs):] + configs[:r % len(configs)]:
            runs[k].append(run(*k))
    share = {k: float(np.median([x["share"] for x in v])) for k, v in runs.items()}
    for c in CONSUMERS:
        if c != "array":
            emit(f"echo_floor_cpu[{c}]", share[("echo", c)], "cores", targets=len(TARGETS), seconds=DURATION,
                 runs=runs[("echo", c)])
        floor = share[("echo", "pose" if c == "array" else c)]   # the echo has no array: the one-topic consumer's
        goal = {"goal_ratio": {"pose": 0.8, "every": 1.1}[c]} if c != "array" else {}
        emit(f"node_cpu_per_target[{c}]", share[("fusion", c)], "cores", baseline=floor, targets=len(TARGETS),
             seconds=DURATION, runs=runs[("fusion", c)], **goal)
    emit("node_core_cpu_per_target", core_cost(), "cores", baseline=share[("fusion", "pose")], targets=len(TARGETS))
    for o in SPLITS:
        k = (f"echo:{o}", "pose")
        emit(f"echo_floor_cpu[pose,outputs={o}]", share[k], "cores", baseline=share[("echo", "pose")],
             targets=len(TARGETS), seconds=DURATION, runs=runs[k])
    for v in VARIANTS:
        k = (f"fusion:{v}", "pose")
        emit(f"node_cpu_per_target[pose,{v}]", share[k], "cores", baseline=share[("echo", "pose")],
             targets=len(TARGETS), seconds=DURATION, runs=runs[k],
             **({"goal_ratio": 0.8} if v in GOAL_VARIANTS else {}))


if __name__ == "__main__":
    main()
