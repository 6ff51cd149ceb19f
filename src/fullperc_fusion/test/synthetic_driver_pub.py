"""Stand-in for the three drivers in fusion_node's multi-process test: publishes synthetic
omc/<body>/pose (120 Hz, frame omc) and ots/<tool>/pose (60 Hz, frame ots) in real time -- relative names, so
``--ns /or1`` publishes /or1/omc/... (the default namespace: /omc/...).

The target (OMC body and OTS tool ``tool``) moves slowly in ``base``; the OMC sees it with a constant
offset, the OTS sees it only during [ots_from, ots_to) seconds. With ``--bad`` it also publishes a NaN
OMC pose, an OTS pose with a non-unit quaternion and, after the run, an OMC pose stamped 0.5 s before its last
sample -- once the node's /fullperc/tool/final has passed that stamp (at most ``--wait`` seconds), so the sample is
older than the node's history however far the node lagged (sent while the node was 0.5 s behind, it would have been
taken in the same batch as the samples it precedes, sorted by stamp: in order, not late).
Everything published is written as JSON lines to ``--log`` (kind, body, stamp, position, flags) so the
test can check the node's output against exactly what went in.

Faults for the /diagnostics alarms (each option repeatable; BODY is ``tool`` or one of ``--extra-bodies``,
further OMC bodies that follow the same path, seen by the OMC only):
  --omc-jump BODY:AT:DX   from AT seconds on, the OMC pose of BODY is DX metres off along omc x (a hop or jump)
  --omc-nan BODY:FROM     from FROM seconds on, every OMC pose of BODY has a NaN position
Timing (the time guard):
  --future AT:AHEAD       at AT seconds, one extra OMC pose of ``tool`` stamped AHEAD seconds in the future
  --pause AT:LEN          publish nothing from AT for LEN seconds (the node's idle flush runs meanwhile)
Static links (calibration, link monitoring):
  --static-only           publish only /omc/base, /omc/ots_rig and /ots/base (what `calibrate` subscribes to)
  --link-noise            sensor noise on those three (OMC 0.1 mm / 1 mrad, Vega 0.05 mm / 0.5 mrad per frame)
  --move-base AT:DX       from AT s on the reference marker is DX m further along omc x (OMC and Vega see it)
  --bump-ots AT:DX        from AT s on the Vega stands DX m further along its own x axis (its views of the base
                          and of the tool both change; the OMC's view of the rig too)

Namespaces and QoS (issue 39):
  --ns NS                 the node's namespace (every topic under it)
  --shift DX              the target's path DX m further along base x (two namespaces, two different poses)
  --best-effort           publish best effort (the sensor-data profile's reliability), not reliable

Frames (fusion_node ``inputs: frames``):
  --frames                also publish every device frame as one omc/bodies / ots/bodies (TrackedBodies: the
                          frame's bodies in publishing order, fit_error 2e-4 m (OMC) / 1e-4 m (OTS), markers 4,
                          frame number the frame's index) and the tool's omc/tool/quality and ots/tool/quality
                          (TrackingQuality, the same values): a per-body node and a frames node get the same input

Run: python synthetic_driver_pub.py --log out.jsonl [--duration 4] [--bad] [--extra-bodies probe,broken]
     [--omc-jump tool:2.0:1.0] [--omc-nan broken:1.0]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common.ros_conv import ns_to_stamp
from fullperc_common.so3 import so3_exp
from fullperc_common.transforms import T_to_pq, inv_T, make_T


def _rot(axis: str, deg: float) -> np.ndarray:
    """The rotation by ``deg`` about the x, y or z axis (fullperc_common.so3: a process started dozens of times in
    the suite is spared scipy.spatial's import)."""
    return so3_exp(math.radians(deg) * np.eye(3)["xyz".index(axis)])


T_OMC_BASE = make_T([1.0, 0.5, 0.8], R=_rot("z", 30))
T_OMC_OTS = make_T([3.0, 1.0, 1.5], R=_rot("y", 20) @ _rot("z", 150))   # extrinsic z then y
OMC_OFFSET = np.array([3e-3, -2e-3, 1e-3])


def log_complete(path) -> bool:
    """The ``--log`` file ends with its meta row: everything was published (the publisher may still be up a second
    for reliable delivery)."""
    try:
        text = open(path).read()
    except FileNotFoundError:
        return False
    return text.endswith("\n") and '"kind": "meta"' in text.rsplit("\n", 2)[-2]


def read_log(path) -> tuple[list[dict], int]:
    """The rows of a ``--log`` file (what was published) and its ``t0_ns`` (the meta row, written last)."""
    rows = [json.loads(line) for line in open(path).read().splitlines()]
    meta = next(r for r in rows if r["kind"] == "meta")
    return [r for r in rows if r["kind"] != "meta"], meta["t0_ns"]


def truth(t: float) -> np.ndarray:
    """T_base_tool at t seconds after start."""
    return make_T([0.5 + 0.05 * math.cos(0.5 * t), 0.05 * math.sin(0.5 * t), 0.3], R=_rot("z", 5 * t))


def msg(stamp_ns: int, frame: str, p, q) -> PoseStamped:
    m = PoseStamped()
    m.header.stamp = ns_to_stamp(stamp_ns)
    m.header.frame_id = frame
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in p)
    m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = (float(v) for v in q)
    return m


def flush_frames(pubs: dict, frames: dict, number: int) -> None:
    """--frames: one TrackedBodies per device frame gathered (and emptied from ``frames``), and its tool's
    TrackingQuality (the same values as the frame's entry for the tool)."""
    from fullperc_msgs.msg import TrackedBodies, TrackedBody, TrackingQuality

    for (dev, ns), bodies in sorted(frames.items(), key=lambda kv: kv[0][1]):
        fit = 2e-4 if dev == "omc" else 1e-4
        m = TrackedBodies(latency=0.002)
        m.header.stamp, m.header.frame_id = ns_to_stamp(ns), dev
        for body, p, q in bodies:
            b = TrackedBody(name=body, visible=True, fit_error=fit, frame_number=number, markers_used=4)
            b.pose = msg(ns, dev, p, q).pose
            m.bodies.append(b)
            if body == "tool":
                qm = TrackingQuality(header=m.header, body=body, visible=True, fit_error=fit, frame_number=number,
                                     markers_used=4, latency=0.002)
                pubs[f"{dev}/tool/quality"].publish(qm)
        pubs[f"{dev}/bodies"].publish(m)
    frames.clear()


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--log", required=True)
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--ots-from", type=float, default=0.8)
    ap.add_argument("--ots-to", type=float, default=2.5)
    ap.add_argument("--bad", action="store_true")
    ap.add_argument("--wait", type=float, default=30.0, help="max seconds to wait for the fusion_node")
    ap.add_argument("--extra-bodies", default="", help="comma-separated further OMC bodies (OMC only)")
    ap.add_argument("--omc-jump", action="append", default=[], metavar="BODY:AT:DX")
    ap.add_argument("--omc-nan", action="append", default=[], metavar="BODY:FROM")
    ap.add_argument("--static-only", action="store_true")
    ap.add_argument("--link-noise", action="store_true")
    ap.add_argument("--move-base", default=None, metavar="AT:DX")
    ap.add_argument("--bump-ots", default=None, metavar="AT:DX")
    ap.add_argument("--future", default=None, metavar="AT:AHEAD")
    ap.add_argument("--pause", default=None, metavar="AT:LEN")
    ap.add_argument("--ns", default="")
    ap.add_argument("--shift", type=float, default=0.0)
    ap.add_argument("--best-effort", action="store_true")
    ap.add_argument("--frames", action="store_true")
    a = ap.parse_args()
    future = tuple(float(x) for x in a.future.split(":")) if a.future else None
    pause = tuple(float(x) for x in a.pause.split(":")) if a.pause else None
    move_base = tuple(float(x) for x in a.move_base.split(":")) if a.move_base else None
    bump_ots = tuple(float(x) for x in a.bump_ots.split(":")) if a.bump_ots else None
    extra = [b for b in a.extra_bodies.split(",") if b]
    jumps = {b: (float(at), float(dx)) for b, at, dx in (j.split(":") for j in a.omc_jump)}
    nans = {b: float(at) for b, at in (j.split(":") for j in a.omc_nan)}

    rclpy.init()
    node = rclpy.create_node("synthetic_driver_pub", namespace=a.ns or None)
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT if a.best_effort
                     else ReliabilityPolicy.RELIABLE)
    topics = ("omc/base/pose", "omc/ots_rig/pose", "ots/base/pose") if a.static_only else \
        ("omc/base/pose", "omc/ots_rig/pose", "omc/tool/pose", "ots/base/pose", "ots/tool/pose",
         *(f"omc/{b}/pose" for b in extra))
    pubs = {k: node.create_publisher(PoseStamped, k, qos) for k in topics}
    if a.frames:
        from fullperc_msgs.msg import TrackedBodies, TrackingQuality
        pubs |= {f"{d}/bodies": node.create_publisher(TrackedBodies, f"{d}/bodies", qos) for d in ("omc", "ots")}
        pubs |= {f"{d}/tool/quality": node.create_publisher(TrackingQuality, f"{d}/tool/quality", qos)
                 for d in ("omc", "ots")}
    end = time.monotonic() + a.wait
    while time.monotonic() < end and any(p.get_subscription_count() == 0 for p in pubs.values()):
        rclpy.spin_once(node, timeout_sec=0.05)
    if any(p.get_subscription_count() == 0 for p in pubs.values()):
        print("no subscriber appeared", file=sys.stderr)
        return 1
    time.sleep(0.5)  # let the other direction of discovery settle too

    rng = np.random.default_rng(0)
    link_rng = np.random.default_rng(1)   # its own stream: without --link-noise the other samples are unchanged
    log = open(a.log, "w")  # noqa: SIM115 - closed below

    frames: dict[tuple[str, int], list] = {}   # --frames: (device, stamp) -> the bodies published, in order

    def pub(topic, kind, body, ns, frame, p, q, **flags):
        if topic not in pubs:
            return
        pubs[topic].publish(msg(ns, frame, p, q))
        if a.frames:
            frames.setdefault((frame, ns), []).append((body, p, q))
        log.write(json.dumps({"kind": kind, "body": body, "t_ns": ns, "p": [float(v) for v in p], **flags}) + "\n")

    def seen(T, sig_p, sig_r):
        """T with sensor noise when --link-noise (position sig_p [m], rotation sig_r [rad] per axis)."""
        if not a.link_noise:
            return T_to_pq(T)
        d = make_T(link_rng.normal(0, sig_p, 3), R=so3_exp(link_rng.normal(0, sig_r, 3)))
        return T_to_pq(T @ d)

    final_max = [0]   # newest stamp of the node's final estimates (--bad: when to send the backwards sample)
    if a.bad:
        node.create_subscription(
            PoseStamped, "fullperc/tool/final",
            lambda m: final_max.__setitem__(0, max(final_max[0], m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)),
            QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    t0_ns = time.time_ns()
    t0 = time.monotonic()
    k = 0
    bad_done = set()
    while True:
        t = k / 120.0
        if t > a.duration:
            break
        while time.monotonic() - t0 < t:
            time.sleep(0.0005)
        ns = t0_ns + round(t * 1e9)
        if pause is not None and pause[0] <= t < pause[0] + pause[1]:
            k += 1
            continue
        T_omc_base, T_omc_ots, flags_links = T_OMC_BASE, T_OMC_OTS, {}
        if move_base is not None and t >= move_base[0]:
            T_omc_base = make_T([move_base[1], 0.0, 0.0]) @ T_OMC_BASE
            flags_links["moved"] = move_base[1]
        if bump_ots is not None and t >= bump_ots[0]:
            T_omc_ots = T_OMC_OTS @ make_T([bump_ots[1], 0.0, 0.0])
            flags_links["bumped"] = bump_ots[1]
        T_ots_base = inv_T(T_omc_ots) @ T_omc_base
        Tt = T_OMC_BASE @ make_T([a.shift, 0.0, 0.0]) @ truth(t)
        p0, q = T_to_pq(Tt)
        p = p0 + OMC_OFFSET + rng.normal(0, 2e-4, 3)
        for b in ("tool", *extra):
            flags = {}
            pb = p if b == "tool" else p0 + OMC_OFFSET + rng.normal(0, 2e-4, 3)
            if b in jumps and t >= jumps[b][0]:
                pb = pb + np.array([jumps[b][1], 0.0, 0.0])
                flags["jump"] = jumps[b][1]
            if b in nans and t >= nans[b]:
                pb = np.array([math.nan, pb[1], pb[2]])
                flags["bad"] = "nan"
            if b == "tool":
                p = pb
                tool_flags = flags
            else:
                pub(f"omc/{b}/pose", "omc", b, ns, "omc", pb, q, **flags)
        pub("omc/base/pose", "omc", "base", ns, "omc", *seen(T_omc_base, 1e-4, 1e-3), **flags_links)
        pub("omc/ots_rig/pose", "omc", "ots_rig", ns, "omc", *seen(T_omc_ots, 1e-4, 1e-3), **flags_links)
        if a.bad and t >= 1.5 and "nan" not in bad_done:
            bad_done.add("nan")
            pub("omc/tool/pose", "omc", "tool", ns, "omc", [math.nan, p[1], p[2]], q, bad="nan")
        else:
            pub("omc/tool/pose", "omc", "tool", ns, "omc", p, q, **tool_flags)
        if future is not None and t >= future[0] and "future" not in bad_done:
            bad_done.add("future")
            pub("omc/tool/pose", "omc", "tool", ns + round(future[1] * 1e9), "omc", p, q, bad="future")
        if k % 2 == 0:
            ns_l = ns + 3_000_000
            pub("ots/base/pose", "ots", "base", ns_l, "ots", *seen(T_ots_base, 5e-5, 5e-4), **flags_links)
            if a.ots_from <= t < a.ots_to and not a.static_only:
                Tl = T_ots_base @ make_T([a.shift, 0.0, 0.0]) @ truth(t + 0.003)
                pl, ql = T_to_pq(Tl)
                pl = pl + rng.normal(0, 1e-4, 3)
                if a.bad and t >= 1.7 and "nonunit" not in bad_done:
                    bad_done.add("nonunit")
                    pub("ots/tool/pose", "ots", "tool", ns_l, "ots", pl, 1.5 * ql, bad="nonunit")
                else:
                    pub("ots/tool/pose", "ots", "tool", ns_l, "ots", pl, ql)
        flush_frames(pubs, frames, k)
        rclpy.spin_once(node, timeout_sec=0)
        last_ns, last_p, last_q = ns, p, q
        k += 1
    if a.bad:   # a sample 0.5 s older than the last one (between two frames: not a duplicate stamp)
        back_ns = last_ns - 500_000_000 + 1_000_000
        end = time.monotonic() + a.wait
        while time.monotonic() < end and final_max[0] < back_ns + 200_000_000:
            rclpy.spin_once(node, timeout_sec=0.05)
        pub("omc/tool/pose", "omc", "tool", back_ns, "omc", last_p, last_q, bad="backwards",
            node_final_ns=final_max[0])
        flush_frames(pubs, frames, k)
    log.write(json.dumps({"kind": "meta", "t0_ns": t0_ns}) + "\n")
    log.close()
    time.sleep(1.0)   # keep the publishers alive until reliable delivery completed
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
