"""An overloaded fusion_node keeps reporting on /diagnostics although its executor runs no timer.

Seen in a demo run on a 2-core machine: the node, on rclpy's EventsExecutor, was busy in input callbacks back to
back for the whole task and ran neither the diagnostics' evaluation timer nor their publishing timer -- no
/diagnostics for 22 s, so its overload and lost-sample WARNs came out only after the task. Here the node is built
in this process and never spun: no timer runs at all, only the input callback, as in that run.
"""

from __future__ import annotations

import time

import pytest
from rclpy.serialization import serialize_message

from fullperc_common.ros_conv import pose_stamped


def _omc_pose(t_ns: int):
    return pose_stamped(t_ns, "omc", (0.1, 0.2, 1.0), (0.0, 0.0, 0.0, 1.0))


@pytest.fixture
def node(rclpy_context):
    from fullperc_fusion.fusion_node import FusionNode

    n = FusionNode(context=rclpy_context)
    yield n
    n.destroy_node()


def _feed(node, seconds: float) -> None:
    """Input callbacks back to back for ``seconds`` (wall), never returning to an executor."""
    end = time.monotonic() + seconds
    t_ns = time.time_ns()
    while time.monotonic() < end:
        t_ns += 8_333_333
        node._on_input("omc", "tool", serialize_message(_omc_pose(t_ns)), {})   # raw subscriptions: bytes
        time.sleep(0.005)


def test_diagnostics_are_evaluated_and_published_from_the_input_path_when_no_timer_runs(node):
    assert node._diag.published == 0            # built, never spun: nothing sent yet
    before = node._diag._status["target tool"].message
    assert "no OMC (global) sample received yet" in before
    _feed(node, 2.5)
    # two periods without a publish (2 s) -> published from the input path; the values are this input's
    assert node._diag.published >= 1
    after = node._diag._status["target tool"].message
    assert "no OMC (global) sample received yet" not in after, after


def test_on_time_timers_leave_the_input_path_nothing_to_do(node):
    """The input path steps in only for a timer a whole period late: right after an evaluation and a publish it
    does neither (the timers stay the normal path; no double reports)."""
    node._update_diagnostics()
    node._diag.publish()
    sent, evaluated = node._diag.published, node.core.diag_eval_at
    node._on_input("omc", "tool", serialize_message(_omc_pose(time.time_ns())), {})
    assert node._diag.published == sent and node.core.diag_eval_at == evaluated
