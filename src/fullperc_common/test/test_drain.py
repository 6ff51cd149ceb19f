"""take_queued returns what waits on a subscription, oldest first, without spinning an executor."""

import time

import rclpy
from std_msgs.msg import Int32

from fullperc_common.drain import take_queued


def test_take_queued_in_order(rclpy_context):
    node = rclpy.create_node("drain_test", context=rclpy_context)
    try:
        sub = node.create_subscription(Int32, "/drain_test", lambda _m: None, 50)
        pub = node.create_publisher(Int32, "/drain_test", 50)
        end = time.monotonic() + 20
        while pub.get_subscription_count() == 0 and time.monotonic() < end:
            time.sleep(0.01)
        for i in range(7):
            pub.publish(Int32(data=i))
        got: list[int] = []
        while len(got) < 7 and time.monotonic() < end:   # intra-process delivery is quick but not instant
            got += [m.data for m in take_queued(sub)]
            time.sleep(0.01)
        assert got == list(range(7))
        assert take_queued(sub) == []
    finally:
        node.destroy_node()


def test_unsupported_object_gives_nothing():
    class NoHandle:
        pass

    assert take_queued(NoHandle()) == []
