"""fusion_node's shutdown fuses what its input queues still hold (``FusionNode.close``, called by run_node).

A node behind its inputs at SIGINT -- the demo's seven processes on a busy 2-core machine, seconds of samples in
the queues (``qos_depth``) -- used to exit with that tail unfused: the recording then held samples the live node
never fused, and the live-against-offline comparison of the demo could not be made. Here the node is built in this
process and never spun: every sample is still in its subscriptions' queues when close() runs.
"""

from __future__ import annotations

import pytest

from fullperc_common.ros_conv import ns_to_stamp, pose_stamped

N = 200


@pytest.fixture
def node_and_feeder(rclpy_context):
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_fusion.fusion_node import FusionNode
    from fullperc_msgs.msg import TrackingQuality

    node = FusionNode(context=rclpy_context)
    feeder = rclpy.create_node("feeder", context=rclpy_context)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    pubs = (feeder.create_publisher(PoseStamped, "/omc/tool/pose", qos),
            feeder.create_publisher(TrackingQuality, "/omc/tool/quality", qos))
    yield node, pubs
    feeder.destroy_node()
    node.destroy_node()


def _send(pubs, n: int) -> None:
    from rclpy.duration import Duration

    from fullperc_common.testing import wait_for
    from fullperc_msgs.msg import TrackingQuality

    pose_pub, quality_pub = pubs
    wait_for(lambda: pose_pub.get_subscription_count() >= 1 and quality_pub.get_subscription_count() >= 1, 60,
             what="fusion_node's subscriptions")
    t0 = 1_700_000_000_000_000_000
    for k in range(n):
        t = t0 + k * 8_333_333
        q = TrackingQuality()
        q.header.stamp, q.header.frame_id = ns_to_stamp(t), "omc"
        q.visible, q.frame_number = True, k + 1
        quality_pub.publish(q)
        pose_pub.publish(pose_stamped(t, "omc", (0.1, 0.2, 1.0), (0.0, 0.0, 0.0, 1.0)))
    for p in pubs:   # reliable: acknowledged = in the node's reader history
        assert p.wait_for_all_acked(Duration(seconds=60))


def test_close_fuses_every_sample_still_queued_and_counts_none_lost(node_and_feeder):
    node, pubs = node_and_feeder
    _send(pubs, N)
    pipe = node.core.pipes["tool"]
    assert pipe.counts["global_in"] == 0, "never spun: nothing taken yet"
    node.close()
    assert pipe.counts["global_in"] == N
    loss = node.core.book.loss[("omc", "tool")]
    assert (loss.samples_lost, loss.frames_lost, loss.pending) == (0, 0, 0)


def test_close_settles_and_publishes_the_final_diagnostics(node_and_feeder):
    """A visible frame whose pose never came is counted at shutdown (nothing more comes), and the last /diagnostics
    the node sends says so."""
    node, pubs = node_and_feeder
    from rclpy.duration import Duration

    from fullperc_msgs.msg import TrackingQuality

    _send(pubs, N)
    q = TrackingQuality()   # the quality of a frame after the last pose, visible: its pose never comes
    q.header.stamp, q.header.frame_id = ns_to_stamp(1_700_000_000_000_000_000 + N * 8_333_333), "omc"
    q.visible, q.frame_number = True, N + 1
    pubs[1].publish(q)
    assert pubs[1].wait_for_all_acked(Duration(seconds=60))
    sent = node._diag.published
    node.close()
    assert node._diag.published == sent + 1
    values = {kv.key: kv.value for kv in node._diag._status["target tool"].values}
    assert node.core.book.loss[("omc", "tool")].samples_lost == 1
    assert values["omc_samples_lost"] == "1", values


def test_a_callback_takes_every_queued_sample_of_every_input(rclpy_context):
    """A node seconds behind has more queued on a fast topic than on a slow one. Taking at most 1000 per
    subscription, one callback took 8 s of the 120 Hz OMC topic but all 12 s of the 60 Hz Vega's; the next
    callback's OMC samples were then older than the history and dropped as late (a CI demo lost 249 samples of
    a target this way). One callback takes everything queued: nothing is late."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.duration import Duration
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.testing import wait_for
    from fullperc_fusion.fusion_node import FusionNode

    node = FusionNode(context=rclpy_context, parameter_overrides=[Parameter("qos_depth", value=3000)])
    feeder = rclpy.create_node("feeder", context=rclpy_context)
    try:
        qos = QoSProfile(depth=3000, reliability=ReliabilityPolicy.RELIABLE)
        omc = feeder.create_publisher(PoseStamped, "/omc/tool/pose", qos)
        ots = feeder.create_publisher(PoseStamped, "/ots/tool/pose", qos)
        wait_for(lambda: omc.get_subscription_count() >= 1 and ots.get_subscription_count() >= 1, 60,
                 what="fusion_node's subscriptions")
        t0, n_omc, n_ots = 1_700_000_000_000_000_000, 1500, 750   # 12.5 s at 120 Hz and at 60 Hz
        for k in range(n_omc):
            omc.publish(pose_stamped(t0 + k * 8_333_333, "omc", (0.1, 0.2, 1.0), (0.0, 0.0, 0.0, 1.0)))
        for k in range(n_ots):
            ots.publish(pose_stamped(t0 + k * 16_666_667, "ots", (0.1, 0.2, -1.0), (0.0, 0.0, 0.0, 1.0)))
        for p in (omc, ots):
            assert p.wait_for_all_acked(Duration(seconds=60))
        node.close()   # its first callback: one sample, then everything queued behind it
        counts = node.core.pipes["tool"].counts
        assert (counts["global_in"], counts["local_in"]) == (n_omc, n_ots), dict(counts)
        assert counts["late"] == 0, dict(counts)
    finally:
        feeder.destroy_node()
        node.destroy_node()
