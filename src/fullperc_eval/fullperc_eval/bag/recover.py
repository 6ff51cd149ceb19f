"""Recovery of a bag (``reindex``): rebuild metadata.yaml from the storage files, make killed MCAP files complete.

What ``ros2 bag reindex`` and ``mcap recover`` do together: the writer (:mod:`.writer`) keeps what it flushed
readable on disk, and this turns it back into a complete, indexed bag.
"""

from __future__ import annotations

import os
import re
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import BagError
from .metadata import FileInfo, TopicInfo, build_metadata, load_metadata, write_metadata
from .qos import parse_qos
from .reader import MCAP_MAGIC, check_mcap_complete
from .writer import DEFAULT_CHUNK_SIZE, MCAP_LIBRARY, mcap_version


@dataclass
class RecoveryReport:
    file: str
    messages: int
    recovered: bool  # the file was incomplete: MCAP rewritten (original kept as <file>.orig), sqlite3 log checkpointed
    error: str = ""  # why salvage stopped early ('' if the whole file was read)


def _file_index(name: str) -> tuple[int, str]:
    m = re.search(r"_(\d+)\.(mcap|db3)$", name)
    return (int(m.group(1)) if m else 0, name)


def reindex(bagdir: str | os.PathLike) -> tuple[dict, list[RecoveryReport]]:
    """Rebuild metadata.yaml from the storage files; make incomplete MCAP files complete.

    Like ``ros2 bag reindex``. An MCAP without footer (killed recorder) is read record by record
    up to the first damaged record, and rewritten as a complete, indexed file in log-time order;
    the original is kept beside it as ``<file>.orig``. A sqlite3 file is opened read-write so its
    write-ahead log (``<file>-wal``, where a killed recorder's commits are) is checkpointed into it and
    removed. Returns the new metadata and one report per file.
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
        check_mcap_complete(path, path.parent)
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
        w.start(profile=header_profile, library=f"{MCAP_LIBRARY} reindex (python mcap {mcap_version()})")
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
    wal = path.with_name(path.name + "-wal")
    had_log = wal.is_file() and wal.stat().st_size > 0  # a killed recorder's commits are still in the log
    try:
        db = sqlite3.connect(path)
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        db.execute("PRAGMA journal_mode=DELETE")
        n = db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
        db.close()
    except sqlite3.DatabaseError as err:
        raise BagError(f"{path}: not a readable rosbag2 sqlite3 file ({err})") from None
    return RecoveryReport(path.name, int(n), had_log)


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
