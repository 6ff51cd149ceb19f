"""End-to-end latency across processes: driver publish -> fused pose, at OMC 240 Hz + OTS 400 Hz.

Three processes on one DDS domain (localhost): ``e2e_publisher.py`` (stand-in drivers, stamping each
pose with its publish time), the installed ``fusion_node``, and this script, which subscribes to the
fused pose and takes ``receive time - stamp``. The fused stamp is the acquisition stamp of the newest
sample used, so this is publish -> fused delivery including the synchronizer's deliberate wait.

Figures: p50/p99 latency for two synchronizer settings (the node's defaults, slop 4 ms + reorder delay
50 ms; and a low-latency setting, slop 1 ms + delay 2 ms), the count of target samples that never
reached a fused output ("dropped"), and as baseline the raw DDS latency of the same publisher's
``/omc/tool/pose`` received here directly (ratio = fused p50 / raw p50).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import emit  # noqa: E402

from fullperc_fusion.synchronizer import GLOBAL, LOCAL, ApproxSync  # noqa: E402

DURATION = float(os.environ.get("FULLPERC_BENCH_E2E_S", "10"))


def _root() -> Path:
    return Path(os.environ.get("FULLPERC_ROOT", Path(__file__).resolve().parent.parent))


def run(label: str, params: list[str], domain: int) -> None:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    exe = _root() / "install/fullperc_fusion/lib/fullperc_fusion/fusion_node"
    node_p = subprocess.Popen([str(exe), "--ros-args", "-p", "init_samples:=20", *params], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("e2e_bench", context=ctx)
    fused: list[tuple[int, int]] = []
    raw: list[tuple[int, int]] = []

    def stamp(m) -> int:
        return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    from diagnostic_msgs.msg import DiagnosticArray

    diag: dict[str, str] = {}

    def on_diag(arr) -> None:
        for st in arr.status:
            if st.name.endswith("target tool"):
                diag.update({kv.key: kv.value for kv in st.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    for topic, sink in (("/fullperc/tool/pose", fused), ("/omc/tool/pose", raw)):
        node.create_subscription(PoseStamped, topic, lambda m, s=sink: s.append((time.time_ns(), stamp(m))), qos)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                          daemon=True)
    th.start()
    stamps_file = Path(tempfile.mkdtemp()) / "stamps.json"
    pub = subprocess.run([sys.executable, str(Path(__file__).resolve().parent / "e2e_publisher.py"),
                          "--duration", str(DURATION), "--wait-subscribers", "2", "--stamps", str(stamps_file)],
                         env=env, capture_output=True, text=True, timeout=DURATION + 120)
    time.sleep(2.5)   # one more diagnostics period after the last sample
    stop.set()
    th.join()
    node_p.send_signal(2)
    try:
        node_p.wait(10)
    except subprocess.TimeoutExpired:
        node_p.kill()
    rclpy.shutdown(context=ctx)
    counts = json.loads(pub.stdout.strip().splitlines()[-1])
    f = np.array(fused, dtype=np.int64).reshape(-1, 2)
    r = np.array(raw, dtype=np.int64).reshape(-1, 2)
    # skip the first second: static-link initialisation
    if len(f):
        f = f[f[:, 1] > f[0, 1] + 1_000_000_000]
    lat_f = (f[:, 0] - f[:, 1]) / 1e6
    lat_r = (r[:, 0] - r[:, 1]) / 1e6
    inputs = counts["omc"] + counts["ots"]
    # The outputs the node owes: the items the same synchronizer forms from the stamps that were sent
    # (one output per lone sample or pair, stamped with the item's newer stamp). Dropped = owed - received.
    sent = json.loads(stamps_file.read_text())
    slop = 0.004 if "slop:=0.001" not in params else 0.001
    sync = ApproxSync(slop_ns=int(slop * 1e9), delay_ns=0)
    for t, stream in sorted([(t, GLOBAL) for t in sent["omc"]] + [(t, LOCAL) for t in sent["ots"]]):
        sync.push(stream, t)
    owed = np.array(sorted(it.t_ns for it in sync.flush()), dtype=np.int64)
    owed = owed[owed > f[0, 1]] if len(f) else owed      # after the initialisation second, as for latency
    got = set(f[:, 1].tolist())
    dropped = int(sum(1 for t in owed if t not in got))
    emit(f"e2e_latency_p50[{label}]", np.median(lat_f), "ms", baseline=np.median(lat_r))
    emit(f"e2e_latency_p99[{label}]", np.percentile(lat_f, 99), "ms", baseline=np.percentile(lat_r, 99))
    node_drops = {k: int(diag.get(k, 0)) for k in ("late", "sync_late", "duplicate", "sync_duplicate",
                                                    "rejected_stamp") if k in diag}
    emit(f"e2e_dropped[{label}]", sum(node_drops.values()), "count", node_counters=node_drops,
         outputs_owed_ideal=int(owed.size), owed_ideal_not_received=dropped, outputs_received=int(len(f)),
         target_samples_published=inputs, omc_published=counts["omc"], ots_published=counts["ots"])
    emit(f"e2e_raw_dds_dropped[{label}]", counts["omc"] - len(r), "count", published=counts["omc"])


def main() -> None:
    base = 40 + os.getpid() % 50
    run("defaults slop=4ms delay=50ms", [], base)
    run("low-latency slop=1ms delay=2ms", ["-p", "slop:=0.001", "-p", "reorder_delay:=0.002"], base + 1)


if __name__ == "__main__":
    main()
