"""The echo floor (issue 38): a bare rclpy node with fusion_node's I/O and none of its work -- the CPU floor of any
Python ROS node that takes these inputs and publishes these outputs.

It subscribes what fusion_node subscribes for its targets (``omc/<target|base|ots_rig>/pose``,
``ots/<target|base>/pose``), with the same QoS (reliable, keep last 2000: fusion_node's ``qos_depth``), and for every
sample of a target (OMC or OTS) publishes the four messages a fused output of the primary filter has when all are
read: ``fullperc/<target>/pose``, ``pose_cov``, ``status`` (FusionStatus) and one TFMessage on ``/tf`` -- built
the way a first ROS node is written (new message objects, rclpy's default executor), every one published whether or
not anyone reads it, no maths. ``bench/bench_node_cost.py`` runs it beside fusion_node against the same publisher.

``--outputs`` splits that floor (``bench_node_cost.py``'s ``echo_floor_cpu[pose,outputs=pose|none]``): ``pose``
publishes the fused pose only (what fusion_node sends to a consumer of the pose alone, without its maths), ``none``
nothing (the input path alone: takes and deserialisation); the publishers exist either way.

Run: python bench/echo_floor.py --targets tool [--outputs every|pose|none] [--ros-args ...]   (stops on SIGINT)
"""

from __future__ import annotations

import argparse
import sys

import rclpy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common.tf import dynamic_qos
from fullperc_msgs.msg import FusionStatus
from tf2_msgs.msg import TFMessage

DEPTH = 2000   # fusion_node's qos_depth default


class EchoFloor(Node):
    def __init__(self, targets: list[str], outputs: str = "every") -> None:
        super().__init__("echo_floor")
        self.outputs = outputs
        qos = QoSProfile(depth=DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        self.out = {t: (self.create_publisher(PoseStamped, f"fullperc/{t}/pose", qos),
                        self.create_publisher(PoseWithCovarianceStamped, f"fullperc/{t}/pose_cov", qos),
                        self.create_publisher(FusionStatus, f"fullperc/{t}/status", qos)) for t in targets}
        self.tf = self.create_publisher(TFMessage, "/tf", dynamic_qos())
        for body in ("base", "ots_rig"):   # the static links' inputs: taken, nothing published
            self.create_subscription(PoseStamped, f"omc/{body}/pose", lambda m: None, qos)
        self.create_subscription(PoseStamped, "ots/base/pose", lambda m: None, qos)
        for t in targets:
            for src in ("omc", "ots"):
                self.create_subscription(PoseStamped, f"{src}/{t}/pose", lambda m, t=t: self.echo(t, m), qos)

    def echo(self, target: str, m: PoseStamped) -> None:
        if self.outputs == "none":
            return
        pose_pub, cov_pub, st_pub = self.out[target]
        ps = PoseStamped()
        ps.header.stamp, ps.header.frame_id, ps.pose = m.header.stamp, "base", m.pose
        if self.outputs == "pose":
            pose_pub.publish(ps)
            return
        pc = PoseWithCovarianceStamped()
        pc.header, pc.pose.pose = ps.header, m.pose
        tr = TransformStamped()
        tr.header, tr.child_frame_id = ps.header, target
        p, q = m.pose.position, m.pose.orientation
        tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z = p.x, p.y, p.z
        tr.transform.rotation = q
        st = FusionStatus()
        st.header, st.target, st.filter = ps.header, target, "echo"
        pose_pub.publish(ps)
        cov_pub.publish(pc)
        self.tf.publish(TFMessage(transforms=[tr]))
        st_pub.publish(st)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", default="tool", help="comma-separated target names (default: tool)")
    ap.add_argument("--outputs", choices=("every", "pose", "none"), default="every",
                    help="what is published per target sample (default: every -- the echo floor)")
    a = ap.parse_args(argv[:cut])
    rclpy.init(args=["echo_floor", *argv[cut:]])
    node = EchoFloor([t for t in a.targets.split(",") if t], a.outputs)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
