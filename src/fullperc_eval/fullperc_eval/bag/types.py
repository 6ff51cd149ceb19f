"""Message types for bags: names, definitions and hashes from the ament index, the typestore, Python classes.

A bag stores, per topic, the message type's definition text and its RIHS01 hash. Like rosbag2 we take both
from the *installed* interface files ``share/<pkg>/msg/<Name>.msg`` / ``.json`` of the first prefix on
``AMENT_PREFIX_PATH`` that registers the package (what ament_index does). This is deliberately not
:func:`fullperc_common.share.share_path`: the ``.json`` hashes exist only in an install, and a source-tree
``.msg`` would be written with an empty hash. Dataset generators serialize with a rosbags typestore in which our
``fullperc_msgs`` are registered from the same files (:func:`fullperc_typestore`); the recorder, the player and
``echo``/``pub`` need the rosidl-generated Python class of a type (:func:`get_message`).
"""

from __future__ import annotations

import importlib
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

from .errors import BagError

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string", "wstring", "time", "duration"}
# rosbag2's dependency regex (local_message_definition_source.cpp)
_FIELD_TYPE_RE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_TYPE_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:(msg|srv|action)/)?([A-Za-z][A-Za-z0-9_]*)$")


def split_type(msgtype: str) -> tuple[str, str, str]:
    """'pkg/msg/Name' or 'pkg/Name' -> (pkg, 'msg', Name); BagError if malformed."""
    m = _TYPE_RE.match(msgtype or "")
    if not m:
        raise BagError(f"malformed message type {msgtype!r} (expected 'pkg/msg/Name')")
    return m.group(1), m.group(2) or "msg", m.group(3)


def normalize_type(msgtype: str) -> str:
    pkg, kind, name = split_type(msgtype)
    return f"{pkg}/{kind}/{name}"


def ament_prefixes() -> list[Path]:
    """The install prefixes on AMENT_PREFIX_PATH, in order (first wins, as in ament_index)."""
    return [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]


def package_share(pkg: str) -> Path | None:
    """share/<pkg> of the first prefix whose ament index registers <pkg>, else None."""
    for prefix in ament_prefixes():
        if (prefix / "share" / "ament_index" / "resource_index" / "packages" / pkg).exists():
            share = prefix / "share" / pkg
            if share.is_dir():
                return share
    return None


def interface_file(msgtype: str, ext: str = "msg") -> Path | None:
    pkg, kind, name = split_type(msgtype)
    share = package_share(pkg)
    if share is None:
        return None
    path = share / kind / f"{name}.{ext}"
    return path if path.is_file() else None


def _msg_dependencies(pkg: str, text: str) -> list[str]:
    """Sorted, de-duplicated non-primitive field types of one .msg text, as 'pkg/Name'."""
    deps = set()
    for m in _FIELD_TYPE_RE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{pkg}/{t}")
    return sorted(deps)


def rosbag2_msgdef(msgtype: str) -> str | None:
    """The ``ros2msg`` definition text exactly as rosbag2 writes it, or None if no .msg is found.

    Root text first, then each dependency (depth-first, each level sorted, each type once) after a
    line of 80 '=' and 'MSG: pkg/Name' (rosbag2_cpp local_message_definition_source.cpp).
    """
    root = interface_file(msgtype)
    if root is None:
        return None
    seen: set[str] = set()

    def expand(name: str, path: Path) -> str:
        text = path.read_text()
        out = text
        pkg = name.split("/")[0]
        for dep in _msg_dependencies(pkg, text):
            dep_pkg, _, dep_name = split_type(dep)
            dep = f"{dep_pkg}/{dep_name}"
            if dep in seen:
                continue
            seen.add(dep)
            dep_path = interface_file(dep)
            if dep_path is None:
                raise BagError(f"definition of {dep!r} (used by {name!r}) not found on AMENT_PREFIX_PATH")
            out += "\n" + "=" * 80 + "\nMSG: " + dep + "\n" + expand(dep, dep_path)
        return out

    pkg, _, name = split_type(msgtype)
    return expand(f"{pkg}/{name}", root)


def type_hash_from_index(msgtype: str) -> str:
    """RIHS01 hash from the rosidl-generated share/<pkg>/msg/<Name>.json, or '' if not found."""
    path = interface_file(msgtype, "json")
    if path is None:
        return ""
    try:
        data = json.loads(path.read_text())
        want = normalize_type(msgtype)
        for entry in data.get("type_hashes", []):
            if entry.get("type_name") == want:
                return str(entry.get("hash_string", ""))
    except (OSError, ValueError, AttributeError):
        return ""
    return ""


def resolve_definition(msgtype: str, typestore=None) -> tuple[str, str, str]:
    """(encoding, definition text, RIHS01 hash) of a message type for writing it into a bag.

    Prefers the installed .msg/.json files (what rosbag2 records); falls back to the rosbags
    typestore (normalised text, computed hash). BagError names the type when neither knows it.
    """
    msgtype = normalize_type(msgtype)
    text = rosbag2_msgdef(msgtype)
    rihs = type_hash_from_index(msgtype)
    if text is not None and rihs:
        return "ros2msg", text, rihs
    ts = typestore
    if ts is None:
        from rosbags.typesys import Stores, get_typestore

        ts = get_typestore(Stores.ROS2_JAZZY)
    if text is None:
        if msgtype not in ts.types:
            raise BagError(
                f"unknown message type {msgtype!r}: no share/{msgtype.split('/')[0]}/msg/*.msg on "
                "AMENT_PREFIX_PATH and not in the typestore (did you `source scripts/env.sh`?)")
        text = ts.generate_msgdef(msgtype, ros_version=2)[0]
    if not rihs:
        try:
            rihs = ensure_type(ts, msgtype) and ts.hash_rihs01(msgtype)
        except Exception:  # noqa: BLE001 - a missing hash is allowed (rosbag2 writes "")
            rihs = ""
    return "ros2msg", text, rihs or ""


def ensure_type(typestore, msgtype: str) -> bool:
    """Register ``msgtype`` (and its dependencies) in ``typestore`` from the installed .msg files."""
    from rosbags.typesys import get_types_from_msg

    msgtype = normalize_type(msgtype)
    if msgtype in typestore.types:
        return True
    text = rosbag2_msgdef(msgtype)
    if text is None:
        raise BagError(f"unknown message type {msgtype!r}: no .msg definition on AMENT_PREFIX_PATH")
    typs = get_types_from_msg(text, msgtype)
    typestore.register({k: v for k, v in typs.items() if k not in typestore.types})
    return True


def fullperc_typestore(packages: Sequence[str] = ("fullperc_msgs",)):
    """A fresh rosbags Jazzy typestore with every message of ``packages`` registered.

    The .msg files come from the installed share/<pkg>/msg (AMENT_PREFIX_PATH), so the CDR that
    rosbags writes for them is what the rosidl-generated Python code puts on the wire.
    """
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    for pkg in packages:
        for name in _package_messages(pkg):
            ensure_type(ts, f"{pkg}/msg/{name}")
    return ts


def _package_messages(pkg: str) -> tuple[str, ...]:
    share = package_share(pkg)
    if share is None:
        raise BagError(f"package {pkg!r} not found on AMENT_PREFIX_PATH="
                       f"{os.environ.get('AMENT_PREFIX_PATH', '')!r}; `source scripts/env.sh` after `make build`")
    return tuple(sorted(p.stem for p in (share / "msg").glob("*.msg")))


def get_message(msgtype: str):
    """Python class of 'pkg/msg/Name' or 'pkg/Name' (what rosidl_runtime_py.get_message does; not on PyPI).

    BagError naming the type when the name is malformed or the class cannot be imported.
    """
    try:
        pkg, kind, name = split_type(msgtype)
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (BagError, ImportError, AttributeError) as err:
        raise BagError(f"unknown message type {msgtype!r}: cannot import its Python class "
                       f"({type(err).__name__}: {err})") from None
