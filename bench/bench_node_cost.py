"""fusion_node's CPU against the echo floor: what fusing costs beyond the I/O any Python ROS node pays (issue "node
cost").

One run: the installed ``fusion_node`` (node defaults, ``static_links:=average``, ``init_samples:=20`` as
``live_fusion``) and ``echo_floor_node.py`` (a bare rclpy node: the same five pose subscriptions and QoS, the same
four messages per target sample, no maths) run side by side on one DDS domain against one ``e2e_publisher.py``
(OMC 240 Hz: base, ots_rig, tool; OTS 400 Hz: base, tool -- 1,520 messages/s in, 640 target samples/s). A consumer
in this process subscribes one of two sets, to both nodes' topics alike:

  pose   the fused pose only: /fullperc/tool/pose (and /echo/tool/pose)
  all    every output: pose, pose_cov, status, final, /tf (and the echo's pose, pose_cov, status, /echo/tf)

CPU [core] = user + system seconds of each process (/proc, from when both nodes are constructed until it has worked
off the whole input, :func:`settled_cpu`) / seconds of data. REPEATS runs per set, the sets alternating (order
swapped every repeat).

Figures (per consumer set, ``consumers``: pose | all; medians over the repeats, ``runs``: each run's values):
  echo_floor_cpu [core]        the echo node
  node_cpu_per_target [core]   fusion_node / targets (1); baseline = the echo floor of the same runs, ratio;
                               ``goal``: the ratio the issue asks for (pose 0.8, all 1.1); the run's fused latency
                               p99 and its raw DDS p99 beside it (``fused_latency_p99`` proper: bench_e2e_latency)
Run: python bench/bench_node_cost.py   (FULLPERC_BENCH_COST_S: seconds of data, default 6; FULLPERC_BENCH_REPEATS:
default 3). Both nodes share the machine with the publisher and the consumer: the ratio is the figure, the absolute
cores depend on the load (``load``).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import cpu_seconds, emit, emit_error, load  # noqa: E402
from live_fusion import fusion_exe  # noqa: E402

HERE = Path(__file__).resolve().parent
DURATION = float(os.environ.get("FULLPERC_BENCH_COST_S", "6"))
REPEATS = int(os.environ.get("FULLPERC_BENCH_REPEATS", "3"))
GOALS = {"pose": 0.8, "all": 1.1}
TARGET = "tool"


def consumer_topics(kind: str) -> dict[str, str]:
    """topic -> message type name of the consumer set ``kind`` (module docstring), both nodes' topics."""
    if kind == "pose":
        return {f"/fullperc/{TARGET}/pose": "PoseStamped", f"/echo/{TARGET}/pose": "PoseStamped"}
    out = {}
    for prefix in (f"/fullperc/{TARGET}", f"/echo/{TARGET}"):
        out.update({f"{prefix}/pose": "PoseStamped", f"{prefix}/pose_cov": "PoseWithCovarianceStamped",
                    f"{prefix}/status": "FusionStatus"})
    out.update({f"/fullperc/{TARGET}/final": "PoseStamped", "/tf": "TFMessage", "/echo/tf": "TFMessage"})
    return out


def settled_cpu(procs: dict[str, subprocess.Popen], cpu0: dict[str, float], limit_s: float = 20.0) -> dict:
    """CPU seconds of each process since ``cpu0`` once it has worked off its input: read when a 0.5 s window adds
    less than 0.1 core (a node behind its input on a loaded machine still owes the rest; its CPU for the whole input
    is the figure, not what the scheduler let it have while data flowed)."""
    last = {k: cpu_seconds(p.pid) for k, p in procs.items()}
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        time.sleep(0.5)
        now = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        idle = all(now[k] - last[k] < 0.05 for k in procs)
        last = now
        if idle:
            break
    return {k: last[k] - cpu0[k] for k in procs}


def one_run(kind: str, domain: int) -> dict:
    import rclpy
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.tf import dynamic_qos
    from fullperc_msgs.msg import FusionStatus
    from tf2_msgs.msg import TFMessage

    types = {"PoseStamped": PoseStamped, "PoseWithCovarianceStamped": PoseWithCovarianceStamped,
             "FusionStatus": FusionStatus, "TFMessage": TFMessage}
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    procs = {"fusion": subprocess.Popen([str(fusion_exe()), "--ros-args", "-p", "init_samples:=20",
                                         "-p", "static_links:=average"], env=env, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, start_new_session=True),
             "echo": subprocess.Popen([sys.executable, str(HERE / "echo_floor_node.py"), "--tool", TARGET], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)}
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("node_cost_consumer", context=ctx)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    counts = {t: 0 for t in consumer_topics(kind)}
    fused: list[tuple[int, int]] = []
    raw: list[tuple[int, int]] = []

    def stamp(m) -> int:
        return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

    def on_msg(topic: str, m) -> None:
        counts[topic] += 1
        if topic == f"/fullperc/{TARGET}/pose":
            fused.append((time.time_ns(), stamp(m)))

    for topic, tname in consumer_topics(kind).items():
        node.create_subscription(types[tname], topic, lambda m, t=topic: on_msg(t, m),
                                 dynamic_qos() if tname == "TFMessage" else qos)
    node.create_subscription(PoseStamped, f"/omc/{TARGET}/pose", lambda m: raw.append((time.time_ns(), stamp(m))),
                             qos)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                          daemon=True)
    th.start()
    try:
        t_wait = time.monotonic()
        while ((node.count_publishers(f"/fullperc/{TARGET}/pose") < 1 or node.count_publishers(
                f"/echo/{TARGET}/pose") < 1) and time.monotonic() - t_wait < 120
               and all(p.poll() is None for p in procs.values())):
            time.sleep(0.05)
        cpu0 = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        pub = subprocess.run([sys.executable, str(HERE / "e2e_publisher.py"), "--duration", str(DURATION),
                              "--wait-subscribers", "3", "--wait-base", "2", "--tools", TARGET, "--rig", "ots_rig"],
                             env=env, capture_output=True, text=True, timeout=DURATION + 120)
        run_load = load()
        cpu = settled_cpu(procs, cpu0)
        alive = all(p.poll() is None for p in procs.values())
    finally:
        stop.set()
        th.join()
        for p in procs.values():
            p.send_signal(2)
        for p in procs.values():
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        rclpy.shutdown(context=ctx)
    if pub.returncode != 0:
        raise RuntimeError(f"e2e_publisher failed (exit {pub.returncode}): {pub.stderr.strip()[-300:]}")
    rates = json.loads(pub.stdout.strip().splitlines()[-1])
    f = np.array(fused, dtype=np.int64).reshape(-1, 2)
    f = f[f[:, 1] > f[:, 1].min() + 1_000_000_000] if len(f) else f   # the first second: static links averaged
    r = np.array(raw, dtype=np.int64).reshape(-1, 2)
    res = {"fusion_cpu": round(cpu["fusion"] / DURATION, 4), "echo_cpu": round(cpu["echo"] / DURATION, 4),
           "p99_ms": round(float(np.percentile((f[:, 0] - f[:, 1]) / 1e6, 99)), 3) if len(f) else None,
           "raw_p99_ms": round(float(np.percentile((r[:, 0] - r[:, 1]) / 1e6, 99)), 3) if len(r) else None,
           "received": counts, "alive": alive, "rates_hz": [round(rates["omc_hz"], 1), round(rates["ots_hz"], 1)],
           "load": run_load}
    print(f"# node_cost consumers={kind} {res}", file=sys.stderr, flush=True)
    return res


def main() -> None:
    from fullperc_common.testing import claim_domain

    runs: dict[str, list[dict]] = {"pose": [], "all": []}
    with claim_domain() as lease:
        for k in range(REPEATS):
            for kind in ("pose", "all") if k % 2 == 0 else ("all", "pose"):
                try:
                    runs[kind].append(one_run(kind, lease.domain))
                except RuntimeError as e:
                    print(f"# node_cost consumers={kind}: {e}", file=sys.stderr, flush=True)
    for kind, rs in runs.items():
        common = {"consumers": kind, "topics": sorted(consumer_topics(kind)), "targets": 1, "omc_hz": 240,
                  "ots_hz": 400, "messages_in_per_s": 1520, "duration_s": DURATION, "repeats": len(rs)}
        if not rs:
            emit_error("echo_floor_cpu", "core", "no run finished", **common)
            emit_error("node_cpu_per_target", "core", "no run finished", **common)
            continue
        echo = statistics.median(r["echo_cpu"] for r in rs)
        node = statistics.median(r["fusion_cpu"] for r in rs)
        per_run = [{k: r[k] for k in ("fusion_cpu", "echo_cpu", "p99_ms", "raw_p99_ms", "alive", "rates_hz", "load")}
                   for r in rs]
        emit("echo_floor_cpu", echo, "core", runs=[r["echo_cpu"] for r in rs], **common)
        p99 = [r["p99_ms"] for r in rs if r["p99_ms"] is not None]
        raw = [r["raw_p99_ms"] for r in rs if r["raw_p99_ms"] is not None]
        emit("node_cpu_per_target", node, "core", baseline=echo, goal=GOALS[kind],
             fused_latency_p99_ms=statistics.median(p99) if p99 else None,
             raw_latency_p99_ms=statistics.median(raw) if raw else None, received=rs[-1]["received"],
             runs=per_run, **common)


if __name__ == "__main__":
    main()
