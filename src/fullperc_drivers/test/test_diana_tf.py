"""diana_state's /tf (issue 17 item 1): the arm's links from FK, chained, are the flange/tool poses; across
processes on the ``diana_api`` backend with the compiled C double."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).parent))
from test_omc_driver import Listener as _OmcListener  # noqa: E402  (same spin helpers)

from fullperc_drivers.diana_kinematics import DianaKinematics  # noqa: E402

TOOL = [0.01, 0.02, 0.15, *Rotation.from_euler("xyz", [0.1, 0.0, -0.3]).as_quat()]


def _chain(links, child):
    parents = {c: (p, T) for p, c, T in links}
    T = np.eye(4)
    while child in parents:
        p, T_pc = parents[child]
        T = T_pc @ T
        child = p
    return child, T


def test_link_transforms_chain_to_fk():
    kin = DianaKinematics(tool_offset=TOOL)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(-1.5, 1.5, 7)
        links = kin.link_transforms(q, "diana_base", tool=True)
        assert [c for _, c, _ in links] == [f"diana_link{i}" for i in range(1, 8)] + ["diana_flange", "diana_tool"]
        root, T = _chain(links, "diana_flange")
        assert root == "diana_base"
        np.testing.assert_allclose(T, kin.fk(q), atol=1e-12)
        np.testing.assert_allclose(_chain(links, "diana_tool")[1], kin.fk_tool(q), atol=1e-12)
    assert "diana_tool" not in [c for _, c, _ in kin.link_transforms(np.zeros(7))]


class TfListener(_OmcListener):
    def __init__(self, ctx):  # noqa: D107 - other topics than the OMC listener
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_common.tf import dynamic_qos
        from tf2_msgs.msg import TFMessage

        self.node = Node("diana_tf_listener", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.tf, self.flange, self.tool, self.diag = [], [], [], []
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(TFMessage, "/tf", self.tf.append, dynamic_qos())
        self.node.create_subscription(PoseStamped, "/diana/flange_pose", self.flange.append, qos)
        self.node.create_subscription(PoseStamped, "/diana/tool_pose", self.tool.append, qos)


def _ns(h) -> int:
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


@pytest.mark.system
def test_diana_state_broadcasts_the_arm_on_tf(procs, rclpy_context, tmp_path):
    from test_diana_api import C_DIR, compile_double

    from fullperc_common.testing import installed_exe, wait_for
    from fullperc_common.tf import transform_to_T
    from fullperc_common.transforms import make_T

    lib = compile_double(C_DIR / "fake_diana_api.c", tmp_path / "libDianaApi.so")
    procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", "-p", "backend:=diana_api",
                 "-p", f"api_library:={lib}", "-p", "robot_ip:=192.168.10.75", "-p", "rate_hz:=50.0",
                 "-p", "publish_tool:=true", "-p", f"tool_offset:=[{', '.join(repr(float(v)) for v in TOOL)}]"])
    lis = TfListener(rclpy_context)
    try:
        wait_for(lambda: (lis.spin(), len(lis.tf) >= 10 and len(lis.flange) >= 10 and len(lis.tool) >= 10)[1],
                 timeout=60, what="/tf and flange poses")
    finally:
        lis.close()
    flange = {_ns(m.header): m.pose for m in lis.flange}
    tool = {_ns(m.header): m.pose for m in lis.tool}
    checked = 0
    for msg in lis.tf:
        stamps = {_ns(t.header) for t in msg.transforms}
        assert len(stamps) == 1          # one joint state -> one message, stamp = the joint state's stamp
        (stamp,) = stamps
        links = [(t.header.frame_id, t.child_frame_id, transform_to_T(t)) for t in msg.transforms]
        assert [c for _, c, _ in links] == [f"diana_link{i}" for i in range(1, 8)] + ["diana_flange", "diana_tool"]
        if stamp not in flange or stamp not in tool:
            continue
        for child, pose in (("diana_flange", flange[stamp]), ("diana_tool", tool[stamp])):
            root, T = _chain(links, child)
            o, p = pose.orientation, pose.position
            assert root == "diana_base"
            np.testing.assert_allclose(T, make_T([p.x, p.y, p.z], [o.x, o.y, o.z, o.w]), atol=1e-9)
        checked += 1
    assert checked >= 5
    # the double's controller sits at q = 0: the flange at (-0.087, 0, 1.3165) m (reference/diana_eval.md)
    np.testing.assert_allclose(_chain(links, "diana_flange")[1][:3, 3], [-0.087, 0.0, 1.3165], atol=1e-9)
