"""Parameter declaration with validation that fails at start-up with the parameter's name."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class ParameterError(ValueError):
    """A node parameter has a wrong value; the message names the parameter."""


def declare(node, name: str, default: Any, check: Callable[[Any], bool] | None = None,
            why: str = "", description: str = "") -> Any:
    """Declare ``name`` with ``default`` and return its value; raise ParameterError if ``check`` fails."""
    from rcl_interfaces.msg import ParameterDescriptor

    value = node.declare_parameter(name, default, ParameterDescriptor(description=description)).value
    if check is not None and not check(value):
        raise ParameterError(f"parameter '{name}' = {value!r} is invalid: {why}")
    return value
