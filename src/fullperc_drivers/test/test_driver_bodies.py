"""A pose the driver node itself refuses reaches ``<prefix>/bodies`` as its quality message says: ``visible: false``
and an all-zero pose, beside the other bodies of the frame.

The cores refuse non-finite poses before the nodes see them (``nokov.frames.body_validity``, the NDI driver's
transform check), so no device double gets one as far as ``ros_conv.pose_stamped``'s ValueError: here each node is
built in this process (its device address a free port, as ``test_config_files`` builds it) and handed a frame with
such a pose directly; what it publishes is recorded at ``Publisher.publish``. The messages across processes, frame
by frame, are checked in ``test_omc_driver`` (``/omc/bodies``) and ``test/test_driver_ndi_faults.py``
(``/ots/bodies``).
"""

from __future__ import annotations

import socket

import numpy as np
import pytest

from fullperc_common.ports import free_port

STAMP_NS = 1_764_530_000_123_456_789
GOOD_P, GOOD_Q = np.array([0.1, -0.2, 1.5]), np.array([0.0, 0.0, 0.6, 0.8])
BAD_P, BAD_Q = np.array([np.nan, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, 1.0])




def _omc(node):
    from fullperc_drivers.nokov.frames import BodySample, MocapFrame

    bodies = [BodySample(1, "base", True, GOOD_P, GOOD_Q, 0.0002, 4),
              BodySample(2, "tool", True, BAD_P, BAD_Q, 0.0003, 5)]   # the core would have refused it: not here
    node._publish(MocapFrame(4711, STAMP_NS, STAMP_NS + 3_000_000, 0.003, bodies))


def _ndi(node):
    from fullperc_drivers.ndi.driver import FrameResult, ToolSample

    tools = {"tool": ToolSample("tool", True, BAD_P, BAD_Q, 0.0004, 0x31, 812, 4),
             "base": ToolSample("base", True, GOOD_P, GOOD_Q, 0.0002, 0x31, 812, 4)}
    node._publish(FrameResult(STAMP_NS, STAMP_NS + 2_000_000, 812, 0, tools))


def _node(driver: str):
    """The driver node of this process, its device address a free port (nothing is sent to it or answers there)."""
    if driver == "omc_driver":
        from fullperc_drivers.omc_driver import OmcDriverNode

        return OmcDriverNode, ["-p", f"stream_port:={free_port(socket.SOCK_DGRAM)}", "-p", "bodies:=[base, tool]"]
    from fullperc_drivers.ndi_driver import NdiDriverNode

    return NdiDriverNode, ["-p", f"port:={free_port(socket.SOCK_STREAM)}"]   # tools [tool, base]: the default


# driver -> (hand it a frame, topic prefix); the body "tool" has the pose the node refuses, "base" a good one
CASES = {"omc_driver": (_omc, "/omc"), "ndi_driver": (_ndi, "/ots")}


@pytest.mark.parametrize("driver", sorted(CASES))
def test_a_pose_the_node_refuses_is_sent_not_visible_in_bodies(driver, ros_env, monkeypatch):
    import rclpy
    from geometry_msgs.msg import Pose
    from rclpy.publisher import Publisher

    feed, prefix = CASES[driver]
    refused = "tool"
    cls, args = _node(driver)
    sent: list[tuple[str, object]] = []
    rclpy.init(args=["--ros-args", *args])
    try:
        node = cls()
        try:
            with monkeypatch.context() as m:   # every message the node publishes, by resolved topic, in order
                m.setattr(Publisher, "publish", lambda self, msg: sent.append((self.topic_name, msg)))
                feed(node)
        finally:
            node.close()   # stops the node's device thread
            node.destroy_node()
    finally:
        rclpy.shutdown()
    by_topic: dict[str, list] = {}
    for topic, msg in sent:
        by_topic.setdefault(topic, []).append(msg)
    (frame,) = by_topic[f"{prefix}/bodies"]                    # one per frame
    (base_pose,) = by_topic[f"{prefix}/base/pose"]
    (q_refused,) = by_topic[f"{prefix}/{refused}/quality"]
    (q_base,) = by_topic[f"{prefix}/base/quality"]
    assert f"{prefix}/{refused}/pose" not in by_topic
    assert [t for t, _ in sent][-1] == f"{prefix}/bodies"       # after the frame's per-body messages
    assert frame.header == base_pose.header == q_base.header == q_refused.header
    assert frame.header.stamp.sec * 10**9 + frame.header.stamp.nanosec == STAMP_NS
    order = [q.body for t, q in sent if t.endswith("/quality")]
    assert [b.name for b in frame.bodies] == order and frame.latency == q_base.latency
    for b in frame.bodies:
        q = q_refused if b.name == refused else q_base
        assert (b.visible, b.fit_error, b.frame_number, b.markers_used, b.port_status) == \
            (q.visible, q.fit_error, q.frame_number, q.markers_used, q.port_status)
    bad = next(b for b in frame.bodies if b.name == refused)
    good = next(b for b in frame.bodies if b.name == "base")
    assert not bad.visible and not q_refused.visible and bad.pose == Pose()
    assert good.visible and good.pose == base_pose.pose
