"""params.declare: a value of the wrong type is a ParameterError naming the parameter, the types and a fix."""

from __future__ import annotations

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from fullperc_common.params import ParameterError, declare


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
