"""fusion_node's TF across processes (issue 17 item 1): synthetic driver topics from one process, the installed
fusion_node in another; this test subscribes to /tf and /tf_static (a late, transient-local subscriber too)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import SpunNode, installed_exe, load_by_path, side_by_side_fixture, wait_for

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
pytestmark = pytest.mark.system
DIANA_BASE = [0.4, -0.3, 0.0, 0.0, 0.0, 0.7071067811865476, 0.7071067811865476]


def _pub_module():
    return load_by_path(PUB, "synthetic_driver_pub")


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class TfListener(SpunNode):
    def __init__(self, ctx):
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_common.tf import dynamic_qos, static_qos
        from tf2_msgs.msg import TFMessage

        self.TFMessage, self.static_qos = TFMessage, static_qos
        super().__init__(ctx, "fusion_tf_listener")
        self.tf, self.static, self.late_static, self.poses, self.final = [], [], [], [], []
        self.node.create_subscription(TFMessage, "/tf", self.tf.append, dynamic_qos())
        self.node.create_subscription(TFMessage, "/tf_static", self.static.append, static_qos())
        self.node.create_subscription(PoseStamped, "/fullperc/tool/pose", self.poses.append,
                                      QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE))
        self.node.create_subscription(PoseStamped, "/fullperc/tool/final", self.final.append,
                                      QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE))
        self.start()

    def subscribe_late(self):
        self.node.create_subscription(self.TFMessage, "/tf_static", self.late_static.append, self.static_qos())


def _static_map(msg) -> dict:
    from fullperc_common.tf import transform_to_T
    return {t.child_frame_id: (t.header.frame_id, transform_to_T(t)) for t in msg.transforms}


def _fusion_node_broadcasts_tf_and_tf_static(procs, rclpy_context, python_exe, tmp_path):
    mod = _pub_module()
    lis = TfListener(rclpy_context)
    try:
        pose7 = "[" + ", ".join(repr(v) for v in DIANA_BASE) + "]"
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p", "init_samples:=20",
                            "-p", f"tf.diana_base:={pose7}"], name="fusion_node")
        wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in ("/tf", "/tf_static",
                                                                         "/fullperc/tool/pose")),
                 60, what="fusion_node's publishers")
        wait_for(lambda: all(s.get_publisher_count() > 0 for s in lis.node.subscriptions), 60,
                 what="subscriptions matched")
        # before any data only the given link: base -> diana_base (transient local: delivered although late)
        wait_for(lambda: lis.static, 60, what="/tf_static with tf.diana_base")
        assert set(_static_map(lis.static[0])) == {"diana_base"}
        pub = procs.start([python_exe, str(PUB), "--log", str(tmp_path / "pub.jsonl"), "--duration", "2.0"],
                          name="pub")
        wait_for(lambda: pub.poll() is not None, 90, what="publisher to finish")
        assert pub.returncode == 0, procs.log(pub)
        # every output is out once the newest tool sample is final (the idle flush); then /tf and the poses agree
        rows = [json.loads(ln) for ln in (tmp_path / "pub.jsonl").read_text().splitlines()]
        last_tool = max(r["t_ns"] for r in rows if r.get("body") == "tool")
        wait_for(lambda: lis.final and _ns(lis.final[-1].header.stamp) >= last_tool, 30,
                 what="the newest tool sample final")
        wait_for(lambda: len(lis.poses) == sum(len(m.transforms) for m in lis.tf), 30, what="poses and /tf agree")
        lis.subscribe_late()   # a subscriber that joins now gets the whole static tree from one message
        wait_for(lambda: lis.late_static, 60, what="late /tf_static")
        assert node.poll() is None, procs.log(node)
    finally:
        lis.close()

    # /tf: base -> tool, one per fused output of the primary filter, same stamp and pose as /fullperc/tool/pose
    trs = [t for m in lis.tf for t in m.transforms]
    assert trs and all((t.header.frame_id, t.child_frame_id) == ("base", "tool") for t in trs)
    by_stamp = {_ns(p.header.stamp): p.pose for p in lis.poses}
    for t in trs:
        p = by_stamp[_ns(t.header.stamp)]
        assert np.allclose([t.transform.translation.x, t.transform.translation.y, t.transform.translation.z],
                           [p.position.x, p.position.y, p.position.z], atol=1e-12)
        assert np.allclose([t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
                            t.transform.rotation.w],
                           [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w], atol=1e-9)
    # /tf_static: the union, with the links the synthetic drivers were built from (averaged, noise-free input)
    for msg in (lis.static[-1], lis.late_static[0]):
        links = _static_map(msg)
        assert set(links) == {"base", "ots", "diana_base"}
        assert links["base"][0] == "omc" and links["ots"][0] == "base" and links["diana_base"][0] == "base"
        np.testing.assert_allclose(links["base"][1], mod.T_OMC_BASE, atol=1e-6)
        T_base_ots = np.linalg.inv(mod.T_OMC_BASE) @ mod.T_OMC_OTS
        np.testing.assert_allclose(links["ots"][1], T_base_ots, atol=1e-6)
        np.testing.assert_allclose(links["diana_base"][1][:3, 3], DIANA_BASE[:3], atol=1e-12)
    assert len(lis.late_static) == 1


def _tf_disabled_publishes_no_tf(procs, rclpy_context):
    lis = TfListener(rclpy_context)
    try:
        p = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p", "tf.enabled:=false"],
                        name="fusion_node")
        wait_for(lambda: lis.node.count_publishers("/fullperc/tool/pose") > 0 or p.poll() is not None, 60,
                 what="fusion_node's publishers")
        assert p.poll() is None, procs.log(p)
        assert lis.node.count_publishers("/tf") == 0 and lis.node.count_publishers("/tf_static") == 0
    finally:
        lis.close()


scenarios = side_by_side_fixture(
    _fusion_node_broadcasts_tf_and_tf_static,
    _tf_disabled_publishes_no_tf)


def test_fusion_node_broadcasts_tf_and_tf_static(scenarios, request):
    scenarios.result(request.node.name)


def test_tf_disabled_publishes_no_tf(scenarios, request):
    scenarios.result(request.node.name)


def test_tf_rate_reaches_the_broadcaster_and_a_negative_one_is_refused(rclpy_context):
    """``tf.rate`` is the /tf broadcaster's cap (its behaviour: test_tf.py); below 0 it is refused at start."""
    from rclpy.parameter import Parameter

    from fullperc_common.params import ParameterError
    from fullperc_fusion.fusion_node import FusionNode

    node = FusionNode(context=rclpy_context, parameter_overrides=[Parameter("tf.rate", value=50.0)])
    try:
        assert node._tf.period_ns == 20_000_000
    finally:
        node.destroy_node()
    default = FusionNode(context=rclpy_context)
    try:
        assert default._tf.period_ns == 0   # every output
    finally:
        default.destroy_node()
    with pytest.raises(ParameterError, match="tf.rate"):
        FusionNode(context=rclpy_context, parameter_overrides=[Parameter("tf.rate", value=-1.0)])
