"""Reading a user's YAML file with an error that names the file: the layout, a calibration, a noise model, a
fusion_node params file read offline.

Why one function: a file a user points a node at (``layout_file``, ``calibration_file``) must fail with one line
that says which file and why (unreadable, not YAML), as the caller's own error type, so the node exits 2 naming it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml


class RosParamsLoader(yaml.SafeLoader):
    """PyYAML's safe loader reading numbers as ROS 2 parameter files are read (rcl_yaml_param_parser).

    PyYAML follows YAML 1.1, where a float needs a dot: ``1e-3`` comes back as the string '1e-3'. rcl reads the same
    plain scalar as the double 0.001, so ``fusion_node`` accepts ``accel: 1e-3`` from a params file while the
    offline evaluator, reading the same file with PyYAML, would refuse it. This loader adds YAML 1.2's float form
    (exponent without a dot) for plain scalars; quoted scalars stay strings, as in rcl."""


RosParamsLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9]+(?:\.[0-9]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))

# libyaml's parser where PyYAML was built with it (the wheels are): the same safe constructor and resolvers, so the
# same Python objects, ~9x faster -- the layout alone took ~15 ms of every offline evaluation with the pure-Python
# one. The key is the loader a caller asks for, the value the one that reads the same way through libyaml.
_FAST: dict[type, type] = {}
if hasattr(yaml, "CSafeLoader"):
    class _RosParamsCLoader(yaml.CSafeLoader):
        """:class:`RosParamsLoader` through libyaml."""

    _RosParamsCLoader.yaml_implicit_resolvers = RosParamsLoader.yaml_implicit_resolvers
    _FAST = {yaml.SafeLoader: yaml.CSafeLoader, RosParamsLoader: _RosParamsCLoader}


def load_yaml_file(path: str | os.PathLike, what: str, error: type[Exception],
                   loader: type[yaml.SafeLoader] = yaml.SafeLoader) -> Any:
    """The parsed content of ``path``; ``error("<what> <path>: cannot read: …" | "…: not valid YAML: …")``.
    ``loader``: a SafeLoader (:class:`RosParamsLoader` for a ROS 2 params file)."""
    p = Path(path)
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:   # not UTF-8 (a binary file given by mistake) is unreadable too
        raise error(f"{what} {p}: cannot read: {e}") from e
    try:
        return yaml.load(text, Loader=_FAST.get(loader, loader))
    except yaml.YAMLError as e:
        raise error(f"{what} {p}: not valid YAML: {e}") from e
