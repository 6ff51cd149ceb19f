"""The five fullperc nodes with a data source each, for test_node_lifecycle.py and soak/soak_signals.py.

Imported: :data:`NODES` (how to start each installed node, what feeds it, which output shows that data flows)
and :func:`signal_cycle` (start the node, wait until its output flows, send a signal, collect the exit).
Run as a script it is the data source that runs until stopped:

  python lifecycle_nodes.py omc --port P      UDP OMC frames (simulator wire format) at 500 Hz
  python lifecycle_nodes.py diana --port P    UDP Diana joint states at 500 Hz
  python lifecycle_nodes.py poses fusion      /omc/{base,ots_rig,tool}/pose 120 Hz, /ots/{base,tool}/pose 60 Hz
  python lifecycle_nodes.py poses margin      /fullperc/tool/pose (frame omc) and /omc/base/pose at 120 Hz

ndi_driver is fed by the installed ``vega_emulator``. Nothing here imports fullperc_eval.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from fullperc_common.ports import free_port
from fullperc_common.testing import Procs, poll_until, workspace_root

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class NodeSpec:
    name: str
    pkg: str
    float_param: str            # a float parameter (for the "-p name:=0" test)
    output: str                 # topic whose messages show that data flows through the node
    output_type: str            # "PoseStamped" | "JointState" | "Region"
    feed: str                   # "omc" | "diana" | "vega" | "poses fusion" | "poses margin"
    params_file: str            # the parameter reference printed by --help (in the package's config/)
    extra_args: tuple[str, ...] = field(default=())

    def exe(self) -> str:
        return str(workspace_root() / "install" / self.pkg / "lib" / self.pkg / self.name)


NODES: dict[str, NodeSpec] = {s.name: s for s in (
    NodeSpec("omc_driver", "fullperc_drivers", "stale_timeout_s", "/omc/base/pose", "PoseStamped", "omc", "omc.yaml"),
    NodeSpec("ndi_driver", "fullperc_drivers", "read_timeout_s", "/ots/tool/pose", "PoseStamped", "vega",
             "ndi_vega.yaml"),
    NodeSpec("diana_state", "fullperc_drivers", "rate_hz", "/diana/joint_states", "JointState", "diana",
             "diana.yaml"),
    NodeSpec("fusion_node", "fullperc_fusion", "slop", "/fullperc/tool/pose", "PoseStamped", "poses fusion",
             "fusion.yaml"),
    NodeSpec("margin_node", "fullperc_fusion", "map_resolution", "/fullperc/tool/region", "Region", "poses margin",
             "margin.yaml"),
)}


def msg_type(name: str):
    if name == "PoseStamped":
        from geometry_msgs.msg import PoseStamped
        return PoseStamped
    if name == "JointState":
        from sensor_msgs.msg import JointState
        return JointState
    from fullperc_msgs.msg import Region
    return Region




def start_feed(procs: Procs, spec: NodeSpec, tmp: Path) -> list[str]:
    """Start the node's data source; returns the ROS arguments the node needs to receive from it."""
    py = sys.executable
    if spec.feed in ("omc", "diana"):
        port = free_port()
        procs.start([py, __file__, spec.feed, "--port", str(port)], name=f"feed_{spec.feed}")
        return ["--ros-args", "-p", f"stream_port:={port}"]
    if spec.feed == "vega":
        port_file = tmp / "vega_port"
        exe = workspace_root() / "install" / "fullperc_eval" / "lib" / "fullperc_eval" / "vega_emulator"
        emu = procs.start([str(exe), "--port", "0", "--port-file", str(port_file),
                           "--pose", "tool=25,-40,-1500,0,0,0.6,0.8"], name="vega_emulator")
        if not poll_until(lambda: port_file.exists() and port_file.read_text().strip(), 60):
            raise RuntimeError(f"vega_emulator did not report its port:\n{procs.log(emu)}")
        return ["--ros-args", "-p", f"port:={int(port_file.read_text())}"]
    kind = spec.feed.split()[1]
    procs.start([py, __file__, "poses", kind], name=f"feed_poses_{kind}")
    return []


@dataclass
class CycleResult:
    sig: str
    returncode: int | None = None
    flowed: int = 0             # output messages seen before the signal
    log: str = ""
    problem: str = ""           # why this run is not a clean exit ("" = clean)

    @property
    def clean(self) -> bool:
        return not self.problem


def signal_cycle(procs: Procs, spec: NodeSpec, ros_args: list[str], counter, sig: int, k: int,
                 min_msgs: int = 5, liveness_s: float = 90.0, on_flowing=None, again_after_s: float | None = None
                 ) -> CycleResult:
    """Start ``spec``'s node, wait until ``min_msgs`` new messages of its output arrived, send ``sig``.

    With ``again_after_s`` the same signal is sent a second time that long after the first, i.e. while the node
    shuts down (Ctrl-C pressed twice, or a launcher escalating). Clean: exit status 0 and no "Traceback" in
    the node's output. ``on_flowing(p, counter)`` runs once the data flows, before the signal. The timeouts are
    liveness bounds (a hung node must not hang the run), not measurements.

    ``counter`` counts ``spec.output`` (a :class:`~fullperc_common.testing.TopicCounter`), or is a function that
    makes one: then it is made once the node has written its first line (its DDS participant is up) and closed at
    the end of the cycle. A reader that exists before a new process's participant appears is often matched with its
    writers only at Fast DDS's next periodic announcement (up to ~3 s later, seen here: 0.5-3.6 s to the first
    message); one made after the participant appeared is matched at once.
    """
    res = CycleResult(signal.Signals(sig).name + ("" if again_after_s is None else " twice"))
    make = counter if callable(counter) else None
    try:
        if make is None:
            before = counter.count(spec.output)
        p = procs.start([spec.exe(), *ros_args], name=f"{spec.name}_{k}")
        if make is not None:
            poll_until(lambda: p.poll() is not None or procs.log(p).strip(), liveness_s)
            counter, before = make(), 0
        return _cycle(procs, spec, p, counter, before, res, sig, min_msgs, liveness_s, on_flowing, again_after_s)
    finally:
        if make is not None and not callable(counter):
            counter.close()


def _cycle(procs, spec, p, counter, before, res, sig, min_msgs, liveness_s, on_flowing, again_after_s):
    flowing = poll_until(lambda: p.poll() is not None or counter.count(spec.output) - before >= min_msgs,
                         liveness_s)
    res.flowed = counter.count(spec.output) - before
    if p.poll() is not None:
        res.returncode = p.returncode
        res.log = procs.log(p)
        res.problem = f"exited with {p.returncode} before the signal"
        return res
    if not flowing:
        procs.stop(p, signal.SIGKILL)
        res.log = procs.log(p)
        res.problem = f"no data flowed within {liveness_s:.0f} s ({res.flowed} messages on {spec.output})"
        return res
    if on_flowing is not None:
        on_flowing(p, counter)
    try:
        os.killpg(p.pid, sig)
        if again_after_s is not None:
            time.sleep(again_after_s)
            os.killpg(p.pid, sig)
    except ProcessLookupError:
        pass
    if poll_until(lambda: p.poll() is not None, liveness_s) is None:
        procs.stop(p, signal.SIGKILL)
        res.problem = f"still running {liveness_s:.0f} s after {res.sig}"
    res.returncode = p.wait()
    res.log = procs.log(p)
    if not res.problem and res.returncode != 0:
        res.problem = f"exit status {res.returncode} after {res.sig}"
    elif not res.problem and "Traceback" in res.log:
        res.problem = f"traceback in the output after {res.sig}"
    return res


# ---- data sources (script mode) -------------------------------------------------------------------------
def _feed_udp(kind: str, port: int, rate: float) -> None:
    import numpy as np

    from fullperc_drivers.streams import DianaState, OmcBody, OmcFrame, encode_diana, encode_omc

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0, k = time.monotonic(), 0
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    while True:
        k += 1
        time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
        now = time.time_ns()
        if kind == "omc":
            data = encode_omc(OmcFrame(1000 + k, now - 2_000_000, 0.002, [
                OmcBody(1, "base", np.array([1000.0, -500.0, 750.0]), ident, 0.1, True, 4),
                OmcBody(2, "tool", np.array([200.0, 300.0 + 0.1 * (k % 1000), 1200.0]), ident, 0.2, True, 5),
                OmcBody(3, "ots_rig", np.array([1.0, 2.0, 3.0]), ident, 0.1, True, 4)]))
        else:
            q = np.array([0.3 * math.sin(k / 100 + j) for j in range(7)]) + np.array([0, 0, 0, 1.0, 0, 0, 0])
            data = encode_diana(DianaState(k, now, q, np.zeros(7)))
        try:
            sock.sendto(data, ("127.0.0.1", port))
        except OSError:
            pass  # nobody bound yet on some systems: keep sending


def _feed_poses(kind: str, rate: float) -> None:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node(f"lifecycle_feed_{kind}")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    # Static geometry: base marker and OTS rig seen by the OMC, base and tool seen by the OTS, tool by both.
    # T_omc_ots = translation (3, 1, 1.5) with identity rotation; T_omc_base = (1, 0.5, 0.8).
    base_omc, rig_omc, ots_omc = (1.0, 0.5, 0.8), (3.0, 1.0, 1.5), (3.0, 1.0, 1.5)
    topics = {"fusion": ["/omc/base/pose", "/omc/ots_rig/pose", "/omc/tool/pose", "/ots/base/pose",
                         "/ots/tool/pose"],
              "margin": ["/fullperc/tool/pose", "/omc/base/pose"]}[kind]
    pubs = {t: node.create_publisher(PoseStamped, t, qos) for t in topics}

    def publish(topic: str, stamp_ns: int, frame: str, p) -> None:
        m = PoseStamped()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        m.header.frame_id = frame
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in p)
        m.pose.orientation.w = 1.0
        pubs[topic].publish(m)

    t0, k = time.monotonic(), 0
    try:
        while rclpy.ok():
            k += 1
            time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
            ns = time.time_ns()
            tool_base = (0.5 + 0.05 * math.cos(k / 240), 0.05 * math.sin(k / 240), 0.3)
            tool_omc = tuple(a + b for a, b in zip(base_omc, tool_base, strict=True))
            publish("/omc/base/pose", ns, "omc", base_omc)
            if kind == "margin":
                publish("/fullperc/tool/pose", ns, "omc", tool_omc)
                continue
            publish("/omc/ots_rig/pose", ns, "omc", rig_omc)
            publish("/omc/tool/pose", ns, "omc", tool_omc)
            if k % 2 == 0:
                publish("/ots/base/pose", ns + 1_000_000, "ots", tuple(a - b for a, b in zip(base_omc, ots_omc,
                                                                                              strict=True)))
                publish("/ots/tool/pose", ns + 1_000_000, "ots", tuple(a - b for a, b in zip(tool_omc, ots_omc,
                                                                                              strict=True)))
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="kind", required=True)
    for k in ("omc", "diana"):
        s = sub.add_parser(k)
        s.add_argument("--port", type=int, required=True)
        s.add_argument("--rate", type=float, default=500.0)
    s = sub.add_parser("poses")
    s.add_argument("which", choices=("fusion", "margin"))
    s.add_argument("--rate", type=float, default=120.0)
    a = ap.parse_args()
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        if a.kind == "poses":
            _feed_poses(a.which, a.rate)
        else:
            _feed_udp(a.kind, a.port, a.rate)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
