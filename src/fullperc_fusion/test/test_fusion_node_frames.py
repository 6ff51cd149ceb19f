"""fusion_node with ``inputs: frames``: one synthetic driver publishes every device frame twice -- per body
(``<prefix>/<body>/pose`` and the tool's ``/quality``) and as one ``<prefix>/bodies`` TrackedBodies
(synthetic_driver_pub.py ``--frames``) -- to two installed fusion_nodes at once, one reading each. The frames node's
final estimates (``fullperc/<target>/final``) must be the per-body node's: the same items, the same poses. Over DDS
on a busy machine the two may differ by micrometres (a record repaired by DDS after its item left one node's
history is fused without it there), so this test bounds the difference; that the two input paths give the same
result bit for bit for the same messages is ``test_fusion_inputs.py``'s (no DDS, no timing)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from fullperc_common.testing import RosSession, SpunNode, installed_exe, load_by_path, wait_for, wait_for_first_line

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
pytestmark = pytest.mark.system

FINAL = {"per_body": "/fullperc/tool/final", "frames": "/frames/tool/final"}
STATUS = {"per_body": "/fullperc/tool/status", "frames": "/frames/tool/status"}


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _listen(ctx, topics: list[str]) -> tuple[SpunNode, dict[str, list]]:
    """Subscribes ``topics`` in this process (a :class:`SpunNode`); the messages of each, in arrival order."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_msgs.msg import FusionStatus

    lis = SpunNode(ctx, "frames_test_listener")
    got: dict[str, list] = {t: [] for t in topics}
    qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
    for t in topics:
        lis.node.create_subscription(FusionStatus if t.endswith("status") else PoseStamped, t,
                                     lambda m, t=t: got[t].append(m), qos)
    lis.start()
    return lis, got


def test_frames_input_gives_the_per_body_result(tmp_path):
    common = ["-p", "filter:=fullperc", "-p", "filters:=[cbkf]", "-p", "init_samples:=20", "-p", "qos_depth:=2000"]
    frames_args = ["-p", "inputs:=frames", "-r", "__node:=fusion_frames",
                   "-r", f"{FINAL['per_body']}:={FINAL['frames']}", "-r", f"{STATUS['per_body']}:={STATUS['frames']}"]
    topics = [*FINAL.values(), *STATUS.values()]
    with RosSession(tmp_path) as s:
        procs = s.procs
        nodes = {"per_body": procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", *common],
                                         name="per_body"),
                 "frames": procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", *common,
                                        *frames_args], name="frames")}
        for n in nodes.values():
            wait_for_first_line(procs, n)
        lis, got = _listen(s.context, topics)
        node = lis.node
        try:
            wait_for(lambda: all(node.count_publishers(t) > 0 for t in topics), 60, what="both nodes' outputs")
            pub = procs.start([sys.executable, str(PUB), "--log", str(tmp_path / "pub.jsonl"), "--frames",
                               "--duration", "3.0"], name="pub")
            mod = load_by_path(PUB, "synthetic_driver_pub")
            wait_for(lambda: pub.poll() is not None or mod.log_complete(tmp_path / "pub.jsonl"), 90,
                     what="the publisher's data", detail=lambda: procs.log(pub)[-2000:])
            rows, _ = mod.read_log(tmp_path / "pub.jsonl")
            last = max(r["t_ns"] for r in rows if r["body"] == "tool")
            wait_for(lambda: all(got[t] and _ns(got[t][-1].header.stamp) >= last for t in FINAL.values()), 60,
                     what="both nodes' final estimates of the last tool sample",
                     detail=lambda: ({t: len(v) for t, v in got.items()}, procs.log(nodes["frames"])[-2000:]))
            wait_for(lambda: pub.poll() is not None, 30, what="the publisher to exit")
            assert pub.returncode == 0, procs.log(pub)
            assert all(n.poll() is None for n in nodes.values()), procs.log(nodes["frames"])
        finally:
            lis.close()

    def rows_of(topic: str) -> list[tuple]:
        return [(_ns(m.header.stamp), m.header.frame_id, m.pose.position.x, m.pose.position.y, m.pose.position.z,
                 m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w)
                for m in got[topic]]

    per_body, frames = {r[0]: r for r in rows_of(FINAL["per_body"])}, {r[0]: r for r in rows_of(FINAL["frames"])}
    n_omc = sum(1 for r in rows if r["body"] == "tool" and r["kind"] == "omc")   # an OTS sample pairs with one
    assert len(per_body) > 0.8 * n_omc, (len(per_body), n_omc)   # every item final, bar those before the links
    common = per_body.keys() & frames.keys()
    assert len(common) >= 0.95 * max(len(per_body), len(frames)), (len(common), len(per_body), len(frames))
    assert all(frames[t][1] == "base" for t in common)
    worst = max(max(abs(a - b) for a, b in zip(frames[t][2:], per_body[t][2:], strict=True)) for t in common)
    assert worst < 2e-5, worst   # 20 µm (position [m], quaternion): a body or source mixed up is millimetres off
    # both fused both sources while the Vega saw the tool: the frames node read the OTS frames too
    for key in STATUS:
        assert any(st.sources == 3 for st in got[STATUS[key]]), key
