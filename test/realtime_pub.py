"""Stand-in drivers for test_fusion_realtime.py: OMC and OTS poses of ``tool`` and ``base`` plus the tools'
TrackingQuality (frame numbers), stamped with the host clock at publish time (optionally shifted).

Each device frame k is published at ``start + k / rate`` (absolute schedule, no drift); the tool pose and its
quality carry the same stamp and frame number, the base is published every ``--base-every`` frames. Phases:
``--phase SECONDS:SHIFT_S`` (repeatable) publish SECONDS of data with stamps = host clock + SHIFT_S (a negative
shift makes data from the past, so a later phase with 0 is a jump ahead by -SHIFT_S without waiting for it).
The last line on stdout is JSON: {"omc": n, "ots": n} tool poses published, and their stamps with --stamps FILE.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common.node_main import wait_for_acks
from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_msgs.msg import TrackingQuality

T_OMC_BASE = (np.array([1.0, 0.5, 0.8]), np.array([0.0, 0.0, 0.0, 1.0]))
T_OTS_BASE = (np.array([0.1, -0.2, -1.5]), np.array([0.0, 0.0, 0.0, 1.0]))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--omc-hz", type=float, default=240.0)
    ap.add_argument("--ots-hz", type=float, default=400.0)
    ap.add_argument("--base-every", type=int, default=1)
    ap.add_argument("--phase", action="append", default=[], help="SECONDS:SHIFT_S")
    ap.add_argument("--wait-subscribers", type=float, default=30.0)
    ap.add_argument("--stamps", default="")
    ap.add_argument("--drop-last", action="store_true",
                    help="the last frame of each device: its TrackingQuality (visible) but not its tool pose")
    a = ap.parse_args()
    phases = [(float(x.split(":")[0]), float(x.split(":")[1])) for x in (a.phase or ["3:0"])]
    rclpy.init()
    node = rclpy.create_node("realtime_pub")
    # a history the writers can re-send from for the whole run (Fast DDS asks again after its 3 s heartbeat), and
    # wait for every acknowledgement before exiting: a sample lost on the way at the end of the stream would be
    # lost for good with no later frame number to reveal it, and the test could not account for it
    qos = QoSProfile(depth=50000, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {(d, b): node.create_publisher(PoseStamped, f"/{d}/{b}/pose", qos)
            for d in ("omc", "ots") for b in ("tool", "base")}
    qpubs = {d: node.create_publisher(TrackingQuality, f"/{d}/tool/quality", qos) for d in ("omc", "ots")}
    end = time.monotonic() + a.wait_subscribers
    while time.monotonic() < end and any(p.get_subscription_count() == 0 for p in [*pubs.values(), *qpubs.values()]):
        time.sleep(0.05)
    time.sleep(0.5)
    frames = {"omc": 0, "ots": 0}
    sent: dict[str, list[int]] = {"omc": [], "ots": []}
    for i_phase, (seconds, shift) in enumerate(phases):
        t0 = time.monotonic_ns()
        due = {"omc": t0, "ots": t0}
        period = {"omc": int(1e9 / a.omc_hz), "ots": int(1e9 / a.ots_hz)}
        stop = t0 + int(seconds * 1e9)
        while True:
            dev = min(due, key=due.get)
            if due[dev] >= stop:
                break
            now = time.monotonic_ns()
            if due[dev] > now:
                time.sleep((due[dev] - now) * 1e-9)
            due[dev] += period[dev]
            frames[dev] += 1
            k = frames[dev]
            stamp = time.time_ns() + int(shift * 1e9)
            ph = 0.3 * k / (a.omc_hz if dev == "omc" else a.ots_hz)
            p_base = np.array([0.4 + 0.05 * np.sin(ph), 0.1 * np.cos(ph), 0.3])  # tool in base, slowly moving
            base = T_OMC_BASE if dev == "omc" else T_OTS_BASE
            if k % a.base_every == 0:
                pubs[(dev, "base")].publish(pose_stamped(stamp, dev, *base))
            dropped = a.drop_last and i_phase == len(phases) - 1 and due[dev] >= stop   # this device's last frame
            if not dropped:
                pubs[(dev, "tool")].publish(pose_stamped(stamp, dev, base[0] + p_base, base[1]))
            q = TrackingQuality()
            q.header.stamp = ns_to_stamp(stamp)
            q.header.frame_id = dev
            q.body, q.visible, q.frame_number, q.fit_error = "tool", True, k, -1.0
            qpubs[dev].publish(q)
            if not dropped:
                sent[dev].append(stamp)
    unacked = [t for t in wait_for_acks(node, 60.0) if t.startswith(("/omc/", "/ots/"))]   # not /rosout ...
    if a.stamps:
        with open(a.stamps, "w") as f:
            json.dump(sent, f)
    print(json.dumps({**{k: len(v) for k, v in sent.items()}, "unacked": unacked}), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
