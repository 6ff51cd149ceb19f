"""SubscriberLog reports each publisher's matched subscriptions as they come and go."""

import rclpy
from geometry_msgs.msg import PoseStamped

from fullperc_common.subscribers import SubscriberLog
from fullperc_common.testing import wait_for


class _Logger:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def info(self, msg: str) -> None:
        self.lines.append(msg)


def _count(watch: SubscriberLog, topic: str) -> int:
    watch.check()
    return watch.counts[topic]


def test_counts_matched_subscriptions(rclpy_context):
    pub_node = rclpy.create_node("subscribers_pub", context=rclpy_context)
    sub_node = rclpy.create_node("subscribers_sub", context=rclpy_context)
    try:
        pubs = {"a": pub_node.create_publisher(PoseStamped, "/sublog/a/pose", 10),
                "b": pub_node.create_publisher(PoseStamped, "/sublog/b/pose", 10)}
        log = _Logger()
        pub_node.get_logger = lambda: log  # capture what the operator would read
        watch = SubscriberLog(pub_node, lambda: pubs, period_s=3600.0)
        assert watch.check() == {"/sublog/a/pose": 0, "/sublog/b/pose": 0}
        assert log.lines == []  # nobody listening yet: nothing worth a line
        subs = [sub_node.create_subscription(PoseStamped, "/sublog/a/pose", lambda m: None, 10) for _ in range(2)]
        wait_for(lambda: _count(watch, "/sublog/a/pose") == 2, 10, what="two matches")
        assert log.lines[-1] == "subscribers on /sublog/a/pose: 2"
        assert watch.counts["/sublog/b/pose"] == 0
        assert watch.check() == {}  # no change, no line
        n = len(log.lines)
        for s in subs:
            sub_node.destroy_subscription(s)
        wait_for(lambda: _count(watch, "/sublog/a/pose") == 0, 10, what="unmatched")
        assert log.lines[-1] == "subscribers on /sublog/a/pose: 0" and len(log.lines) > n
    finally:
        sub_node.destroy_node()
        pub_node.destroy_node()
