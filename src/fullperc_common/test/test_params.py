"""params.declare: a value of the wrong type is a ParameterError naming the parameter, the types and a fix;
``read_only`` (and declare_fixed) make rclpy refuse a run-time set through the parameter service, with the reason."""

from __future__ import annotations

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from fullperc_common.params import ParameterError, declare, declare_fixed


def _node(ctx, **overrides) -> Node:
    return Node("params_test", context=ctx,
                parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])


@pytest.mark.parametrize("given, default, words", [
    (0, 0.004, ["'slop'", "expects a float", "integer 0", "write 0.0"]),
    ("abc", 0.004, ["'slop'", "expects a float", "string 'abc'"]),
    (2.5, 30, ["'slop'", "expects an integer", "float 2.5"]),
    ([1, 2], [0.0, 0.0], ["'slop'", "list of floats", "list of integers [1, 2]", "write [1.0, 2.0]"]),
    ("yes please", True, ["'slop'", "boolean", "string 'yes please'"]),
    (3, "name", ["'slop'", "expects a string", "integer 3"]),
])
def test_wrong_type_names_parameter_types_and_fix(rclpy_context, given, default, words):
    node = _node(rclpy_context, slop=given)
    try:
        with pytest.raises(ParameterError) as ei:
            declare(node, "slop", default)
        msg = str(ei.value)
        assert "\n" not in msg and all(w in msg for w in words), msg
    finally:
        node.destroy_node()


def test_one_wrong_type_is_named_the_other_parameters_declare(rclpy_context):
    node = _node(rclpy_context, slop=0, gain=0.5, depth=-1)
    try:
        with pytest.raises(ParameterError, match="'slop'"):
            declare(node, "slop", 0.004)
        assert declare(node, "gain", 1.5, lambda v: v >= 0, "must be >= 0") == 0.5
        assert declare(node, "other", 1.5) == 1.5  # default when not overridden
        with pytest.raises(ParameterError, match="'depth'.*must be > 0"):
            declare(node, "depth", 10, lambda v: v > 0, "must be > 0")
    finally:
        node.destroy_node()


def test_read_only_is_refused_through_the_parameter_service_with_the_reason(rclpy_context):
    from rcl_interfaces.srv import SetParameters
    from rclpy.executors import SingleThreadedExecutor

    from fullperc_common.testing import wait_for

    node = _node(rclpy_context, fixed=3)
    caller = Node("params_test_caller", context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    try:
        assert declare(node, "fixed", 1, read_only=True) == 3          # a start-up value still applies
        declare(node, "free", 1.0)
        declare_fixed(node, "also_fixed", "a", lambda v: bool(v), "non-empty")
        assert [node.describe_parameter(n).read_only for n in ("fixed", "free", "also_fixed")] == [True, False, True]
        ex.add_node(node)
        ex.add_node(caller)
        cli = caller.create_client(SetParameters, "/params_test/set_parameters")
        wait_for(lambda: (ex.spin_once(timeout_sec=0.05), cli.service_is_ready())[1], what="the parameter service")
        sets = [Parameter("fixed", value=5), Parameter("free", value=2.0), Parameter("also_fixed", value="b")]
        fut = cli.call_async(SetParameters.Request(parameters=[p.to_parameter_msg() for p in sets]))
        wait_for(lambda: (ex.spin_once(timeout_sec=0.05), fut.done())[1], what="the set_parameters answer")
        res = fut.result().results
        assert [r.successful for r in res] == [False, True, False]
        assert "read-only" in res[0].reason and "fixed" in res[0].reason, res[0].reason
        assert "read-only" in res[2].reason and "also_fixed" in res[2].reason, res[2].reason
        assert (node.get_parameter("fixed").value, node.get_parameter("free").value,
                node.get_parameter("also_fixed").value) == (3, 2.0, "a")
    finally:
        ex.shutdown()
        caller.destroy_node()
        node.destroy_node()
