"""margin_node's shutdown labels what its pose queues still hold (``MarginNode.close``, called by run_node).

The demo stops fusion_node before margin_node; fusion_node publishes its queued backlog as it exits, and on a busy
machine those are the task's last seconds: a margin_node that exited with them unread never labelled the last
region (CI recorded B-G for B-G-P). Here the node is built in this process and never spun: every pose is still in
its subscription's queue when close() runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_fusion.margin.view_margin import UNKNOWN

sys.path.insert(0, str(Path(__file__).parent))
from test_margin_node import write_layout  # noqa: E402  (the hand-computable layout)

N = 50


def test_close_labels_every_pose_still_queued(rclpy_context, tmp_path):
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.duration import Duration
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.testing import wait_for
    from fullperc_fusion.margin_node import MarginNode
    from fullperc_msgs.msg import Region

    node = MarginNode(context=rclpy_context, parameter_overrides=[
        Parameter("layout_file", value=str(write_layout(tmp_path / "layout.yaml"))),
        Parameter("targets", value=["probe"]), Parameter("publish_map", value=False)])
    feeder = rclpy.create_node("feeder", context=rclpy_context)
    try:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        pub = feeder.create_publisher(PoseStamped, "/fullperc/probe/pose", qos)
        got: list[Region] = []
        feeder.create_subscription(Region, "/fullperc/probe/region", got.append, qos)
        wait_for(lambda: pub.get_subscription_count() >= 1 and node.region_pubs["probe"].get_subscription_count()
                 >= 1, 60, what="margin_node's subscription and the feeder's")
        t0 = 1_700_000_000_000_000_000
        for k in range(N):   # poses in the layout frame: labelled without a base pose
            pub.publish(pose_stamped(t0 + k * 10_000_000, "omc", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0)))
        assert pub.wait_for_all_acked(Duration(seconds=60))   # reliable: acknowledged = in margin_node's queue
        assert node.counts["probe"] == 0, "never spun: nothing taken yet"
        node.close()
        assert node.counts["probe"] == N
        executor = rclpy.executors.SingleThreadedExecutor(context=rclpy_context)
        executor.add_node(feeder)
        wait_for(lambda: (executor.spin_once(timeout_sec=0.05), len(got) >= N)[1], 60, what=f"{N} region labels")
        assert [m.header.stamp for m in got] == [ns_to_stamp(t0 + k * 10_000_000) for k in range(N)]
        assert all(m.label != UNKNOWN for m in got)
    finally:
        feeder.destroy_node()
        node.destroy_node()
