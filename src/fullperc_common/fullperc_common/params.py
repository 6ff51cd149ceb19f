"""Parameter declaration with validation that fails at start-up with the parameter's name.

Types are strict (a float parameter given ``0`` is an error, not silently ``0.0``: rclpy's typed parameters
would otherwise flip to an integer on the next ``ros2 param set``), but the error says what to write instead.
rclpy's own parameter exceptions (wrong type from ``-p`` or a ``--params-file``) are turned into
:class:`ParameterError` with one line that names the parameter, here for :func:`declare` and in
:func:`~fullperc_common.node_main.run_node` for nodes that call ``declare_parameter`` directly.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any


class ParameterError(ValueError):
    """A node parameter has a wrong value; the message names the parameter."""


# rclpy.exceptions.InvalidParameterTypeException (Jazzy): the exception keeps no fields, only this message.
_TYPE_MISMATCH = re.compile(r"Trying to set parameter '(?P<name>.+?)' to '(?P<value>.*)' of type '(?P<got>\w+)', "
                            r"expecting type '(?:Type\.)?(?P<want>\w+)'", re.S)

_EXPECTS = {"BOOL": "a boolean (true or false)", "INTEGER": "an integer", "DOUBLE": "a float", "STRING": "a string",
            "BYTE_ARRAY": "a list of bytes", "BOOL_ARRAY": "a list of booleans", "INTEGER_ARRAY": "a list of integers",
            "DOUBLE_ARRAY": "a list of floats", "STRING_ARRAY": "a list of strings", "NOT_SET": "no value"}
_GOT = {"BOOL": "boolean", "INTEGER": "integer", "DOUBLE": "float", "STRING": "string", "BYTE_ARRAY": "list of bytes",
        "BOOL_ARRAY": "list of booleans", "INTEGER_ARRAY": "list of integers", "DOUBLE_ARRAY": "list of floats",
        "STRING_ARRAY": "list of strings", "NOT_SET": "no value"}


def type_mismatch_message(name: str, value: str, got: str, want: str) -> str:
    """One line for a value of rclpy type ``got`` (e.g. ``INTEGER``) given to parameter ``name`` of type ``want``.

    ``value`` is the value as text (as rclpy's exception prints it). The hint says how to write it correctly
    where that is unambiguous (an integer for a float: add ``.0``).
    """
    shown = f"'{value}'" if got == "STRING" else value
    msg = f"parameter '{name}' expects {_EXPECTS.get(want, want)}, got {_GOT.get(got, got)} {shown}"
    hint = ""
    if want == "DOUBLE" and got == "INTEGER":
        hint = f"write {value}.0"
    elif want == "DOUBLE_ARRAY" and got == "INTEGER_ARRAY":
        items = [s.strip() for s in value.strip("[]").split(",") if s.strip()]
        hint = "write [" + ", ".join(f"{s}.0" for s in items) + "]"
    elif want == "BOOL" and got == "STRING":
        hint = "write true or false"
    elif want == "STRING" and got in ("INTEGER", "DOUBLE", "BOOL"):
        hint = f"a string needs YAML quotes: '{value}'"
    elif want.endswith("_ARRAY") and not got.endswith("_ARRAY"):
        hint = "write a list: [a, b, ...]"
    return f"{msg} ({hint})" if hint else msg


def parameter_exception_message(e: BaseException, name: str | None = None) -> str:
    """One line naming the parameter for one of rclpy's ParameterException subclasses (or its message)."""
    text = " ".join(str(e).split())
    m = _TYPE_MISMATCH.search(str(e))
    if m:
        return type_mismatch_message(m["name"], " ".join(m["value"].split()), m["got"], m["want"])
    if name and f"'{name}'" not in text and not text.endswith(f": {name}"):
        return f"parameter '{name}': {text}"
    return text


def declare(node, name: str, default: Any, check: Callable[[Any], bool] | None = None,
            why: str = "", description: str = "", read_only: bool = False) -> Any:
    """Declare ``name`` with ``default`` and return its value; raise ParameterError if ``check`` fails.

    A value of the wrong type (from ``-p`` or a parameter file) raises ParameterError too, naming the parameter,
    the expected and the given type (rclpy raises its InvalidParameterTypeException).

    ``read_only``: the node reads the value once, at start. rclpy then refuses a run-time set (``ros2 param set``,
    the ``set_parameters`` service) with ``successful: false`` and the reason "Trying to set a read-only
    parameter: <name>." before any callback of the node runs -- instead of reporting success and changing
    nothing. A parameter the node does apply at run time stays writable and needs the node's own
    ``add_on_set_parameters_callback`` to validate and apply it.
    """
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import ParameterException

    try:
        desc = ParameterDescriptor(description=description, read_only=read_only)
        value = node.declare_parameter(name, default, desc).value
    except ParameterException as e:
        raise ParameterError(parameter_exception_message(e, name)) from e
    if check is not None and not check(value):
        raise ParameterError(f"parameter '{name}' = {value!r} is invalid: {why}")
    return value


def declare_fixed(node, name: str, default: Any, check: Callable[[Any], bool] | None = None,
                  why: str = "", description: str = "") -> Any:
    """:func:`declare` with ``read_only=True``: a parameter the node reads at start only."""
    return declare(node, name, default, check, why, description, read_only=True)
