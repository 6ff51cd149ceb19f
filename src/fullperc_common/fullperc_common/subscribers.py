"""Log when a driver's publishers gain or lose subscribers.

DDS discovery between two processes can take seconds (a missed initial announcement waits for the next
periodic one, 3 s in Fast DDS). Samples published before a recorder or ``fusion_node`` is matched are
simply not delivered to it, and ``fusion_node`` averages its static links over the *first* samples it
receives -- so an operator starting a procedure, or ``supervisor demo`` starting the simulated task,
needs to know that the data path is wired. Only the publisher knows which subscriptions it matched, so
the driver says so: one line per change, ``subscribers on /ots/base/pose: 2``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping


class SubscriberLog:
    """Polls ``get_subscription_count()`` of the publishers ``publishers()`` returns and logs changes."""

    def __init__(self, node, publishers: Callable[[], Mapping[str, object]], period_s: float = 0.2) -> None:
        self._node = node
        self._publishers = publishers
        self.counts: dict[str, int] = {}
        self.timer = node.create_timer(period_s, self.check)

    def check(self) -> dict[str, int]:
        """Log every topic whose matched-subscription count changed since the last check; return the changes."""
        changed: dict[str, int] = {}
        for pub in list(self._publishers().values()):
            topic = pub.topic_name
            n = int(pub.get_subscription_count())
            if self.counts.get(topic) != n:
                if n or topic in self.counts:  # no line for a topic that never had a subscriber
                    self._node.get_logger().info(f"subscribers on {topic}: {n}")
                self.counts[topic] = n
                changed[topic] = n
        return changed
