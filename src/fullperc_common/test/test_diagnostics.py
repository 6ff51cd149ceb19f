"""Diagnostics.set accepts both the message's byte constants and plain ints."""

from diagnostic_msgs.msg import DiagnosticArray

from fullperc_common import diagnostics


class _FakeNode:
    def __init__(self):
        self.published = []

    def get_name(self):
        return "n"

    def create_publisher(self, *_a):
        node = self

        class P:
            def publish(self, msg):
                node.published.append(msg)

        return P()

    def create_timer(self, *_a):
        return None

    def get_clock(self):
        import rclpy.clock

        return rclpy.clock.Clock()


def test_levels_bytes_and_int():
    node = _FakeNode()
    d = diagnostics.Diagnostics(node)
    d.set("a", diagnostics.WARN, "warned", {"count": 3})
    d.set("b", 2, "error")
    d.publish()
    arr: DiagnosticArray = node.published[-1]
    levels = {s.name: s.level for s in arr.status}
    assert levels == {"n: a": bytes([1]), "n: b": bytes([2])}
    assert arr.status[0].values[0].key == "count" and arr.status[0].values[0].value == "3"


def test_as_level_accepts_message_bytes_and_ints():
    from fullperc_common.diagnostics import ERROR, OK, WARN, as_level

    assert [as_level(v) for v in (OK, WARN, ERROR)] == [0, 1, 2]
    assert as_level(2) == 2


def test_set_verdict_publishes_a_level_change_at_once():
    from fullperc_common.health import Verdict

    node = _FakeNode()
    d = diagnostics.Diagnostics(node)
    d.set_verdict("link", Verdict(1, "waiting", {"rate_hz": "0.0"}), {"state": "connecting"})
    assert len(node.published) == 1  # a new status counts as a change
    d.set_verdict("link", Verdict(1, "still waiting", {"rate_hz": "0.0"}))
    assert len(node.published) == 1  # same level: the periodic timer publishes it
    d.set_verdict("link", Verdict(2, "no frames", {"rate_hz": "0.0"}), {"state": "reconnecting"})
    assert len(node.published) == 2
    st = node.published[-1].status[0]
    assert st.level == bytes([2]) and st.message == "no frames"
    assert {kv.key: kv.value for kv in st.values} == {"state": "reconnecting", "rate_hz": "0.0"}


def test_published_counts_the_arrays_sent():
    node = _FakeNode()
    d = diagnostics.Diagnostics(node)
    d.publish()                               # nothing to send yet
    assert d.published == 0 and not node.published
    d.set("a", diagnostics.OK, "ok", publish_on_change=True)
    d.publish()
    assert d.published == len(node.published) == 2
