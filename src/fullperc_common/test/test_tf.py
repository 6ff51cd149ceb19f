"""fullperc_common.tf: TransformStamped conversion, tf2_ros's QoS, the static union, and tf2_msgs' type hash."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.testing import wait_for
from fullperc_common.tf import (
    Broadcaster,
    StaticBroadcaster,
    dynamic_qos,
    static_listener_qos,
    static_qos,
    transform_stamped,
    transform_to_T,
)
from fullperc_common.transforms import make_T


def test_transform_stamped_round_trip_and_fields():
    T = make_T([0.1, -0.2, 0.3], Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_quat())
    m = transform_stamped(1_700_000_000_123_456_789, "base", "tool", T)
    assert (m.header.frame_id, m.child_frame_id) == ("base", "tool")
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    np.testing.assert_allclose(transform_to_T(m), T, atol=1e-12)
    # the child's pose in the parent: a point at the child's origin is T's translation in the parent
    assert (m.transform.translation.x, m.transform.translation.y, m.transform.translation.z) == (0.1, -0.2, 0.3)
    m2 = transform_stamped(5, "omc", "base", p=[1.0, 2.0, 3.0], q_xyzw=[0.0, 0.0, 0.0, 1.0])
    assert m2.transform.rotation.w == 1.0 and m2.transform.translation.z == 3.0


@pytest.mark.parametrize("kw", [dict(parent="", child="a"), dict(parent="a", child="a"),
                                dict(parent="a", child="b", p=[np.nan, 0, 0], q_xyzw=[0, 0, 0, 1]),
                                dict(parent="a", child="b", p=[0, 0, 0], q_xyzw=[0, 0, 0, 2]),
                                dict(parent="a", child="b", T=np.full((4, 4), np.nan))])
def test_transform_stamped_refuses_bad_input(kw):
    kw.setdefault("p", [0, 0, 0])
    kw.setdefault("q_xyzw", [0, 0, 0, 1])
    with pytest.raises(ValueError):
        transform_stamped(0, **kw)


def test_qos_is_tf2_ros():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    d, s = dynamic_qos(), static_qos()
    assert (d.depth, d.history, d.reliability, d.durability) == (
        100, HistoryPolicy.KEEP_LAST, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)
    assert (s.depth, s.history, s.reliability, s.durability) == (
        1, HistoryPolicy.KEEP_LAST, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
    r = static_listener_qos()   # tf2_ros.StaticListenerQoS: a reader keeps every broadcaster's latched message
    assert (r.depth, r.history, r.reliability, r.durability) == (
        100, HistoryPolicy.KEEP_LAST, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)


def test_static_union_reaches_a_late_subscriber_and_type_hash_matches_rosbags_jazzy(rclpy_context):
    """A subscriber created after three static sends gets one message with the union (newest per child), and
    the type hash our tf2_msgs advertises on the wire is the one rosbags' Jazzy store (= upstream) expects."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rosbags.typesys import Stores, get_typestore

    from tf2_msgs.msg import TFMessage

    node = rclpy.create_node("tf_test", context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                          daemon=True)
    th.start()
    try:
        sb, db = StaticBroadcaster(node), Broadcaster(node)
        sb.send([transform_stamped(1, "omc", "base", p=[1, 0, 0], q_xyzw=[0, 0, 0, 1])])
        sb.send([transform_stamped(2, "base", "ots", p=[0, 1, 0], q_xyzw=[0, 0, 0, 1])])
        sb.send([transform_stamped(3, "omc", "base", p=[2, 0, 0], q_xyzw=[0, 0, 0, 1])])
        got_static, got_tf = [], []
        node.create_subscription(TFMessage, "/tf_static", got_static.append, static_qos())
        node.create_subscription(TFMessage, "/tf", got_tf.append, dynamic_qos())
        wait_for(lambda: got_static, 30, what="the latched /tf_static message")
        wait_for(lambda: node.count_subscribers("/tf") > 0 and db.pub.get_subscription_count() > 0, 30,
                 what="/tf matched")
        db.send([transform_stamped(4, "base", "tool", p=[0, 0, 1], q_xyzw=[0, 0, 0, 1])])
        wait_for(lambda: got_tf, 30, what="/tf message")
        hashes = {str(i.topic_type_hash) for t in ("/tf", "/tf_static") for i in node.get_publishers_info_by_topic(t)}
    finally:
        stop.set()
        th.join(5)
        node.destroy_node()
    assert len(got_static) == 1
    tr = {t.child_frame_id: (t.header.frame_id, t.transform.translation.x, t.transform.translation.y)
          for t in got_static[0].transforms}
    assert tr == {"base": ("omc", 2.0, 0.0), "ots": ("base", 0.0, 1.0)}
    assert [(t.header.frame_id, t.child_frame_id) for t in got_tf[0].transforms] == [("base", "tool")]
    expected = get_typestore(Stores.ROS2_JAZZY).hash_rihs01("tf2_msgs/msg/TFMessage")
    assert hashes == {expected}
    assert expected == "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_broadcaster_collects_and_sends_one_message_per_flush():
    """fusion_node adds each target's transforms and flushes once per wake-up: one TFMessage with all of them, in the
    order added; a flush with nothing collected sends nothing."""
    class Pub:
        def __init__(self) -> None:
            self.sent: list = []

        def publish(self, msg) -> None:
            self.sent.append([t.child_frame_id for t in msg.transforms])

    pub = Pub()
    node = type("N", (), {"create_publisher": lambda self, *a: pub})()
    br = Broadcaster(node)
    a, b, c = (transform_stamped(1, "base", child, T=np.eye(4)) for child in ("tool", "instrument", "reference"))
    br.add([a])
    br.add([b, c])
    assert pub.sent == []
    br.flush()
    br.flush()
    assert pub.sent == [["tool", "instrument", "reference"]]
    br.add([c])
    br.flush()
    assert pub.sent[-1] == ["reference"] and len(pub.sent) == 2


def test_broadcaster_rate_keeps_one_transform_per_period_of_stamps_per_child():
    """tf.rate 50 Hz over 400 Hz outputs of two targets: per child frame, the first transform of each 20 ms of stamps
    (by stamp: the same ones in a replay); a stamp that went back is kept and restarts the count; 0 keeps all."""
    class Pub:
        def __init__(self) -> None:
            self.sent: list = []

        def publish(self, msg) -> None:
            self.sent.append([(t.child_frame_id, t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec)
                              for t in msg.transforms])

    pub = Pub()
    node = type("N", (), {"create_publisher": lambda self, *a: pub})()
    br = Broadcaster(node, rate=50.0)
    t0 = 1_700_000_000_000_000_000
    for k in range(40):                    # 100 ms of outputs at 400 Hz, both targets each time
        ns = t0 + k * 2_500_000
        br.add([transform_stamped(ns, "base", child, T=np.eye(4)) for child in ("tool", "instrument")])
        br.flush()
    kept = [x for msg in pub.sent for x in msg]
    for child in ("tool", "instrument"):
        stamps = [ns - t0 for c, ns in kept if c == child]
        assert stamps == [0, 20_000_000, 40_000_000, 60_000_000, 80_000_000], (child, stamps)
    br.add([transform_stamped(t0 - 5_000_000_000, "base", "tool", T=np.eye(4))])   # time went back 5 s
    br.add([transform_stamped(t0 - 4_999_000_000, "base", "tool", T=np.eye(4))])   # 1 ms later: not kept
    br.flush()
    assert pub.sent[-1] == [("tool", t0 - 5_000_000_000)]
    every = Broadcaster(node, rate=0.0)
    every.add([transform_stamped(t0 + k, "base", "tool", T=np.eye(4)) for k in range(3)])
    every.flush()
    assert len(pub.sent[-1]) == 3
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="tf rate"):
            Broadcaster(node, rate=bad)
