"""A node parameter as one table row (:class:`Param`), its validity rule (:class:`Rule`) and :func:`convert`.

Why a row: a parameter's name, default, kind, rule, unit, description and the dataclass field it sets are said once,
and everything else derives from the rows -- the declaration (``fusion_node``, ``calibrate``), ``--help`` and the
documentation, the check, the error, and the mapping into the dataclasses (``fusion_config``). Why a named rule
(:data:`POSITIVE`, :func:`one_of` ...): one check and its explanation are written once, and every row that needs it
names it, so a check and the text that explains it cannot drift apart.

Why in the pipeline layer: the node-wide table (``fusion_config``, above the pipeline) and the source blocks
(:mod:`.sources`, in it) use the same rows, rules and conversion, and a pose parameter is checked by the frame
chain's own :func:`~.frame_chain.pose_to_T`.

Conversion (:func:`convert`): by kind, strict -- an int is accepted for a float, nothing else is converted (``"1"``
is not a number, ``1`` is not a bool); then the rule. A value ``None`` (an empty YAML key, an undeclared optional
ROS parameter) means "not given": the default. A wrong value raises
:class:`~fullperc_common.params.ParameterError` naming the parameter.
"""

from __future__ import annotations

import array
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from fullperc_common.params import ParameterError
from fullperc_fusion.pipeline.frame_chain import BadSample, pose_to_T

KINDS = ("str", "int", "float", "bool", "str_list", "pose7")

Get = Callable[[str, Any], Any]   # get(name, default) -> the raw value (None: not given)


class Rule(NamedTuple):
    """A validity rule: ``check(value)`` on the converted value and ``why``, the error's explanation. A row takes
    it as its ``check, why`` pair: ``Param(name, default, kind, *rule, unit, doc)``."""

    check: Callable[[Any], bool]
    why: str


def _pos(v) -> bool:
    return math.isfinite(v) and v > 0


def _nonneg(v) -> bool:
    return math.isfinite(v) and v >= 0


POSITIVE = Rule(_pos, "must be finite and > 0")
NONNEGATIVE = Rule(_nonneg, "must be finite and >= 0")
NONEMPTY = Rule(bool, "must not be empty")
COUNT = Rule(lambda v: v > 0, "must be > 0")                # a positive integer
UNIT_FRACTION = Rule(lambda v: math.isfinite(v) and 0.0 < v <= 1.0, "must be finite, > 0 and <= 1")


def at_least(n: int) -> Rule:
    """An integer of at least ``n``."""
    return Rule(lambda v: v >= n, f"must be >= {n}")


def finite_at_least(x: float) -> Rule:
    """A finite number of at least ``x``."""
    return Rule(lambda v: math.isfinite(v) and v >= x, f"must be finite and >= {x:g}")


def one_of(choices: tuple, why: str = "") -> Rule:
    """One of ``choices`` (the tuple the code that uses the value defines, so the two cannot disagree)."""
    return Rule(lambda v: v in choices, why or f"one of {choices}")


@dataclass(frozen=True)
class Param:
    """One parameter: ``default`` None = optional without a value (``kind`` still says its type); ``check`` and
    ``why`` its :class:`Rule` (none: any value of the kind); ``field`` the field of the filters' parameter dataclass
    it sets ('' = none; ``fusion_config.filter_params``)."""

    name: str
    default: Any
    kind: str
    check: Callable[[Any], bool] | None = None
    why: str = ""
    unit: str = ""
    doc: str = ""
    field: str = ""

    @property
    def description(self) -> str:
        return f"{self.doc} [{self.unit}]" if self.unit else self.doc


def bad_value(name: str, value: Any, why: str) -> ParameterError:
    """The one error text of a parameter with a wrong value."""
    return ParameterError(f"parameter '{name}' = {value!r} is invalid: {why}")


def convert(p: Param, value: Any) -> Any:
    """``value`` as the Python value of ``p`` (default when None), checked; ParameterError naming ``p``."""
    if value is None:
        value = p.default
        if value is None:
            return [] if p.kind == "str_list" else None
    k = p.kind
    if k == "float":
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise bad_value(p.name, value, "must be a number")
        out: Any = float(value)
    elif k == "int":
        if isinstance(value, float | np.floating) and float(value).is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise bad_value(p.name, value, "must be an integer")
        out = int(value)
    elif k == "bool":
        if not isinstance(value, bool | np.bool_):
            raise bad_value(p.name, value, "must be true or false")
        out = bool(value)
    elif k == "str":
        if not isinstance(value, str):
            raise bad_value(p.name, value, "must be a string")
        out = value
    elif k == "str_list":
        if isinstance(value, str) or not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise bad_value(p.name, value, "must be a list of strings")
        out = list(value)
    elif k == "pose7":
        if isinstance(value, str) or not isinstance(value, list | tuple | np.ndarray | array.array):
            raise bad_value(p.name, value, "must be [x y z qx qy qz qw]")
        if len(value) == 0:
            return None
        if len(value) != 7:
            raise bad_value(p.name, list(value), "must be [x y z qx qy qz qw]")
        try:
            v = [float(x) for x in value]
            pose_to_T((np.asarray(v[:3]), np.asarray(v[3:])))
        except (TypeError, ValueError, BadSample) as e:
            raise bad_value(p.name, list(value), f"must be [x y z qx qy qz qw] with a unit quaternion ({e})") from None
        out = v
    else:  # pragma: no cover - the tables are static
        raise AssertionError(f"unknown kind {k!r} of parameter {p.name}")
    if p.check is not None and not p.check(out):
        raise bad_value(p.name, out, p.why)
    return out
