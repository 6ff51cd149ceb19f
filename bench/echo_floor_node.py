"""The echo floor of bench_node_cost: a bare rclpy node doing fusion_node's I/O and no maths.

It subscribes the five pose topics fusion_node subscribes for one target (``/omc/{<tool>,base,ots_rig}/pose``,
``/ots/{<tool>,base}/pose``) with the same QoS (reliable, keep last 2000), and for every sample of the target's own
body (OMC or OTS) publishes the four messages fusion_node publishes per fused output -- PoseStamped,
PoseWithCovarianceStamped, one TFMessage, FusionStatus -- on ``/echo/<tool>/{pose,pose_cov,status}`` and
``/echo/tf``, built new per sample and published whether or not anyone listens, as any Python ROS node would. Spun
by rclpy's default executor (``rclpy.spin``). What it costs is the floor of a Python node with this I/O: the
figure fusion_node's own CPU is compared with.

Run: python bench/echo_floor_node.py [--tool tool] [--rig ots_rig]   (stops on SIGINT/SIGTERM)
"""

from __future__ import annotations

import argparse
import signal

import rclpy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_msgs.msg import FusionStatus
from tf2_msgs.msg import TFMessage


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tool", default="tool")
    ap.add_argument("--rig", default="ots_rig")
    a = ap.parse_args()
    rclpy.init()
    node = rclpy.create_node("echo_floor")
    qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
    pose_pub = node.create_publisher(PoseStamped, f"/echo/{a.tool}/pose", qos)
    cov_pub = node.create_publisher(PoseWithCovarianceStamped, f"/echo/{a.tool}/pose_cov", qos)
    st_pub = node.create_publisher(FusionStatus, f"/echo/{a.tool}/status", qos)
    tf_pub = node.create_publisher(TFMessage, "/echo/tf", QoSProfile(depth=100,
                                                                      reliability=ReliabilityPolicy.RELIABLE))

    def echo(m: PoseStamped) -> None:
        ps = PoseStamped()
        ps.header.stamp, ps.header.frame_id, ps.pose = m.header.stamp, "base", m.pose
        pose_pub.publish(ps)
        pc = PoseWithCovarianceStamped()
        pc.header = ps.header
        pc.pose.pose = m.pose
        cov_pub.publish(pc)
        t = TransformStamped()
        t.header, t.child_frame_id = ps.header, a.tool
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (
            m.pose.position.x, m.pose.position.y, m.pose.position.z)
        t.transform.rotation = m.pose.orientation
        tf_pub.publish(TFMessage(transforms=[t]))
        st = FusionStatus()
        st.header, st.target, st.filter = ps.header, a.tool, "echo"
        st_pub.publish(st)

    for dev, body in (("omc", a.tool), ("omc", "base"), ("omc", a.rig), ("ots", a.tool), ("ots", "base")):
        node.create_subscription(PoseStamped, f"/{dev}/{body}/pose",
                                 echo if body == a.tool else (lambda m: None), qos)
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
