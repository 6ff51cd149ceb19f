"""ROS-free rosbag2 (Jazzy, metadata version 9) bag writing, reading and recovery.

Why our own writer instead of ``rosbags.rosbag2.Writer``: rosbags keeps a whole MCAP chunk (or the
whole sqlite transaction) in memory until ``close()``, so a killed recorder loses everything. This
writer finishes a chunk / commits at a bounded interval (``flush_interval``) and rewrites
metadata.yaml each time, so a SIGKILLed recorder loses at most that interval; :func:`reindex`
then turns the summary-less MCAP into a complete, indexed one (like ``ros2 bag reindex`` plus
``mcap recover``). It also writes what rosbag2 writes and rosbags omits: the ``<bag>_<N>.mcap``
file names, the channel ``topic_type_hash`` and rosbag2's own message-definition text.

Everything here runs without rclpy: the recorder node (``bag_record``) hands in raw CDR bytes;
dataset generators hand in rosbags typestore messages (:meth:`BagWriter.write_msg`), with our
``fullperc_msgs`` types registered from the installed ``share/fullperc_msgs/msg/*.msg``
(found through ``AMENT_PREFIX_PATH`` like ament_index does).

Conventions are those of ``/work/shared/reference/bags_ros2.md`` §1 (metadata.yaml v9 key order,
MCAP ``ros2`` profile, sqlite3 schema version 4).

Command line: ``python -m fullperc_eval.bag_io info|reindex BAG``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sqlite3
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

METADATA_VERSION = 9
METADATA_FILE = "metadata.yaml"
STORAGES = ("mcap", "sqlite3")
STORAGE_EXT = {"mcap": ".mcap", "sqlite3": ".db3"}
MCAP_MAGIC = b"\x89MCAP0\r\n"
INFINITE_SEC, INFINITE_NSEC = 9223372036, 854775807  # rmw "infinite" duration as rosbag2 writes it
DEFAULT_CHUNK_SIZE = 768 * 1024  # libmcap's default, what rosbag2 uses
DEFAULT_FLUSH_INTERVAL = 0.5  # s; bounds what a killed recorder loses
SQLITE_SCHEMA_VERSION = 4

# rmw enum values (v8 metadata) <-> names (v9 metadata), checked against rclpy in the reference notes.
_QOS_ENUMS: dict[str, tuple[str, ...]] = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": ("system_default", "automatic", "manual_by_node", "manual_by_topic", "unknown",
                   "best_available"),
}
_QOS_DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string", "wstring", "time", "duration"}
# rosbag2's dependency regex (local_message_definition_source.cpp)
_FIELD_TYPE_RE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_TYPE_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:(msg|srv|action)/)?([A-Za-z][A-Za-z0-9_]*)$")


class BagError(Exception):
    """A bag cannot be written, read or recovered; the message says why and what to do."""


# --------------------------------------------------------------------------------------------
# Interface definitions from the ament index (share/<pkg>/msg/*.msg, *.json)
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# QoS profiles as rosbag2 v9 stores them (list of maps with policy names)
# --------------------------------------------------------------------------------------------

def _duration(ns: int | None) -> dict[str, int]:
    if ns is None or ns < 0 or ns >= INFINITE_SEC * 10**9 + INFINITE_NSEC:
        return {"sec": INFINITE_SEC, "nsec": INFINITE_NSEC}
    return {"sec": int(ns) // 10**9, "nsec": int(ns) % 10**9}


def make_qos(history: str | int = "keep_last", depth: int = 10, reliability: str | int = "reliable",
             durability: str | int = "volatile", deadline_ns: int | None = None, lifespan_ns: int | None = None,
             liveliness: str | int = "automatic", liveliness_lease_ns: int | None = None,
             avoid_ros_namespace_conventions: bool = False) -> dict[str, Any]:
    """One offered QoS profile in metadata v9 form; durations None/negative mean infinite."""
    return {
        "history": _qos_name("history", history),
        "depth": int(depth),
        "reliability": _qos_name("reliability", reliability),
        "durability": _qos_name("durability", durability),
        "deadline": _duration(deadline_ns),
        "lifespan": _duration(lifespan_ns),
        "liveliness": _qos_name("liveliness", liveliness),
        "liveliness_lease_duration": _duration(liveliness_lease_ns),
        "avoid_ros_namespace_conventions": bool(avoid_ros_namespace_conventions),
    }


def _qos_name(policy: str, value: str | int) -> str:
    names = _QOS_ENUMS[policy]
    if isinstance(value, bool):
        raise BagError(f"QoS {policy}: {value!r} is not a policy value")
    if isinstance(value, int):
        return names[value] if 0 <= value < len(names) else "unknown"
    v = str(value).strip().lower()
    if v.isdigit():
        return _qos_name(policy, int(v))
    if v not in names:
        raise BagError(f"QoS {policy}: unknown value {value!r} (one of {', '.join(names)})")
    return v


def _parse_duration(d: dict | None) -> int | None:
    d = d or {}
    ns = int(d.get("sec", INFINITE_SEC)) * 10**9 + int(d.get("nsec", INFINITE_NSEC))
    return None if ns >= INFINITE_SEC * 10**9 + INFINITE_NSEC else ns


def parse_qos(value: Any) -> list[dict[str, Any]]:
    """Offered QoS profiles from metadata (v9 list of maps, or v8 YAML string with ints) -> v9 form."""
    if value is None or value == "":
        return []
    if isinstance(value, str):
        try:
            value = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise BagError(f"offered_qos_profiles is not valid YAML: {err}") from None
        if value is None:
            return []
    if not isinstance(value, list):
        raise BagError(f"offered_qos_profiles must be a list, got {type(value).__name__}")
    out = []
    for prof in value:
        if not isinstance(prof, dict):
            raise BagError(f"offered_qos_profiles entry must be a map, got {prof!r}")
        try:
            deadline, lifespan, lease = (_parse_duration(prof.get(k)) for k in _QOS_DURATIONS)
            depth = int(prof.get("depth", 0))
        except (TypeError, ValueError, AttributeError) as err:
            raise BagError(f"offered_qos_profiles entry {prof!r} is malformed ({err})") from None
        out.append(make_qos(prof.get("history", "unknown"), depth,
                            prof.get("reliability", "unknown"), prof.get("durability", "unknown"),
                            deadline, lifespan, prof.get("liveliness", "unknown"), lease,
                            bool(prof.get("avoid_ros_namespace_conventions", False))))
    return out


def qos_yaml(profiles: Sequence[dict[str, Any]]) -> str:
    """The YAML string rosbag2 puts into MCAP channel metadata / sqlite topics.offered_qos_profiles."""
    return yaml.safe_dump(list(profiles), sort_keys=False, default_flow_style=False) if profiles else ""


# --------------------------------------------------------------------------------------------
# metadata.yaml
# --------------------------------------------------------------------------------------------

@dataclass
class TopicInfo:
    """One recorded topic: what goes into topics_with_message_count (+ the schema for MCAP)."""

    name: str
    msgtype: str
    offered_qos: list[dict[str, Any]] = field(default_factory=list)
    type_hash: str = ""
    serialization_format: str = "cdr"
    msgdef: str = ""
    encoding: str = "ros2msg"
    count: int = 0

    def metadata(self) -> dict[str, Any]:
        return {
            "topic_metadata": {
                "name": self.name,
                "type": self.msgtype,
                "serialization_format": self.serialization_format,
                "offered_qos_profiles": list(self.offered_qos),
                "type_description_hash": self.type_hash,
            },
            "message_count": self.count,
        }


@dataclass
class FileInfo:
    path: str  # relative to the bag directory
    count: int = 0
    start: int | None = None
    end: int | None = None

    def add(self, t: int) -> None:
        self.count += 1
        self.start = t if self.start is None else min(self.start, t)
        self.end = t if self.end is None else max(self.end, t)


def build_metadata(storage: str, topics: Iterable[TopicInfo], files: Sequence[FileInfo], *,
                   compression_format: str = "", compression_mode: str = "",
                   custom_data: dict[str, str] | None = None, ros_distro: str | None = None) -> dict:
    """metadata.yaml content (v9) in rosbag2's key order (rosbag2_storage yaml.hpp)."""
    starts = [f.start for f in files if f.start is not None]
    ends = [f.end for f in files if f.end is not None]
    start = min(starts) if starts else 0
    duration = (max(ends) - start) if ends else 0
    info = {
        "version": METADATA_VERSION,
        "storage_identifier": storage,
        "duration": {"nanoseconds": int(duration)},
        "starting_time": {"nanoseconds_since_epoch": int(start)},
        "message_count": int(sum(f.count for f in files)),
        "topics_with_message_count": [t.metadata() for t in topics],
        "compression_format": compression_format,
        "compression_mode": compression_mode,
        "relative_file_paths": [f.path for f in files],
        "files": [{
            "path": f.path,
            "starting_time": {"nanoseconds_since_epoch": int(f.start or 0)},
            "duration": {"nanoseconds": int((f.end - f.start) if f.count else 0)},
            "message_count": int(f.count),
        } for f in files],
        "custom_data": dict(custom_data) if custom_data else None,
        "ros_distro": ros_distro if ros_distro is not None else (os.environ.get("ROS_DISTRO") or "jazzy"),
    }
    return {"rosbag2_bagfile_information": info}


def write_metadata(bagdir: Path, metadata: dict) -> None:
    """Atomically replace metadata.yaml (a reader never sees a half-written file)."""
    bagdir = Path(bagdir)
    tmp = bagdir / (METADATA_FILE + ".tmp")
    tmp.write_text(yaml.safe_dump(metadata, sort_keys=False, default_flow_style=False))
    os.replace(tmp, bagdir / METADATA_FILE)


def load_metadata(bagdir: Path) -> dict:
    """The rosbag2_bagfile_information map of a bag directory; BagError with a hint if absent/bad."""
    bagdir = Path(bagdir)
    path = bagdir / METADATA_FILE
    if not bagdir.exists():
        raise BagError(f"bag {str(bagdir)!r} does not exist")
    if not bagdir.is_dir():
        raise BagError(f"bag {str(bagdir)!r} is not a directory (give the rosbag2 bag directory)")
    if not path.is_file():
        raise BagError(f"bag {str(bagdir)!r} has no {METADATA_FILE} (recorder killed before its first flush, "
                       f"or not a rosbag2 bag); rebuild it with: python -m fullperc_eval.bag_io reindex {bagdir}")
    try:
        data = yaml.safe_load(path.read_text())
        info = data["rosbag2_bagfile_information"]
        for key in ("version", "storage_identifier", "topics_with_message_count", "relative_file_paths"):
            info[key]  # noqa: B018 - presence check
    except (yaml.YAMLError, TypeError, KeyError, UnicodeDecodeError) as err:
        raise BagError(f"{path} is not a valid rosbag2 metadata file ({type(err).__name__}: {err}); "
                       f"rebuild it with: python -m fullperc_eval.bag_io reindex {bagdir}") from None
    return info


# --------------------------------------------------------------------------------------------
# Storage back ends
# --------------------------------------------------------------------------------------------

class _McapFile:
    """One <bag>_<N>.mcap file written the way rosbag2_storage_mcap does (profile ros2)."""

    def __init__(self, path: Path, chunk_size: int, compression: str) -> None:
        from mcap.writer import CompressionType, Writer

        comp = {"": CompressionType.NONE, "none": CompressionType.NONE, "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4}[compression]
        self.path = path
        self.stream = open(path, "xb")  # noqa: SIM115 - closed in close()
        self.writer = Writer(self.stream, chunk_size=chunk_size, compression=comp)
        self.writer.start(profile="ros2", library=f"fullperc_eval.bag_io (python mcap {_mcap_version()})")
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}

    def add_topic(self, t: TopicInfo) -> None:
        sid = self.schemas.get(t.msgtype)
        if sid is None:
            sid = self.writer.register_schema(t.msgtype, t.encoding, t.msgdef.encode())
            self.schemas[t.msgtype] = sid
        meta = {"offered_qos_profiles": qos_yaml(t.offered_qos), "topic_type_hash": t.type_hash}
        self.channels[t.name] = self.writer.register_channel(t.name, t.serialization_format, sid, meta)

    def write(self, topic: str, t: int, data: bytes, publish_time: int) -> None:
        self.writer.add_message(self.channels[topic], t, data, publish_time, sequence=0)

    def size(self) -> int:
        return self.stream.tell()

    def flush(self, fsync: bool) -> None:
        self.writer.flush()
        if fsync:
            os.fsync(self.stream.fileno())

    def close(self, serialized_metadata: str) -> None:
        self.writer.add_metadata("rosbag2", {"serialized_metadata": serialized_metadata})
        self.writer.finish()
        self.stream.close()


class _SqliteFile:
    """One <bag>_<N>.db3 file with rosbag2's schema version 4; WAL so a kill keeps committed data."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.db = sqlite3.connect(path, isolation_level="DEFERRED", check_same_thread=False)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=NORMAL")
        self.db.executescript("""
            CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
            CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL, metadata TEXT NOT NULL);
            CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
                serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL,
                type_description_hash TEXT NOT NULL);
            CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL,
                encoding TEXT NOT NULL, encoded_message_definition TEXT NOT NULL,
                type_description_hash TEXT NOT NULL);
            CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL,
                timestamp INTEGER NOT NULL, data BLOB NOT NULL);
            CREATE INDEX timestamp_idx ON messages (timestamp ASC);
        """)
        self.db.execute("INSERT INTO schema VALUES (?, ?)",
                        (SQLITE_SCHEMA_VERSION, os.environ.get("ROS_DISTRO") or "jazzy"))
        self.db.commit()
        self.topic_ids: dict[str, int] = {}
        self.defs: set[str] = set()
        self.pending: list[tuple[int, int, bytes]] = []

    def add_topic(self, t: TopicInfo) -> None:
        cur = self.db.execute(
            "INSERT INTO topics(name, type, serialization_format, offered_qos_profiles, type_description_hash)"
            " VALUES (?, ?, ?, ?, ?)", (t.name, t.msgtype, t.serialization_format, qos_yaml(t.offered_qos),
                                        t.type_hash))
        self.topic_ids[t.name] = int(cur.lastrowid)
        if t.msgtype not in self.defs:
            self.db.execute("INSERT INTO message_definitions(topic_type, encoding, encoded_message_definition,"
                            " type_description_hash) VALUES (?, ?, ?, ?)",
                            (t.msgtype, t.encoding, t.msgdef, t.type_hash))
            self.defs.add(t.msgtype)
        self.db.commit()

    def write(self, topic: str, t: int, data: bytes, publish_time: int) -> None:
        self.pending.append((self.topic_ids[topic], t, bytes(data)))

    def size(self) -> int:
        return self.path.stat().st_size

    def flush(self, fsync: bool) -> None:
        if self.pending:
            self.db.executemany("INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)", self.pending)
            self.pending.clear()
        self.db.commit()

    def close(self, serialized_metadata: str) -> None:
        self.flush(False)
        self.db.execute("INSERT INTO metadata(metadata_version, metadata) VALUES (?, ?)",
                        (METADATA_VERSION, serialized_metadata))
        self.db.commit()
        self.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self.db.execute("PRAGMA journal_mode=DELETE")  # single self-contained file after a clean close
        self.db.close()


def _mcap_version() -> str:
    from importlib.metadata import version

    try:
        return version("mcap")
    except Exception:  # noqa: BLE001
        return "?"


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------

class BagWriter:
    """Write a rosbag2 bag (MCAP default, or sqlite3) from raw CDR or rosbags typestore messages.

    >>> with BagWriter(out) as w:                      # doctest: +SKIP
    ...     w.add_topic("/omc/tool/pose", "geometry_msgs/msg/PoseStamped")
    ...     w.write_msg("/omc/tool/pose", t_ns, msg)    # msg from w.typestore.types[...]

    Data reaches the file (and metadata.yaml is refreshed) at least every ``flush_interval``
    seconds of wall time as long as :meth:`write` or :meth:`flush_if_due` is called. Split
    limits (``max_bag_size`` bytes, ``max_bag_duration`` ns, 0 = off) start ``<bag>_<N+1>``.
    """

    def __init__(self, path: str | os.PathLike, *, storage: str = "mcap", chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = "", flush_interval: float = DEFAULT_FLUSH_INTERVAL, fsync: bool = False,
                 max_bag_size: int = 0, max_bag_duration: int = 0, custom_data: dict[str, str] | None = None,
                 typestore=None) -> None:
        if storage not in STORAGES:
            raise BagError(f"unknown storage {storage!r} (one of {', '.join(STORAGES)})")
        if compression not in ("", "none", "zstd", "lz4"):
            raise BagError(f"unknown compression {compression!r} (zstd, lz4 or none)")
        if compression not in ("", "none") and storage != "mcap":
            raise BagError("compression is only supported with mcap storage (chunk compression)")
        if flush_interval <= 0:
            raise BagError("flush_interval must be > 0")
        self.path = Path(path)
        self.storage = storage
        self.chunk_size = int(chunk_size)
        self.compression = "" if compression == "none" else compression
        self.flush_interval = float(flush_interval)
        self.fsync = fsync
        self.max_bag_size = int(max_bag_size)
        self.max_bag_duration = int(max_bag_duration)
        self.custom_data = dict(custom_data or {})
        self._typestore = typestore
        self.topics: dict[str, TopicInfo] = {}
        self.files: list[FileInfo] = []
        self._file: _McapFile | _SqliteFile | None = None
        self._last_flush = time.monotonic()
        self._closed = False

    # -- lifecycle
    def open(self) -> BagWriter:
        if self.path.exists():
            raise BagError(f"output folder {str(self.path)!r} already exists")
        try:
            self.path.mkdir(parents=True)
        except OSError as err:
            raise BagError(f"cannot create bag folder {str(self.path)!r}: {err.strerror}") from None
        self._open_file()
        self._write_metadata()
        return self

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def typestore(self):
        """rosbags typestore used by :meth:`write_msg` (Jazzy + fullperc_msgs by default)."""
        if self._typestore is None:
            self._typestore = fullperc_typestore()
        return self._typestore

    def _open_file(self) -> None:
        name = f"{self.path.name}_{len(self.files)}{STORAGE_EXT[self.storage]}"
        fpath = self.path / name
        self._file = (_McapFile(fpath, self.chunk_size, self.compression) if self.storage == "mcap"
                      else _SqliteFile(fpath))
        self.files.append(FileInfo(name))
        for t in self.topics.values():  # rosbag2 registers every known topic in each split file
            self._file.add_topic(t)

    def metadata(self) -> dict:
        # MCAP chunk compression lives inside the storage file; rosbag2 then leaves both
        # compression fields empty (as with its zstd storage preset profiles).
        return build_metadata(self.storage, self.topics.values(), self.files, custom_data=self.custom_data)

    def _write_metadata(self) -> None:
        write_metadata(self.path, self.metadata())

    # -- topics and messages
    def add_topic(self, name: str, msgtype: str, offered_qos: Sequence[dict[str, Any]] | None = None, *,
                  msgdef: str | None = None, encoding: str = "ros2msg", type_hash: str | None = None,
                  serialization_format: str = "cdr") -> TopicInfo:
        """Register a topic; its definition/hash come from the ament index unless given.

        ``offered_qos`` defaults to one reliable/volatile keep_last(10) profile (what a dataset
        generator's publisher would have offered). BagError for unknown types or duplicates.
        """
        self._check_open()
        if not name.startswith("/"):
            raise BagError(f"topic name {name!r} must be fully qualified (start with '/')")
        if name in self.topics:
            raise BagError(f"topic {name!r} is already in the bag")
        msgtype = normalize_type(msgtype)
        if msgdef is None:
            encoding, msgdef, found_hash = resolve_definition(msgtype, self._typestore)
            type_hash = found_hash if type_hash is None else type_hash
        info = TopicInfo(name, msgtype, [dict(q) for q in (offered_qos if offered_qos is not None
                                                           else [make_qos()])],
                         type_hash or "", serialization_format, msgdef, encoding)
        self._file.add_topic(info)
        self.topics[name] = info
        return info

    def write(self, topic: str, timestamp: int, data: bytes | bytearray | memoryview,
              publish_time: int | None = None) -> None:
        """Append raw serialized bytes received at ``timestamp`` (ns, the bag time)."""
        self._check_open()
        info = self.topics.get(topic)
        if info is None:
            raise BagError(f"topic {topic!r} was not added to the bag (call add_topic first)")
        t = int(timestamp)
        if self.max_bag_duration and self.files[-1].start is not None and \
                t - self.files[-1].start >= self.max_bag_duration:
            self.split()
        self._file.write(topic, t, bytes(data), t if publish_time is None else int(publish_time))
        self.files[-1].add(t)
        info.count += 1
        if self.max_bag_size and self._file.size() >= self.max_bag_size:
            self.split()
        self.flush_if_due()

    def write_msg(self, topic: str, timestamp: int, msg: Any, publish_time: int | None = None) -> None:
        """Serialize a rosbags typestore message (CDR, little endian) and append it."""
        info = self.topics.get(topic)
        if info is None:
            raise BagError(f"topic {topic!r} was not added to the bag (call add_topic first)")
        try:
            data = self.typestore.serialize_cdr(msg, info.msgtype)
        except Exception as err:  # noqa: BLE001 - rosbags raises several error types
            raise BagError(f"cannot serialize a {type(msg).__name__} as {info.msgtype} for {topic}: {err}") from None
        self.write(topic, timestamp, data, publish_time)

    # -- durability
    def flush_if_due(self) -> bool:
        if not self._closed and self._file is not None and \
                time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Push everything written so far to the file and refresh metadata.yaml."""
        self._check_open()
        self._file.flush(self.fsync)
        self._write_metadata()
        self._last_flush = time.monotonic()

    def split(self) -> None:
        """Close the current file and continue in the next <bag>_<N>."""
        self._check_open()
        self._file.close(self._serialized_metadata())
        self._open_file()
        self._write_metadata()

    def _serialized_metadata(self) -> str:
        return yaml.safe_dump(self.metadata()["rosbag2_bagfile_information"], sort_keys=False)

    def close(self) -> None:
        if self._closed or self._file is None:
            return
        self._file.close(self._serialized_metadata())
        self._closed = True
        self._write_metadata()

    def _check_open(self) -> None:
        if self._closed or self._file is None:
            raise BagError("bag writer is not open")

    @property
    def message_count(self) -> int:
        return sum(f.count for f in self.files)


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------

@dataclass
class BagMessage:
    topic: str
    msgtype: str
    timestamp: int  # bag (receive) time, ns
    data: bytes  # serialized CDR as recorded


class BagReader:
    """Read a rosbag2 bag through rosbags' AnyReader, with errors turned into clear BagErrors.

    ``topics`` maps name -> TopicInfo (type, count, offered QoS in v9 form, type hash) from
    metadata.yaml; :meth:`messages` yields :class:`BagMessage` in timestamp order.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.info = load_metadata(self.path)
        self.storage = str(self.info.get("storage_identifier", ""))
        for rel in self.info.get("relative_file_paths") or []:
            f = self.path / rel
            if not f.is_file():
                raise BagError(f"bag {str(self.path)!r}: file {rel!r} listed in {METADATA_FILE} is missing")
            if self.storage == "mcap":
                _check_mcap_complete(f, self.path)
        self.topics: dict[str, TopicInfo] = {}
        for entry in self.info.get("topics_with_message_count") or []:
            try:
                tm = entry["topic_metadata"]
                self.topics[tm["name"]] = TopicInfo(
                    tm["name"], tm["type"], parse_qos(tm.get("offered_qos_profiles")),
                    str(tm.get("type_description_hash", "") or ""), tm.get("serialization_format", "cdr"),
                    count=int(entry.get("message_count", 0)))
            except (KeyError, TypeError, ValueError) as err:
                raise BagError(f"{self.path / METADATA_FILE}: malformed topic entry {entry!r} ({err})") from None
        self._reader = None

    def open(self) -> BagReader:
        from rosbags.highlevel import AnyReader

        try:
            self._reader = AnyReader([self.path])
            self._reader.open()
        except Exception as err:  # noqa: BLE001 - rosbags raises many types for broken files
            self._reader = None
            raise BagError(f"cannot read bag {str(self.path)!r}: {type(err).__name__}: {err}") from None
        return self

    def __enter__(self) -> BagReader:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    @property
    def start_time(self) -> int:
        return int(self.info.get("starting_time", {}).get("nanoseconds_since_epoch", 0))

    @property
    def duration(self) -> int:
        return int(self.info.get("duration", {}).get("nanoseconds", 0))

    @property
    def message_count(self) -> int:
        return int(self.info.get("message_count", 0))

    def messages(self, topics: Iterable[str] | None = None, start: int | None = None,
                 stop: int | None = None) -> Iterator[BagMessage]:
        """Messages of ``topics`` (all if None) with ``start <= timestamp < stop``, in time order."""
        if self._reader is None:
            self.open()
        want = None if topics is None else set(topics)
        conns = [c for c in self._reader.connections if want is None or c.topic in want]
        try:
            for conn, t, raw in self._reader.messages(connections=conns, start=start, stop=stop):
                yield BagMessage(conn.topic, conn.msgtype, int(t), bytes(raw))
        except BagError:
            raise
        except Exception as err:  # noqa: BLE001
            raise BagError(f"bag {str(self.path)!r} is corrupt: {type(err).__name__}: {err}") from None

    def deserialize(self, data: bytes, msgtype: str) -> Any:
        """Decode with the definitions stored in the bag (no installed packages needed)."""
        if self._reader is None:
            self.open()
        return self._reader.deserialize(data, msgtype)


def _check_mcap_complete(path: Path, bagdir: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(8)
        if head != MCAP_MAGIC:
            raise BagError(f"{path} is not an MCAP file (bad magic); the bag is corrupt")
        f.seek(0, os.SEEK_END)
        if f.tell() < 16:
            raise BagError(f"{path} is truncated; the bag is corrupt")
        f.seek(-8, os.SEEK_END)
        if f.read(8) != MCAP_MAGIC:
            raise BagError(f"{path} is incomplete (the recorder did not close it, e.g. it was killed); "
                           f"recover it with: python -m fullperc_eval.bag_io reindex {bagdir}")


# --------------------------------------------------------------------------------------------
# Recovery (reindex)
# --------------------------------------------------------------------------------------------

@dataclass
class RecoveryReport:
    file: str
    messages: int
    recovered: bool  # the file was incomplete and got rewritten (original kept as <file>.orig)
    error: str = ""  # why salvage stopped early ('' if the whole file was read)


def _file_index(name: str) -> tuple[int, str]:
    m = re.search(r"_(\d+)\.(mcap|db3)$", name)
    return (int(m.group(1)) if m else 0, name)


def reindex(bagdir: str | os.PathLike) -> tuple[dict, list[RecoveryReport]]:
    """Rebuild metadata.yaml from the storage files; make incomplete MCAP files complete.

    Like ``ros2 bag reindex``. An MCAP without footer (killed recorder) is read record by record
    up to the first damaged record, and rewritten as a complete, indexed file in log-time order;
    the original is kept beside it as ``<file>.orig``. A sqlite3 file is opened read-write so its
    WAL is checkpointed. Returns the new metadata and one report per file.
    """
    bagdir = Path(bagdir)
    if not bagdir.is_dir():
        raise BagError(f"bag {str(bagdir)!r} is not a directory")
    mcaps = sorted((p for p in bagdir.glob("*.mcap")), key=lambda p: _file_index(p.name))
    dbs = sorted((p for p in bagdir.glob("*.db3")), key=lambda p: _file_index(p.name))
    if mcaps and dbs:
        raise BagError(f"bag {str(bagdir)!r} holds both .mcap and .db3 files; cannot tell the storage")
    if not mcaps and not dbs:
        raise BagError(f"bag {str(bagdir)!r} has no .mcap or .db3 storage file to reindex")
    old: dict = {}
    try:
        old = load_metadata(bagdir)
    except BagError:
        pass
    reports: list[RecoveryReport] = []
    topics: dict[str, TopicInfo] = {}
    files: list[FileInfo] = []
    if mcaps:
        for p in mcaps:
            reports.append(_recover_mcap(p))
            files.append(_scan_mcap(p, topics))
        storage = "mcap"
    else:
        for p in dbs:
            reports.append(_recover_sqlite(p))
            files.append(_scan_sqlite(p, topics))
        storage = "sqlite3"
    meta = build_metadata(storage, topics.values(), files,
                          compression_format=str(old.get("compression_format", "") or ""),
                          compression_mode=str(old.get("compression_mode", "") or ""),
                          custom_data=old.get("custom_data") or None,
                          ros_distro=old.get("ros_distro") if old else None)
    write_metadata(bagdir, meta)
    return meta, reports


def _mcap_is_complete(path: Path) -> bool:
    try:
        _check_mcap_complete(path, path.parent)
    except BagError:
        return False
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return make_reader(f).get_summary() is not None
    except Exception:  # noqa: BLE001
        return False


def _recover_mcap(path: Path) -> RecoveryReport:
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    if _mcap_is_complete(path):
        return RecoveryReport(path.name, -1, False)
    with open(path, "rb") as f:
        if f.read(8) != MCAP_MAGIC:
            raise BagError(f"{path} is not an MCAP file (bad magic); nothing to recover")
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    messages: list[Any] = []
    header_profile = "ros2"
    error = ""
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    messages.append(rec)
                elif isinstance(rec, Metadata):
                    pass  # the rosbag2 record is regenerated below
                elif type(rec).__name__ == "Header":
                    header_profile = rec.profile or "ros2"
        except Exception as err:  # noqa: BLE001 - truncation shows up as several error types
            error = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
    from mcap.writer import CompressionType, Writer

    tmp = path.with_name(path.name + ".recovering")
    messages = [m for m in messages if m.channel_id in channels]
    messages.sort(key=lambda m: m.log_time)
    with open(tmp, "wb") as out:
        w = Writer(out, chunk_size=DEFAULT_CHUNK_SIZE, compression=CompressionType.NONE)
        w.start(profile=header_profile, library=f"fullperc_eval.bag_io reindex (python mcap {_mcap_version()})")
        sid_map = {}
        for sid, s in schemas.items():
            sid_map[sid] = w.register_schema(s.name, s.encoding, s.data)
        cid_map = {}
        for cid, c in channels.items():
            cid_map[cid] = w.register_channel(c.topic, c.message_encoding, sid_map.get(c.schema_id, 0),
                                              dict(c.metadata))
        for m in messages:
            w.add_message(cid_map[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
        w.add_metadata("rosbag2", {"serialized_metadata": ""})
        w.finish()
    os.replace(path, path.with_name(path.name + ".orig"))
    os.replace(tmp, path)
    return RecoveryReport(path.name, len(messages), True, error)


def _scan_mcap(path: Path, topics: dict[str, TopicInfo]) -> FileInfo:
    from mcap.reader import make_reader

    fi = FileInfo(path.name)
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as err:  # noqa: BLE001
        raise BagError(f"{path}: cannot read the MCAP summary ({type(err).__name__}: {err})") from None
    if summary is None:
        raise BagError(f"{path}: MCAP has no summary")
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        msgtype = schema.name if schema else ""
        info = topics.get(ch.topic)
        if info is None:
            info = topics[ch.topic] = TopicInfo(
                ch.topic, msgtype, parse_qos(ch.metadata.get("offered_qos_profiles", "")),
                ch.metadata.get("topic_type_hash", ""), ch.message_encoding)
        info.count += int(counts.get(cid, 0))
    st = summary.statistics
    if st and st.message_count:
        fi.count, fi.start, fi.end = int(st.message_count), int(st.message_start_time), int(st.message_end_time)
    return fi


def _recover_sqlite(path: Path) -> RecoveryReport:
    try:
        db = sqlite3.connect(path)
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        db.execute("PRAGMA journal_mode=DELETE")
        n = db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
        db.close()
    except sqlite3.DatabaseError as err:
        raise BagError(f"{path}: not a readable rosbag2 sqlite3 file ({err})") from None
    return RecoveryReport(path.name, int(n), False)


def _scan_sqlite(path: Path, topics: dict[str, TopicInfo]) -> FileInfo:
    fi = FileInfo(path.name)
    try:
        db = sqlite3.connect(path)
        rows = db.execute("SELECT t.name, t.type, t.serialization_format, t.offered_qos_profiles, "
                          "t.type_description_hash, COUNT(m.id), MIN(m.timestamp), MAX(m.timestamp) "
                          "FROM topics t LEFT JOIN messages m ON m.topic_id = t.id GROUP BY t.id").fetchall()
        db.close()
    except sqlite3.DatabaseError as err:
        raise BagError(f"{path}: not a readable rosbag2 sqlite3 file ({err})") from None
    for name, typ, fmt, qos, rihs, n, t0, t1 in rows:
        info = topics.get(name)
        if info is None:
            info = topics[name] = TopicInfo(name, typ, parse_qos(qos), rihs or "", fmt)
        info.count += int(n)
        if n:
            fi.count += int(n)
            fi.start = t0 if fi.start is None else min(fi.start, t0)
            fi.end = t1 if fi.end is None else max(fi.end, t1)
    return fi


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

def format_info(reader: BagReader) -> str:
    lines = [f"Files:             {', '.join(reader.info.get('relative_file_paths') or [])}",
             f"Storage id:        {reader.storage}",
             f"Duration:          {reader.duration / 1e9:.3f} s",
             f"Start:             {reader.start_time} ns",
             f"Messages:          {reader.message_count}",
             "Topic information:"]
    for t in reader.topics.values():
        lines.append(f"  Topic: {t.name} | Type: {t.msgtype} | Count: {t.count} | "
                     f"Serialization Format: {t.serialization_format}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.bag_io", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("info", help="print what metadata.yaml says about a bag").add_argument("bag")
    sub.add_parser("reindex", help="rebuild metadata.yaml and recover incomplete MCAP files").add_argument("bag")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "info":
            print(format_info(BagReader(args.bag)))
        else:
            meta, reports = reindex(args.bag)
            for r in reports:
                if r.recovered:
                    print(f"{r.file}: recovered {r.messages} messages"
                          + (f" (stopped at: {r.error})" if r.error else "") + f"; original kept as {r.file}.orig")
                else:
                    print(f"{r.file}: complete")
            info = meta["rosbag2_bagfile_information"]
            print(f"wrote {Path(args.bag) / METADATA_FILE}: {info['message_count']} messages, "
                  f"{len(info['topics_with_message_count'])} topics")
    except BagError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
