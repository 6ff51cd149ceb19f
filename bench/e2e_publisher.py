"""Driver stand-in for the live benches (fused latency, capacity): OMC and OTS poses at device rates, in real time.

OMC (frame ``omc``) at ``--omc-hz``: bodies ``base`` and every ``--tools`` name; OTS (frame ``ots``) at
``--ots-hz``: tools ``base`` and the same names. Every message is stamped with the host time just before it is
published (acquisition time == publish time for this stand-in), so the subscriber's receive time minus the fused
pose's stamp is the end-to-end latency from a driver's publish to the fused pose.
With ``--frames`` each device frame is also published as one ``/omc/bodies`` / ``/ots/bodies`` (TrackedBodies,
what fullperc's drivers publish beside the per-body topics; fusion_node ``inputs: frames``), every body of a frame
then stamped alike (the frame's stamp), and the data waits for those topics' subscribers instead of the per-body ones
(``/omc/<first tool>/pose`` still needs one: the bench's raw DDS baseline).
Prints one JSON line at the end: frames published per source and the achieved frame rates (a stand-in that
cannot keep up with many tools shows it here, rather than as a loss of the node).
"""

from __future__ import annotations

import argparse
import json
import math
import time

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
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
    ap.add_argument("--wait-subscribers", type=int, default=1,
                    help="subscribers /omc/<first tool>/pose must have before data flows (every other target "
                         "topic: 1)")
    ap.add_argument("--wait-base", type=int, default=1,
                    help="subscribers /omc/base/pose and /ots/base/pose must have (one per fusion process)")
    ap.add_argument("--tools", default="tool", help="comma-separated target names (default: tool)")
    ap.add_argument("--frames", action="store_true", help="also publish /omc/bodies and /ots/bodies (TrackedBodies)")
    ap.add_argument("--stamps", help="write the target samples' stamps here (JSON: {omc|ots: {tool: [ns]}})")
    a = ap.parse_args()
    rclpy.init()
    node = rclpy.create_node("e2e_publisher")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    tools = [t for t in a.tools.split(",") if t]
    pubs = {f"/{d}/{b}/pose": node.create_publisher(PoseStamped, f"/{d}/{b}/pose", qos)
            for d in ("omc", "ots") for b in ("base", *tools)}
    need = {f"/omc/{tools[0]}/pose": a.wait_subscribers, "/omc/base/pose": a.wait_base, "/ots/base/pose": a.wait_base}
    if a.frames:
        from fullperc_msgs.msg import TrackedBodies, TrackedBody

        pubs |= {f"/{d}/bodies": node.create_publisher(TrackedBodies, f"/{d}/bodies", qos) for d in ("omc", "ots")}
        need = {t: 0 for t in pubs} | {f"/omc/{tools[0]}/pose": a.wait_subscribers, "/omc/bodies": a.wait_base,
                                       "/ots/bodies": a.wait_base}

    def frame(dev: str, ns: int, bodies: list[tuple[str, object, object]]) -> None:
        """--frames: the device frame's bodies (name, p, q) as one TrackedBodies."""
        m = TrackedBodies(latency=0.0)
        m.header.stamp, m.header.frame_id = ns_to_stamp(ns), dev
        m.bodies = [TrackedBody(name=n, visible=True, pose=pose_stamped(ns, dev, p, q).pose, frame_number=counts[dev])
                    for n, p, q in bodies]
        pubs[f"/{dev}/bodies"].publish(m)

    def device_frame(dev: str, bodies: list[tuple[str, object, object]]) -> None:
        """One device frame, the base first: each body's pose stamped just before its publish (with --frames every
        body with the frame's one stamp, and the frame's TrackedBodies first); the tools' stamps recorded."""
        ns = time.time_ns()
        if a.frames:
            frame(dev, ns, bodies)
        for name, p, q in bodies:
            t_ns = ns if a.frames else time.time_ns()
            pubs[f"/{dev}/{name}/pose"].publish(pose_stamped(t_ns, dev, p, q))
            if name != "base":
                stamps[dev][name].append(t_ns)
        counts[dev] += 1

    while any(p.get_subscription_count() < need.get(topic, 1) for topic, p in pubs.items()):
        rclpy.spin_once(node, timeout_sec=0.05)
    time.sleep(1.0)  # discovery runs both ways; let the node match before data flows
    T_ots_omc = inv_T(T_OMC_OTS)
    p_base_omc, q_base_omc = T_to_pq(T_OMC_BASE)
    p_base_ots, q_base_ots = T_to_pq(T_ots_omc @ T_OMC_BASE)
    t0 = time.monotonic()
    next_omc = next_ots = t0
    counts = {"omc": 0, "ots": 0}
    stamps: dict[str, dict[str, list[int]]] = {"omc": {t: [] for t in tools}, "ots": {t: [] for t in tools}}
    T_ots_omc_q = T_to_pq(T_ots_omc)[1]
    while (now := time.monotonic()) - t0 < a.duration:
        t = now - t0
        if now >= next_omc:
            p = tool_in_omc(t)
            device_frame("omc", [("base", p_base_omc, q_base_omc), *((tool, p, Q_ID) for tool in tools)])
            next_omc += 1.0 / a.omc_hz
        if now >= next_ots:
            p_ots = apply_T(T_ots_omc, tool_in_omc(t))
            device_frame("ots", [("base", p_base_ots, q_base_ots), *((tool, p_ots, T_ots_omc_q) for tool in tools)])
            next_ots += 1.0 / a.ots_hz
        time.sleep(max(0.0, min(next_omc, next_ots) - time.monotonic()))
    elapsed = time.monotonic() - t0
    time.sleep(1.0)
    if a.stamps:
        with open(a.stamps, "w") as f:
            json.dump(stamps, f)
    print(json.dumps({**counts, "omc_hz": counts["omc"] / elapsed, "ots_hz": counts["ots"] / elapsed}), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
