"""Shared harness of the live fusion benches (bench_e2e_latency, bench_capacity): real processes on one DDS domain.

:func:`run_live` starts one or more installed ``fusion_node`` processes, subscribes here (a separate process from
the node and the publisher) to the fused pose of every target, runs ``e2e_publisher.py`` (driver stand-in, poses
stamped with their publish time) and returns per target the latencies (receive time - fused stamp) and the
target samples that never reached a fused output.

"Lost" is defined without assuming how the node pairs samples: a target sample stamped ``s`` is covered when a
fused pose of its target is stamped in ``[s, s + slop]`` (a lone sample is published at its own stamp; an
approximate-time pair at the newer of its two stamps, at most ``slop`` later). The node's own drop counters from
``/diagnostics`` are returned beside it; a pose not received within 2.5 s after the last sample was published
counts as lost (a node with a backlog of seconds does not serve the OR). The first second after the first fused
pose is skipped (the static links are averaged from the first samples then; every node runs with
``init_samples:=20`` instead of 30 to shorten that, all else at the node's defaults unless a bench passes more).
The nodes run with ``static_links:=average``: the figures are the steady state of a calibrated OR. With the default
``calibrate`` every step (a few seconds) would fall inside the 10 s start-up collection, whose per-sample
bookkeeping and one-off robust mean at its end (measured with bench/profile_node.py) are start-up costs, not
the per-sample cost of fusing.
Every run uses LOCALHOST discovery and its own domain id.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from benchlib import cpu_seconds  # bench/: on the path of every importer and of a script run from it

HERE = Path(__file__).resolve().parent
WARMUP_NS = 1_000_000_000
# a /diagnostics value counts as a drop counter when its key has one of these words (late, sync_late, lost, ...)
LOAD_KEYS = ("processing", "queue_depth", "queue_depth_max", "lag_ms", "lag_max_ms", "callback_delay_max_ms",
             "wakeup_p50_ms", "wakeup_p99_ms", "wakeup_max_ms", "received_to_published_p99_ms",
             "items", "rewinds", "replayed_items", "pending")
DROP_WORDS = {"late", "lost", "dropped", "duplicate", "future", "old", "rejected"}


def root() -> Path:
    return Path(os.environ.get("FULLPERC_ROOT", HERE.parent))


def fusion_exe() -> Path:
    return root() / "install/fullperc_fusion/lib/fullperc_fusion/fusion_node"


def default_slop_s() -> float:
    """The node's default ``slop`` (fusion_config), the pairing window of the coverage rule."""
    from fullperc_fusion.fusion_config import PARAMS

    return float(next(p.default for p in PARAMS if p.name == "slop"))


@dataclass
class LiveResult:
    latency_ms: dict[str, np.ndarray]        # per target: receive - stamp of every fused pose after warm-up [ms]
    raw_latency_ms: np.ndarray               # raw DDS: /omc/<first target>/pose received here directly [ms]
    lost: dict[str, int]                     # per target: samples after warm-up not covered by a fused pose
    sent: dict[str, int]                     # per target: samples after warm-up (OMC + OTS)
    node_counters: dict[str, int]            # summed drop counters of the nodes' /diagnostics
    publisher: dict                          # the publisher's summary line (frames, achieved rates)
    nodes_alive: bool = True
    diag: dict[str, dict[str, str]] = field(default_factory=dict)
    node_cpu_s: list[float] = field(default_factory=list)   # CPU seconds of each node process while data flowed
    fused_total: int = 0                     # fused poses received over the whole run (warm-up included)
    load: list[float] = field(default_factory=list)   # load averages right after the data (1 min ~ the run)
    consumed: dict[str, int] = field(default_factory=dict)   # messages received per further consumer topic

    def node_load(self) -> dict[str, dict[str, str]]:
        """Per /diagnostics target entry: the node's own load figures (queue depth, processing lag, rewinds), as
        the node last reported them -- the measured reason when latency or loss misses its goal."""
        return {name: {k: v for k, v in vals.items() if k in LOAD_KEYS} for name, vals in self.diag.items()}

    @property
    def all_latency_ms(self) -> np.ndarray:
        parts = [v for v in self.latency_ms.values() if len(v)]
        return np.concatenate(parts) if parts else np.zeros(0)


def uncovered(sent_ns: np.ndarray, fused_ns: np.ndarray, slop_ns: int) -> int:
    """How many sample stamps ``s`` of ``sent_ns`` have no fused stamp in ``[s, s + slop_ns]`` (the lost rule)."""
    out = np.sort(np.asarray(fused_ns, dtype=np.int64))
    s = np.asarray(sent_ns, dtype=np.int64)
    if not len(out):
        return int(len(s))
    k = np.searchsorted(out, s)                       # first fused stamp >= s
    covered = (k < len(out)) & (out[np.minimum(k, len(out) - 1)] <= s + slop_ns)
    return int((~covered).sum())


def every_filter() -> tuple[str, list[str]]:
    """The node's default primary filter and every other registered one (side by side)."""
    from fullperc_fusion.filters.registry import FILTERS
    from fullperc_fusion.fusion_config import PARAMS

    primary = str(next(p.default for p in PARAMS if p.name == "filter"))
    return primary, [f for f in FILTERS if f != primary]


def target_params(targets: list[str]) -> list[str]:
    """``--ros-args`` of a node fusing ``targets`` (each its own OMC body and OTS tool of the same name)."""
    out = ["-p", f"targets:=[{', '.join(targets)}]"]
    for t in targets:
        out += ["-p", f"{t}.omc_body:={t}", "-p", f"{t}.ots_tool:={t}"]
    return out


def run_live(nodes: list[list[str]], targets: list[str], domain: int | None, duration: float,
             omc_hz: float = 240.0, ots_hz: float = 400.0, executor: str | None = None,
             command: list[str] | None = None, consumers: tuple[str, ...] = (), array: bool = False,
             frames: bool = False) -> LiveResult:
    """Run ``len(nodes)`` fusion_node processes (each with the given extra ``--ros-args``) against the publisher.

    ``domain`` None: a domain id no test or other bench on this machine holds (fullperc_common.testing.claim_domain),
    held for the run. ``executor``: ``events`` | ``single`` sets ``FULLPERC_EXECUTOR`` for the nodes
    (fullperc_common.executor_choice); None leaves the node's default. ``command``: the node's command instead of
    the installed fusion_node (e.g. bench/echo_floor.py). ``consumers``: further outputs subscribed here besides
    every target's fused pose -- ``pose_cov``, ``status``, ``velocity`` (per target) and ``/tf`` -- received and
    counted only (fusion_node publishes a topic only while it has a reader). ``array``: the fused poses are read from
    ``/fullperc/poses`` (fullperc_msgs/FusedPoseArray, one entry per target per wake-up) instead of each target's
    pose topic, which is then not subscribed: a consumer of the array only. Latency is then per entry; a sample
    folded into a newer entry of the same wake-up counts as lost by :func:`uncovered`. ``frames``: the publisher also
    sends every device frame as one TrackedBodies (``e2e_publisher.py --frames``), for nodes with ``inputs: frames``
    (given in ``nodes``), and waits for those readers instead of the per-body ones."""
    if domain is None:
        from fullperc_common.testing import claim_domain

        with claim_domain() as lease:
            return run_live(nodes, targets, lease.domain, duration, omc_hz, ots_hz, executor, command, consumers,
                            array, frames)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    if executor is not None:
        env["FULLPERC_EXECUTOR"] = executor
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    procs = [subprocess.Popen([*(command or [str(fusion_exe())]), "--ros-args", "-p", "init_samples:=20",
                               "-p", "static_links:=average", *p], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
             for p in nodes]
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("live_bench", context=ctx)
    fused: dict[str, list[tuple[int, int]]] = {t: [] for t in targets}
    raw: list[tuple[int, int]] = []
    diag: dict[str, dict[str, str]] = {}

    def stamp(m) -> int:
        return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

    def on_diag(arr) -> None:
        for st in arr.status:
            if "target" in st.name:
                diag[st.name] = {kv.key: kv.value for kv in st.values}

    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    if array:
        from fullperc_msgs.msg import FusedPoseArray

        def on_array(m) -> None:
            now = time.time_ns()
            for e in m.poses:
                if e.target in fused:
                    fused[e.target].append((now, e.stamp.sec * 1_000_000_000 + e.stamp.nanosec))
        node.create_subscription(FusedPoseArray, "/fullperc/poses", on_array, qos)
    for t in () if array else targets:
        node.create_subscription(PoseStamped, f"/fullperc/{t}/pose",
                                 lambda m, s=fused[t]: s.append((time.time_ns(), stamp(m))), qos)
    ready = ["/fullperc/poses"] if array else [f"/fullperc/{t}/pose" for t in targets]
    node.create_subscription(PoseStamped, f"/omc/{targets[0]}/pose",
                             lambda m: raw.append((time.time_ns(), stamp(m))), qos)
    consumed = _subscribe_consumers(node, targets, consumers, qos)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                          daemon=True)
    th.start()
    stamps_file = Path(tempfile.mkdtemp(prefix="live_bench_")) / "stamps.json"
    # CPU is counted from when every node is constructed (its pose publisher seen here): importing and building a
    # node costs ~1.2-1.6 s of CPU, which a 6 s step would otherwise book as 0.2-0.27 core of load
    t_wait = time.monotonic()
    while (any(node.count_publishers(topic) < 1 for topic in ready)
           and time.monotonic() - t_wait < 120 and all(p.poll() is None for p in procs)):
        time.sleep(0.05)
    cpu0 = [cpu_seconds(p.pid) for p in procs]
    try:
        pub = subprocess.run([sys.executable, str(HERE / "e2e_publisher.py"), "--duration", str(duration),
                              "--wait-subscribers", "1" if frames else "2", "--wait-base", str(len(nodes)),
                              "--tools", ",".join(targets), "--omc-hz", str(omc_hz), "--ots-hz", str(ots_hz),
                              "--stamps", str(stamps_file), *(["--frames"] if frames else [])],
                             env=env, capture_output=True, text=True, timeout=duration + 180)
        # CPU while data flowed (the publisher's discovery wait and 1 s pauses add idle spinning only)
        cpu = [cpu_seconds(p.pid) - c for p, c in zip(procs, cpu0, strict=True)]
        run_load = [round(x, 2) for x in os.getloadavg()]
        time.sleep(2.5)   # one more diagnostics period after the last sample
    finally:
        stop.set()
        th.join()
        alive = all(p.poll() is None for p in procs)
        for p in procs:
            p.send_signal(2)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        rclpy.shutdown(context=ctx)
    if pub.returncode != 0:
        raise RuntimeError(f"e2e_publisher failed (exit {pub.returncode}): {pub.stderr.strip()[-500:]}")
    summary = json.loads(pub.stdout.strip().splitlines()[-1])
    sent = json.loads(stamps_file.read_text())
    slop_ns = int(default_slop_s() * 1e9)
    lat: dict[str, np.ndarray] = {}
    lost: dict[str, int] = {}
    n_sent: dict[str, int] = {}
    for t in targets:
        f = np.array(fused[t], dtype=np.int64).reshape(-1, 2)
        s = np.sort(np.array(sent["omc"][t] + sent["ots"][t], dtype=np.int64))
        if len(f):
            start = f[:, 1].min() + WARMUP_NS
            f = f[f[:, 1] > start]
            s = s[s > start]
        lat[t] = (f[:, 0] - f[:, 1]) / 1e6
        lost[t] = uncovered(s, f[:, 1], slop_ns)
        n_sent[t] = int(len(s))
    r = np.array(raw, dtype=np.int64).reshape(-1, 2)
    counters: dict[str, int] = {}
    for values in diag.values():
        for k2, v in values.items():
            if DROP_WORDS & set(k2.split("_")) and v.strip().lstrip("-").isdigit():
                counters[k2] = counters.get(k2, 0) + int(v)
    return LiveResult(lat, (r[:, 0] - r[:, 1]) / 1e6, lost, n_sent, counters, summary, alive, diag, cpu,
                      sum(len(v) for v in fused.values()), run_load, dict(consumed))


def _subscribe_consumers(node, targets: list[str], consumers: tuple[str, ...], qos) -> dict[str, int]:
    """Subscribe ``consumers`` (run_live) on ``node``; returns the per-topic message counts, filled as they come."""
    from geometry_msgs.msg import PoseWithCovarianceStamped, TwistWithCovarianceStamped

    from fullperc_msgs.msg import FusionStatus
    from tf2_msgs.msg import TFMessage

    types = {"pose_cov": PoseWithCovarianceStamped, "status": FusionStatus, "velocity": TwistWithCovarianceStamped}
    counts: dict[str, int] = {}

    def count(topic: str, _msg) -> None:
        counts[topic] = counts.get(topic, 0) + 1

    for what in consumers:
        if what == "/tf":
            from fullperc_common.tf import dynamic_qos

            node.create_subscription(TFMessage, "/tf", lambda m: count("/tf", m), dynamic_qos())
            continue
        if what not in types:
            raise ValueError(f"unknown consumer {what!r}: one of {sorted(types)} or /tf")
        for t in targets:
            topic = f"/fullperc/{t}/{what}"
            node.create_subscription(types[what], topic, lambda m, k=topic: count(k, m), qos)
    return counts
