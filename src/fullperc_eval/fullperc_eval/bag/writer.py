"""Writing rosbag2 bags (MCAP default, or sqlite3) from raw CDR or rosbags typestore messages.

Why our own writer instead of ``rosbags.rosbag2.Writer``: rosbags keeps a whole MCAP chunk (or the
whole sqlite transaction) in memory until ``close()``, so a killed recorder loses everything. This
writer finishes a chunk / commits at a bounded interval (``flush_interval``) and rewrites
metadata.yaml each time, so a SIGKILLed recorder loses at most that interval; :func:`.recover.reindex`
then turns the summary-less MCAP into a complete, indexed one (like ``ros2 bag reindex`` plus
``mcap recover``). It also writes what rosbag2 writes and rosbags omits: the ``<bag>_<N>.mcap``
file names, the channel ``topic_type_hash`` and rosbag2's own message-definition text.

Everything here runs without rclpy: the recorder node (:mod:`.record`) hands in raw CDR bytes;
dataset generators hand in rosbags typestore messages (:meth:`BagWriter.write_msg`). Conventions: MCAP
``ros2`` profile, sqlite3 schema version 4 (``reference/bags_ros2.md`` §1).
"""

from __future__ import annotations

import os
import sqlite3
import time
from collections.abc import Sequence
from importlib.metadata import version
from pathlib import Path
from typing import Any

from .errors import BagError
from .metadata import (
    METADATA_VERSION,
    STORAGE_EXT,
    STORAGES,
    FileInfo,
    TopicInfo,
    build_metadata,
    dump_yaml,
    write_metadata,
)
from .qos import make_qos, qos_yaml
from .types import fullperc_typestore, normalize_type, resolve_definition

DEFAULT_CHUNK_SIZE = 768 * 1024  # libmcap's default, what rosbag2 uses
DEFAULT_FLUSH_INTERVAL = 0.5  # s; bounds what a killed recorder loses
SQLITE_SCHEMA_VERSION = 4
# The MCAP header's "library" names the writer. The committed sample bags carry this name; it is kept as it is
# (not the module's current path) so that regenerated bags stay byte-identical to them.
MCAP_LIBRARY = "fullperc_eval.bag_io"


class _McapFile:
    """One <bag>_<N>.mcap file written the way rosbag2_storage_mcap does (profile ros2)."""

    def __init__(self, path: Path, chunk_size: int, compression: str) -> None:
        from mcap.writer import CompressionType, Writer

        comp = {"": CompressionType.NONE, "none": CompressionType.NONE, "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4}[compression]
        self.path = path
        self.stream = open(path, "xb")  # noqa: SIM115 - closed in close()
        self.writer = Writer(self.stream, chunk_size=chunk_size, compression=comp)
        self.writer.start(profile="ros2", library=f"{MCAP_LIBRARY} (python mcap {mcap_version()})")
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


def mcap_version() -> str:
    """Version of the ``mcap`` package (for the MCAP header's library field), '?' if unknown."""
    try:
        return version("mcap")
    except Exception:  # noqa: BLE001
        return "?"


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
        return dump_yaml(self.metadata()["rosbag2_bagfile_information"], sort_keys=False)

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
