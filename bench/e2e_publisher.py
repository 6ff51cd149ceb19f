"""Driver stand-in for bench_e2e_latency: publishes OMC and OTS poses at device rates, in real time.

OMC (frame ``omc``) at ``--omc-hz``: bodies ``base`` and ``tool``; OTS (frame ``ots``) at ``--ots-hz``:
tools ``base`` and ``tool``. Every message is stamped with the host time at which it is published
(acquisition time == publish time for this stand-in), so the subscriber's receive time minus the fused
pose's stamp is the end-to-end latency from a driver's publish to the fused pose.
Prints one JSON line at the end: how many target samples were published per source.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common.ros_conv import pose_stamped
from fullperc_common.transforms import T_to_pq, apply_T, inv_T, make_T

T_OMC_BASE = make_T([1.0, 0.5, 0.8], [0, 0, 0.2588190451, 0.9659258263])
T_OMC_OTS = make_T([3.0, 1.0, 1.5], [0, 0, 0.9659258263, 0.2588190451])
Q_ID = [0.0, 0.0, 0.0, 1.0]


def tool_in_omc(t: float):
    p_base = [0.4 + 0.05 * math.cos(0.5 * t), 0.05 * math.sin(0.5 * t), 0.3]
    return apply_T(T_OMC_BASE, p_base)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--omc-hz", type=float, default=240.0)
    ap.add_argument("--ots-hz", type=float, default=400.0)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--wait-subscribers", type=int, default=1)
    ap.add_argument("--stamps", help="write the target samples' stamps here (JSON: omc, ots lists)")
    a = ap.parse_args()
    rclpy.init()
    node = rclpy.create_node("e2e_publisher")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {k: node.create_publisher(PoseStamped, k, qos)
            for k in ("/omc/base/pose", "/omc/tool/pose", "/ots/base/pose", "/ots/tool/pose")}
    while pubs["/omc/tool/pose"].get_subscription_count() < a.wait_subscribers:
        rclpy.spin_once(node, timeout_sec=0.05)
    time.sleep(1.0)  # discovery runs both ways; let the node match before data flows
    T_ots_omc = inv_T(T_OMC_OTS)
    p_base_omc, q_base_omc = T_to_pq(T_OMC_BASE)
    p_base_ots, q_base_ots = T_to_pq(T_ots_omc @ T_OMC_BASE)
    t0 = time.monotonic()
    next_omc = next_ots = t0
    counts = {"omc": 0, "ots": 0}
    stamps: dict[str, list[int]] = {"omc": [], "ots": []}
    while (now := time.monotonic()) - t0 < a.duration:
        t = now - t0
        if now >= next_omc:
            ns = time.time_ns()
            pubs["/omc/base/pose"].publish(pose_stamped(ns, "omc", p_base_omc, q_base_omc))
            pubs["/omc/tool/pose"].publish(pose_stamped(ns, "omc", tool_in_omc(t), Q_ID))
            counts["omc"] += 1
            stamps["omc"].append(ns)
            next_omc += 1.0 / a.omc_hz
        if now >= next_ots:
            ns = time.time_ns()
            pubs["/ots/base/pose"].publish(pose_stamped(ns, "ots", p_base_ots, q_base_ots))
            p_ots = apply_T(T_ots_omc, tool_in_omc(t))
            pubs["/ots/tool/pose"].publish(pose_stamped(ns, "ots", p_ots, T_to_pq(T_ots_omc)[1]))
            counts["ots"] += 1
            stamps["ots"].append(ns)
            next_ots += 1.0 / a.ots_hz
        time.sleep(max(0.0, min(next_omc, next_ots) - time.monotonic()))
    time.sleep(1.0)
    if a.stamps:
        with open(a.stamps, "w") as f:
            json.dump(stamps, f)
    print(json.dumps(counts), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
