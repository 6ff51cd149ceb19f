"""Reading rosbag2 bags through rosbags' AnyReader, with every failure turned into a clear :class:`BagError`.

Before opening, the bag is checked the way a user would want it explained: metadata.yaml present and valid,
every storage file it lists present, every MCAP file complete and every sqlite3 file checkpointed. A recorder
that was killed leaves an MCAP file without footer, or a sqlite3 file whose messages are still in its write-ahead
log (``<file>-wal``, which rosbags' read-only reader does not see); the error then names the command that
recovers the bag (:data:`.metadata.REINDEX_HINT`).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BagError
from .fast_decode import DecodeError, RawMessages, decode_joint_states, decode_pose_stamped, read_raw
from .metadata import METADATA_FILE, REINDEX_HINT, TopicInfo, load_metadata
from .qos import parse_qos

MCAP_MAGIC = b"\x89MCAP0\r\n"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
JOINT_TYPE = "sensor_msgs/msg/JointState"


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
                check_mcap_complete(f, self.path)
            elif self.storage == "sqlite3":
                check_sqlite_complete(f, self.path)
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


@dataclass
class DecodedMessage:
    """One PoseStamped or JointState of :meth:`BagReader.decoded`: the fields the evaluator uses, as numpy."""

    topic: str
    timestamp: int                       # bag (receive) time, ns
    t_ns: int                            # header stamp, ns
    frame_id: str
    p: np.ndarray | None = None          # PoseStamped: position (3,) [m]
    q: np.ndarray | None = None          # PoseStamped: orientation x y z w
    names: list[str] | None = None       # JointState
    position: np.ndarray | None = None   # JointState


def _raw_messages(reader: BagReader, topics: list[str]) -> RawMessages:
    """The raw records of ``topics`` in bag order: one pass over an MCAP file when possible, else rosbags."""
    if reader.storage == "mcap":
        fast = read_raw(reader.path, [str(f) for f in reader.info.get("relative_file_paths") or []], topics)
        if fast is not None:
            return fast
    k = {t: i for i, t in enumerate(topics)}
    msgs = list(reader.messages(topics))
    return RawMessages(topics, np.fromiter((k[m.topic] for m in msgs), np.int64, len(msgs)),
                       np.fromiter((m.timestamp for m in msgs), np.int64, len(msgs)), [m.data for m in msgs])


def undecodable(reader: BagReader, topic: str, typ: str, e: DecodeError) -> BagError:
    """The error of a bulk decode that nothing could read: bag, topic, message number (from 1) and type."""
    return BagError(f"bag {str(reader.path)!r}: message {e.index + 1} of {topic} cannot be decoded as {typ} ({e})")


def decoded_messages(reader: BagReader, topics: list[str]) -> list[DecodedMessage]:
    """Every PoseStamped / JointState message of ``topics`` decoded in bulk (:mod:`.fast_decode`), in bag order.

    Why: the evaluator's replay spent more time in per-message reading and deserialising than in its filters.
    Values equal rosbags' deserializer bit for bit (test_fast_decode); a record the bulk path cannot read is
    decoded by rosbags, and one nothing can decode raises :class:`BagError` naming topic and message number.
    """
    for t in topics:
        if t not in reader.topics:
            raise BagError(f"bag {str(reader.path)!r} has no topic {t}")
        typ = reader.topics[t].msgtype
        if typ not in (POSE_TYPE, JOINT_TYPE):
            raise BagError(f"bag {str(reader.path)!r}: topic {t} has type {typ}; bulk decoding reads "
                           f"{POSE_TYPE} and {JOINT_TYPE} only")
    raw = _raw_messages(reader, topics)
    out: list[DecodedMessage | None] = [None] * len(raw.data)
    for k, topic in enumerate(topics):
        idx = np.flatnonzero(raw.topic == k)
        typ = reader.topics[topic].msgtype
        recs = [raw.data[i] for i in idx]
        stamps = raw.timestamp[idx].tolist()
        try:
            if typ == POSE_TYPE:
                pb = decode_pose_stamped(recs, lambda d, ty=typ: reader.deserialize(d, ty))
                for j, i in enumerate(idx.tolist()):
                    out[i] = DecodedMessage(topic, stamps[j], int(pb.t_ns[j]), pb.frame_id[j], p=pb.p[j], q=pb.q[j])
            else:
                jb = decode_joint_states(recs, lambda d, ty=typ: reader.deserialize(d, ty))
                for j, i in enumerate(idx.tolist()):
                    out[i] = DecodedMessage(topic, stamps[j], int(jb.t_ns[j]), "", names=jb.names[j],
                                            position=jb.position[j])
        except DecodeError as e:
            raise undecodable(reader, topic, typ, e) from None
    return out  # type: ignore[return-value]  # every slot filled: each record belongs to one topic


def decoded_messages_reference(reader: BagReader, topics: list[str]) -> list[DecodedMessage]:
    """What :func:`decoded_messages` returns, built with rosbags' reader and deserializer one message at a time
    (the evaluator's reading before the bulk path): the reference of the tests and the benchmark's comparison."""
    out = []
    for m in reader.messages(topics):
        try:
            msg = reader.deserialize(m.data, m.msgtype)
        except Exception as err:  # noqa: BLE001 - rosbags raises many types for bad CDR
            raise BagError(f"bag {str(reader.path)!r}: a message of {m.topic} cannot be decoded as {m.msgtype} "
                           f"({type(err).__name__}: {err})") from None
        t_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        if m.msgtype == POSE_TYPE:
            pp, qq = msg.pose.position, msg.pose.orientation
            out.append(DecodedMessage(m.topic, m.timestamp, t_ns, msg.header.frame_id,
                                      p=np.array([pp.x, pp.y, pp.z]), q=np.array([qq.x, qq.y, qq.z, qq.w])))
        else:
            out.append(DecodedMessage(m.topic, m.timestamp, t_ns, "", names=list(msg.name),
                                      position=np.asarray(msg.position, dtype=float)))
    return out


def check_mcap_complete(path: Path, bagdir: Path) -> None:
    """BagError unless ``path`` starts and ends with the MCAP magic (a killed recorder leaves no footer)."""
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
                           f"recover it with: {REINDEX_HINT} {bagdir}")


def check_sqlite_complete(path: Path, bagdir: Path) -> None:
    """BagError if ``path`` has a non-empty write-ahead log: the recorder did not close it (a clean close
    checkpoints the log into the file and removes it), and a read-only reader would miss what the log holds."""
    wal = path.with_name(path.name + "-wal")
    if wal.is_file() and wal.stat().st_size > 0:
        raise BagError(f"{path} is incomplete (the recorder did not close it, e.g. it was killed: its messages are "
                       f"still in {wal.name}); recover it with: {REINDEX_HINT} {bagdir}")
