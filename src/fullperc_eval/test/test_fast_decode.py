"""Bulk reading and decoding (fullperc_eval.bag.fast_decode, BagReader's decoded_messages) against rosbags.

The bulk path must give exactly what rosbags' reader and deserializer give: every message of the committed sample
bags, in the same order, bit for bit; records off the fixed layout (big-endian CDR, a longer frame_id in the same
batch) through the fallback; an undecodable record named by topic and number; and the evaluator's replay must
produce the same outputs with the bulk path as with per-message rosbags decoding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.fast_decode import DecodeError, decode_joint_states, decode_pose_stamped, read_raw
from fullperc_eval.bag.reader import BagReader, DecodedMessage, decoded_messages
from fullperc_eval.bag.reader import decoded_messages_reference as _reference
from fullperc_eval.bag.types import fullperc_typestore
from fullperc_eval.bag.writer import BagWriter

ROOT = Path(__file__).resolve().parents[3]
BAGS = sorted(p.parent for p in ROOT.glob("bags/*/*/metadata.yaml"))
POSE, JOINT = "geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/JointState"
T0 = 1_700_000_000_000_000_000


def _stamp(m) -> int:
    return int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec)


def _assert_same(got: list[DecodedMessage], ref: list[DecodedMessage]) -> None:
    assert len(got) == len(ref)
    for g, e in zip(got, ref, strict=True):
        assert (g.topic, g.timestamp, g.t_ns, g.frame_id, g.names) == (e.topic, e.timestamp, e.t_ns, e.frame_id,
                                                                       e.names)
        for a, b in ((g.p, e.p), (g.q, e.q), (g.position, e.position)):
            assert (a is None) == (b is None)
            if a is not None:
                assert a.tobytes() == b.tobytes()     # bit for bit, not approximately


@pytest.mark.skipif(not BAGS, reason="no committed sample bags under bags/")
@pytest.mark.parametrize("bag", BAGS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_message_of_the_committed_bags_equals_rosbags(bag: Path) -> None:
    with BagReader(bag) as r:
        topics = [t for t, info in r.topics.items() if info.msgtype in (POSE, JOINT)]
        raw = read_raw(bag, r.info["relative_file_paths"], topics)
        assert raw is not None, "a one-file chunked MCAP bag takes the bulk path"
        ref = _reference(r, topics)
        _assert_same(decoded_messages(r, topics), ref)
    assert len(ref) == sum(r.topics[t].count for t in topics)


def _pose(ts, t_ns: int, frame: str, x: float):
    T = ts.types
    return T[POSE](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
        sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame),
        pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=-x, z=2 * x),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.6, z=0.0, w=0.8)))


def test_order_ties_and_chunks_like_rosbags(tmp_path: Path) -> None:
    """Equal and decreasing receive times across topics and small chunks: the same order as rosbags' reader."""
    ts = fullperc_typestore()
    bag = tmp_path / "b"
    rng = np.random.default_rng(0)
    with BagWriter(bag, typestore=ts, chunk_size=2000, compression="zstd") as w:
        for t in ("/a", "/b", "/c"):
            w.add_topic(t, POSE)
        for i in range(600):
            t_recv = T0 + int(rng.integers(0, 40)) * 1_000_000      # many ties, out of order across chunks
            topic = ("/a", "/b", "/c")[i % 3]
            w.write_msg(topic, t_recv, _pose(ts, T0 + i, "omc" if i % 7 else "a_longer_frame", float(i)))
    with BagReader(bag) as r:
        topics = ["/a", "/c"]
        _assert_same(decoded_messages(r, topics), _reference(r, topics))


def test_sqlite_bag_takes_the_rosbags_path(tmp_path: Path) -> None:
    ts = fullperc_typestore()
    bag = tmp_path / "s"
    with BagWriter(bag, storage="sqlite3", typestore=ts) as w:
        w.add_topic("/a", POSE)
        for i in range(50):
            w.write_msg("/a", T0 + i, _pose(ts, T0 + i, "ots", i * 0.1))
    with BagReader(bag) as r:
        _assert_same(decoded_messages(r, ["/a"]), _reference(r, ["/a"]))


def test_off_layout_records_use_the_fallback_and_bad_ones_are_named() -> None:
    ts = fullperc_typestore()
    msgs = [_pose(ts, T0 + i, "omc" if i % 2 else "", 0.25 * i) for i in range(6)]
    raws = [bytes(ts.serialize_cdr(m, POSE)) for m in msgs]
    raws[3] = bytes(ts.serialize_cdr(msgs[3], POSE, little_endian=False))   # big-endian: not the bulk layout
    used = []

    def fallback(d: bytes):
        used.append(d)
        return ts.deserialize_cdr(d, POSE)

    b = decode_pose_stamped(raws, fallback)
    assert used == [raws[3]]
    for i, m in enumerate(msgs):
        assert (b.t_ns[i], b.frame_id[i]) == (_stamp(m), m.header.frame_id)
        assert b.p[i].tolist() == [m.pose.position.x, m.pose.position.y, m.pose.position.z]
        assert b.q[i].tolist() == [0.0, 0.6, 0.0, 0.8]
    with pytest.raises(DecodeError) as e:
        decode_pose_stamped([*raws[:2], raws[2][:30]], fallback)
    assert e.value.index == 2


def test_joint_states_with_different_names_and_counts() -> None:
    ts = fullperc_typestore()
    T = ts.types

    def js(i: int, names: list[str]):
        hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=i), frame_id="")
        return T[JOINT](header=hdr, name=names, position=np.arange(len(names)) + 0.5 * i,
                        velocity=np.zeros(len(names)), effort=np.zeros(0))

    msgs = [js(i, [f"joint_{k}" for k in range(1, 8)] if i % 3 else ["a", "bb"]) for i in range(9)]
    raws = [bytes(ts.serialize_cdr(m, JOINT)) for m in msgs]
    b = decode_joint_states(raws, lambda d: pytest.fail("every record fits the bulk layout"))
    for i, m in enumerate(msgs):
        assert (b.t_ns[i], b.names[i]) == (_stamp(m), list(m.name))
        assert b.position[i].tolist() == list(m.position)


def test_undecodable_message_named_by_topic_and_number(tmp_path: Path) -> None:
    ts = fullperc_typestore()
    bag = tmp_path / "bad"
    good = bytes(ts.serialize_cdr(_pose(ts, T0, "omc", 1.0), POSE))
    with BagWriter(bag, typestore=ts) as w:
        w.add_topic("/a", POSE)
        for i in range(4):
            w.write("/a", T0 + i, good if i != 2 else good[:20])
    with BagReader(bag) as r, pytest.raises(BagError, match=r"message 3 of /a cannot be decoded"):
        decoded_messages(r, ["/a"])
    with BagReader(bag) as r, pytest.raises(BagError, match=r"has no topic /b"):
        decoded_messages(r, ["/a", "/b"])


@pytest.mark.skipif(not BAGS, reason="no committed sample bags under bags/")
def test_replay_outputs_equal_with_per_message_rosbags_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """The evaluator's replay of a sample bag: the same outputs, bit for bit, as with rosbags per message."""
    from fullperc_eval.evaluation import replay as replay_mod
    from fullperc_fusion.fusion_config import load_fusion_config

    cfg, _ = load_fusion_config()
    bag = BAGS[0]
    fast = replay_mod.replay(bag, cfg, progress=False)
    monkeypatch.setattr(replay_mod, "decoded_messages", _reference)
    slow = replay_mod.replay(bag, cfg, progress=False)
    assert fast.messages == slow.messages > 0
    assert fast.joint_t_ns.tobytes() == slow.joint_t_ns.tobytes()
    assert fast.joint_q.tobytes() == slow.joint_q.tobytes()
    for f, arrays in slow.outputs.items():
        for k, v in arrays.items():
            assert fast.outputs[f][k].tobytes() == v.tobytes(), (f, k)


@pytest.mark.skipif(not BAGS, reason="no committed sample bags under bags/")
def test_a_chunk_that_does_not_decompress_is_a_bag_error(tmp_path: Path) -> None:
    """Compressed chunk data the decompressor refuses (here: the zstd frame's magic number overwritten) is named as
    a corrupt bag with the chunk's offset, like a size or CRC mismatch -- never the decompressor's own exception."""
    import shutil
    import struct

    src = BAGS[0]
    files = sorted(p.name for p in src.glob("*.mcap"))
    bag = tmp_path / "bag"
    shutil.copytree(src, bag)
    buf = bytearray((bag / files[0]).read_bytes())
    off = 8
    while off + 9 <= len(buf):
        op, size = struct.unpack_from("<BQ", buf, off)
        if op == 0x06:   # Chunk: start, end, uncompressed size, crc, compression, records
            clen = struct.unpack_from("<I", buf, off + 9 + 28)[0]
            comp = bytes(buf[off + 9 + 32:off + 9 + 32 + clen]).decode()
            rstart = off + 9 + 32 + clen + 8
            break
        off += 9 + size
    else:
        pytest.fail("no chunk in the sample bag")
    if comp != "zstd":
        pytest.skip(f"sample bag chunks are {comp!r}, not zstd")
    buf[rstart:rstart + 4] = b"\0\0\0\0"
    (bag / files[0]).write_bytes(bytes(buf))
    with pytest.raises(BagError, match=r"corrupt: chunk at byte \d+ does not decompress \(zstd: "):
        read_raw(bag, files, ["/omc/tool/pose"])
