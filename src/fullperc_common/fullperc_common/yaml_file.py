"""Reading a user's YAML file with an error that names the file: the layout, a calibration.

Why one function: a file a user points a node at (``layout_file``, ``calibration_file``) must fail with one line
that says which file and why (unreadable, not YAML), as the caller's own error type, so the node exits 2 naming it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml


def load_yaml_file(path: str | os.PathLike, what: str, error: type[Exception]) -> Any:
    """The parsed content of ``path``; ``error("<what> <path>: cannot read: …" | "…: not valid YAML: …")``."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise error(f"{what} {p}: cannot read: {e}") from e
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise error(f"{what} {p}: not valid YAML: {e}") from e
