"""Unit tests of the ROS-free bag modules (fullperc_eval.bag: writer, reader, recover, ...): no DDS, no rclpy.

Bags written by BagWriter are read back with third-party readers (rosbags AnyReader/Reader, the
mcap + mcap_ros2 reader, plain sqlite3), and their metadata.yaml is checked against rosbag2's v9
layout; crash recovery is tested on copies of a bag taken while the writer is still open.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import yaml

from fullperc_eval.bag import cli as bag_cli
from fullperc_eval.bag import writer as bag_writer
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.metadata import STORAGE_EXT, load_metadata
from fullperc_eval.bag.qos import make_qos, parse_qos, qos_yaml
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.bag.recover import reindex
from fullperc_eval.bag.types import fullperc_typestore, interface_file, rosbag2_msgdef, type_hash_from_index
from fullperc_eval.bag.writer import BagWriter

T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def ts():
    return fullperc_typestore()


def _time(ts, ns: int):
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def pose(ts, i: int, ns: int):
    T = ts.types
    hdr = T["std_msgs/msg/Header"](stamp=_time(ts, ns), frame_id="base")
    p = T["geometry_msgs/msg/Point"](x=float(i), y=-0.5 * i, z=0.25)
    q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(i / 10), w=np.cos(i / 10))
    return T["geometry_msgs/msg/PoseStamped"](header=hdr, pose=T["geometry_msgs/msg/Pose"](position=p, orientation=q))


def quality(ts, i: int, ns: int):
    T = ts.types
    hdr = T["std_msgs/msg/Header"](stamp=_time(ts, ns), frame_id="ots")
    return T["fullperc_msgs/msg/TrackingQuality"](header=hdr, body=f"tool{i % 3}", visible=bool(i % 2),
                                                  fit_error=np.float32(1e-4 * i), frame_number=i, markers_used=4,
                                                  latency=np.float32(0.003), port_status=0x31)


def region(ts, i: int, ns: int):
    T = ts.types
    hdr = T["std_msgs/msg/Header"](stamp=_time(ts, ns), frame_id="base")
    return T["fullperc_msgs/msg/Region"](header=hdr, target="tool", label=1 + i % 3, margin_deg=float(i),
                                         threshold_deg=30.0, valid_pairs=i % 5, cameras_seeing=i % 7,
                                         in_local_volume=i % 3 == 0,
                                         position=T["geometry_msgs/msg/Point"](x=0.1 * i, y=0.0, z=1.0))


TOPICS = {"/omc/tool/pose": ("geometry_msgs/msg/PoseStamped", pose),
          "/ots/tool/quality": ("fullperc_msgs/msg/TrackingQuality", quality),
          "/fullperc/tool/region": ("fullperc_msgs/msg/Region", region)}


def write_bag(path: Path, ts, n: int = 50, dt: int = 10_000_000, **kw) -> Path:
    with BagWriter(path, typestore=ts, **kw) as w:
        for name, (typ, _) in TOPICS.items():
            w.add_topic(name, typ)
        for i in range(n):
            for k, (name, (_, make)) in enumerate(TOPICS.items()):
                t = T0 + i * dt + k
                w.write_msg(name, t, make(ts, i, t))
    return path


def assert_same(a, b) -> None:
    """Field-by-field equality of two decoded messages (rosbags dataclass or mcap_ros2 object)."""
    if hasattr(a, "__dataclass_fields__"):
        for f in a.__dataclass_fields__:
            if f == "__msgtype__":
                continue
            assert_same(getattr(a, f), getattr(b, f))
    elif isinstance(a, np.ndarray | list | tuple):
        assert list(np.asarray(a).tolist()) == list(np.asarray(b).tolist())
    elif isinstance(a, float | np.floating):
        assert float(a) == float(b)
    else:
        assert a == b


# ------------------------------------------------------------------ write / read round trip

@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip_with_rosbags_anyreader(tmp_path, ts, storage):
    from rosbags.highlevel import AnyReader

    bag = write_bag(tmp_path / "b", ts, storage=storage)
    ext = STORAGE_EXT[storage]
    assert sorted(p.name for p in bag.iterdir()) == sorted(["metadata.yaml", f"b_0{ext}"])
    got: dict[str, list] = {}
    with AnyReader([bag]) as r:
        assert {c.topic: c.msgtype for c in r.connections} == {k: v[0] for k, v in TOPICS.items()}
        for conn, t, raw in r.messages():
            got.setdefault(conn.topic, []).append((t, r.deserialize(raw, conn.msgtype)))
    for k, (name, (_, make)) in enumerate(TOPICS.items()):
        assert [t for t, _ in got[name]] == [T0 + i * 10_000_000 + k for i in range(50)]
        for i, (t, msg) in enumerate(got[name]):
            assert_same(make(ts, i, t), msg)


def test_mcap_file_readable_by_mcap_ros2(tmp_path, ts):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    bag = write_bag(tmp_path / "b", ts)
    seen: dict[str, int] = {}
    with open(bag / "b_0.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        for ch in summary.channels.values():
            assert ch.message_encoding == "cdr"
            assert set(ch.metadata) == {"offered_qos_profiles", "topic_type_hash"}
            assert yaml.safe_load(ch.metadata["offered_qos_profiles"])[0]["reliability"] == "reliable"
        metas = list(reader.iter_metadata())
        assert [m.name for m in metas] == ["rosbag2"]
        assert "topics_with_message_count" in yaml.safe_load(metas[0].metadata["serialized_metadata"])
        for _, ch, msg, decoded in reader.iter_decoded_messages(log_time_order=True):
            i = seen.get(ch.topic, 0)
            assert decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec == msg.log_time
            if ch.topic == "/ots/tool/quality":
                assert decoded.frame_number == i and decoded.body == f"tool{i % 3}"
            if ch.topic == "/fullperc/tool/region":
                assert decoded.label == 1 + i % 3 and decoded.position.x == pytest.approx(0.1 * i)
            seen[ch.topic] = i + 1
    assert seen == dict.fromkeys(TOPICS, 50)


def test_metadata_v9_layout(tmp_path, ts):
    bag = write_bag(tmp_path / "b", ts, n=20, custom_data={"task": "P-B-G-P"})
    text = (bag / "metadata.yaml").read_text()
    info = yaml.safe_load(text)["rosbag2_bagfile_information"]
    # key order of rosbag2_storage yaml.hpp
    assert list(info) == ["version", "storage_identifier", "duration", "starting_time", "message_count",
                          "topics_with_message_count", "compression_format", "compression_mode",
                          "relative_file_paths", "files", "custom_data", "ros_distro"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["starting_time"]["nanoseconds_since_epoch"] == T0
    assert info["duration"]["nanoseconds"] == 19 * 10_000_000 + 2  # last - first receive time
    assert info["message_count"] == 60
    assert info["custom_data"] == {"task": "P-B-G-P"}
    assert info["files"] == [{"path": "b_0.mcap", "starting_time": {"nanoseconds_since_epoch": T0},
                              "duration": {"nanoseconds": 19 * 10_000_000 + 2}, "message_count": 60}]
    for e in info["topics_with_message_count"]:
        tm = e["topic_metadata"]
        assert e["message_count"] == 20
        q = tm["offered_qos_profiles"]
        assert isinstance(q, list) and q[0]["history"] == "keep_last" and q[0]["durability"] == "volatile"
        assert q[0]["deadline"] == {"sec": 9223372036, "nsec": 854775807}
        # the hash rosidl generated for this type (read here from the .json, not through bag_io)
        pkg, _, name = tm["type"].split("/")
        jpath = next(Path(p) / "share" / pkg / "msg" / f"{name}.json"
                     for p in os.environ["AMENT_PREFIX_PATH"].split(os.pathsep)
                     if (Path(p) / "share" / pkg / "msg" / f"{name}.json").exists())
        assert tm["type_description_hash"] == json.loads(jpath.read_text())["type_hashes"][0]["hash_string"]


def test_metadata_text_is_pyyamls_safe_dump_and_written_through_libyaml(tmp_path, ts):
    """metadata.yaml goes through libyaml's emitter when PyYAML has it (the recorder rewrites the file at every
    flush: 10 s of a 50 s demo recording with the pure-Python one), and the text is exactly yaml.safe_dump's."""
    from fullperc_eval.bag import metadata as md

    bag = write_bag(tmp_path / "b", ts, n=20, custom_data={"task": "P-B-G-P"})
    text = (bag / "metadata.yaml").read_text()
    assert text == yaml.safe_dump(yaml.safe_load(text), sort_keys=False, default_flow_style=False)
    if yaml.__with_libyaml__:
        assert md._DUMPER is yaml.CSafeDumper


def test_rosbags_reader_sees_qos_and_hash(tmp_path, ts):
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "b"
    with BagWriter(bag, typestore=ts) as w:
        w.add_topic("/a", "geometry_msgs/msg/PoseStamped",
                    [make_qos(reliability="best_effort", durability="transient_local", depth=3,
                                     deadline_ns=1_500_000_000)])
        w.write_msg("/a", T0, pose(ts, 1, T0))
    with Reader(bag) as r:
        (c,) = r.connections
        (q,) = c.ext.offered_qos_profiles
        assert (q.reliability.name, q.durability.name, q.depth) == ("BEST_EFFORT", "TRANSIENT_LOCAL", 3)
        assert (q.deadline.sec, q.deadline.nsec) == (1, 500_000_000)
        assert c.msgcount == 1


def test_msgdef_is_rosbag2_text(ts):
    """Root .msg text verbatim, then each dependency once after 80 '=' and 'MSG: pkg/Name'."""
    text = rosbag2_msgdef("fullperc_msgs/msg/Region")
    root = interface_file("fullperc_msgs/msg/Region").read_text()
    assert text.startswith(root)
    sections = text.split("\n" + "=" * 80 + "\n")
    names = [s.splitlines()[0] for s in sections[1:]]
    assert names == ["MSG: geometry_msgs/Point", "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time"]
    assert rosbag2_msgdef("nonexistent_msgs/msg/X") is None


def test_typestore_registers_fullperc_msgs(ts):
    for name in ("FusionStatus", "Region", "TrackingQuality"):
        t = f"fullperc_msgs/msg/{name}"
        assert t in ts.types
        assert ts.hash_rihs01(t) == type_hash_from_index(t)  # rosbags' hash == rosidl's


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_split_by_duration(tmp_path, ts, storage):
    from rosbags.highlevel import AnyReader

    bag = write_bag(tmp_path / "s", ts, n=50, storage=storage, max_bag_duration=100_000_000)
    info = load_metadata(bag)
    ext = STORAGE_EXT[storage]
    assert info["relative_file_paths"] == [f"s_{i}{ext}" for i in range(5)]
    assert [f["message_count"] for f in info["files"]] == [30] * 5
    with AnyReader([bag]) as r:
        ts_all = [t for _, t, _ in r.messages()]
    assert len(ts_all) == 150 and ts_all == sorted(ts_all)


def test_zstd_chunks_readable(tmp_path, ts):
    from rosbags.highlevel import AnyReader

    bag = write_bag(tmp_path / "z", ts, compression="zstd")
    with AnyReader([bag]) as r:
        assert r.message_count == 150


# ------------------------------------------------------------------ crash safety and reindex

def _snapshot(bag: Path, dst: Path) -> Path:
    """What a SIGKILL would leave: the files as they are on disk right now."""
    shutil.copytree(bag, dst)
    return dst


def test_killed_mcap_recovers_exactly_the_flushed_messages(tmp_path, ts):
    from rosbags.highlevel import AnyReader

    bag = tmp_path / "live"
    w = BagWriter(bag, typestore=ts, flush_interval=3600).open()
    w.add_topic("/omc/tool/pose", "geometry_msgs/msg/PoseStamped")
    for i in range(30):
        w.write_msg("/omc/tool/pose", T0 + i, pose(ts, i, T0 + i))
    w.flush()
    for i in range(30, 40):  # written but not flushed: lost by a kill
        w.write_msg("/omc/tool/pose", T0 + i, pose(ts, i, T0 + i))
    killed = _snapshot(bag, tmp_path / "killed")
    w.close()
    # metadata.yaml was refreshed at the flush, but the MCAP has no footer yet
    assert load_metadata(killed)["message_count"] == 30
    with pytest.raises(BagError, match="incomplete.*reindex"):
        BagReader(killed)
    meta, (rep,) = reindex(killed)
    assert rep.recovered and rep.messages == 30 and (killed / "live_0.mcap.orig").exists()
    assert meta["rosbag2_bagfile_information"]["message_count"] == 30
    with AnyReader([killed]) as r:
        xs = [r.deserialize(raw, c.msgtype).pose.position.x for c, _, raw in r.messages()]
    assert xs == [float(i) for i in range(30)]
    # reindexing a complete bag changes nothing but metadata.yaml
    _, (rep2,) = reindex(killed)
    assert not rep2.recovered


def test_flush_interval_bounds_unflushed_data(tmp_path, ts, monkeypatch):
    """write() flushes by itself once flush_interval has passed (no explicit flush call)."""
    clock = [1000.0]
    monkeypatch.setattr(bag_writer.time, "monotonic", lambda: clock[0])
    bag = tmp_path / "live"
    w = BagWriter(bag, typestore=ts, flush_interval=0.5).open()
    w.add_topic("/omc/tool/pose", "geometry_msgs/msg/PoseStamped")
    for i in range(100):  # 100 messages over 0.99 "seconds"
        clock[0] = 1000.0 + i * 0.01
        w.write_msg("/omc/tool/pose", T0 + i, pose(ts, i, T0 + i))
    killed = _snapshot(bag, tmp_path / "killed")
    w.close()
    _, (rep,) = reindex(killed)
    assert rep.messages >= 100 - 50  # at most 0.5 s (50 messages) not on disk


def test_recover_truncated_mid_record(tmp_path, ts):
    """A file cut in the middle of a chunk keeps every complete chunk before the cut."""
    from rosbags.highlevel import AnyReader

    bag = tmp_path / "live"
    w = BagWriter(bag, typestore=ts).open()
    w.add_topic("/omc/tool/pose", "geometry_msgs/msg/PoseStamped")
    sizes = []
    for k in range(4):
        for i in range(k * 10, k * 10 + 10):
            w.write_msg("/omc/tool/pose", T0 + i, pose(ts, i, T0 + i))
        w.flush()
        sizes.append((bag / "live_0.mcap").stat().st_size)
    killed = _snapshot(bag, tmp_path / "killed")
    w.close()
    f = killed / "live_0.mcap"
    f.write_bytes(f.read_bytes()[: (sizes[2] + sizes[3]) // 2])  # cut inside the 4th chunk
    _, (rep,) = reindex(killed)
    assert rep.recovered and rep.messages == 30 and rep.error
    with AnyReader([killed]) as r:
        assert r.message_count == 30


def test_killed_sqlite_keeps_committed_messages(tmp_path, ts):
    from rosbags.highlevel import AnyReader

    bag = tmp_path / "live"
    w = BagWriter(bag, storage="sqlite3", typestore=ts, flush_interval=3600).open()
    w.add_topic("/omc/tool/pose", "geometry_msgs/msg/PoseStamped")
    for i in range(25):
        w.write_msg("/omc/tool/pose", T0 + i, pose(ts, i, T0 + i))
    w.flush()
    for i in range(25, 30):
        w.write_msg("/omc/tool/pose", T0 + i, pose(ts, i, T0 + i))
    killed = _snapshot(bag, tmp_path / "killed")  # includes the -wal file
    w.close()
    meta, (rep,) = reindex(killed)
    assert rep.messages == 25 and meta["rosbag2_bagfile_information"]["message_count"] == 25
    with AnyReader([killed]) as r:
        assert r.message_count == 25
    db = sqlite3.connect(killed / "live_0.db3")
    assert db.execute("SELECT schema_version FROM schema").fetchone()[0] == 4
    db.close()


def test_reindex_rebuilds_missing_metadata(tmp_path, ts):
    bag = write_bag(tmp_path / "b", ts, n=10)
    original = yaml.safe_load((bag / "metadata.yaml").read_text())
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="no metadata.yaml.*reindex"):
        BagReader(bag)
    meta, _ = reindex(bag)
    a, b = meta["rosbag2_bagfile_information"], original["rosbag2_bagfile_information"]
    for key in ("message_count", "duration", "starting_time", "relative_file_paths", "files",
                "topics_with_message_count"):
        assert a[key] == b[key], key


# ------------------------------------------------------------------ our reader and bad input

def test_bag_reader_filters_and_decodes(tmp_path, ts):
    bag = write_bag(tmp_path / "b", ts, n=20)
    with BagReader(bag) as r:
        assert set(r.topics) == set(TOPICS) and r.message_count == 60
        assert r.topics["/ots/tool/quality"].offered_qos[0]["reliability"] == "reliable"
        msgs = list(r.messages(["/ots/tool/quality"], start=T0 + 5 * 10_000_000))
        assert [m.topic for m in msgs] == ["/ots/tool/quality"] * 15
        assert [r.deserialize(m.data, m.msgtype).frame_number for m in msgs] == list(range(5, 20))


def test_bad_inputs_raise_bag_error(tmp_path, ts):
    with pytest.raises(BagError, match="does not exist"):
        BagReader(tmp_path / "missing")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("just: [a, broken\n")
    with pytest.raises(BagError, match="not a valid rosbag2 metadata"):
        BagReader(bad)
    bag = write_bag(tmp_path / "b", ts, n=5)
    (bag / "b_0.mcap").write_bytes(b"garbage" * 20)
    with pytest.raises(BagError, match="not an MCAP file"):
        BagReader(bag)
    with pytest.raises(BagError, match="bad magic"):
        reindex(bag)
    with pytest.raises(BagError, match="no .mcap or .db3"):
        reindex(bad)


def test_writer_rejects_bad_use(tmp_path, ts):
    (tmp_path / "exists").mkdir()
    with pytest.raises(BagError, match="already exists"):
        BagWriter(tmp_path / "exists").open()
    with pytest.raises(BagError, match="unknown storage"):
        BagWriter(tmp_path / "x", storage="rosbag1")
    with BagWriter(tmp_path / "w", typestore=ts) as w:
        with pytest.raises(BagError, match="unknown message type 'nonexistent_msgs/msg/Thing'"):
            w.add_topic("/t", "nonexistent_msgs/msg/Thing")
        with pytest.raises(BagError, match="malformed message type"):
            w.add_topic("/t", "not a type")
        w.add_topic("/t", "std_msgs/msg/String")
        with pytest.raises(BagError, match="already in the bag"):
            w.add_topic("/t", "std_msgs/msg/String")
        with pytest.raises(BagError, match="was not added"):
            w.write("/other", T0, b"\x00\x01\x00\x00")
        with pytest.raises(BagError, match="cannot serialize"):
            w.write_msg("/t", T0, pose(ts, 0, T0))
    with pytest.raises(BagError, match="not open"):
        w.write("/t", T0, b"")


def test_parse_qos_accepts_v8_and_v9():
    v8 = ("- history: 3\n  depth: 0\n  reliability: 1\n  durability: 2\n  deadline:\n    sec: 9223372036\n"
          "    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: 1\n"
          "  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
          "  avoid_ros_namespace_conventions: false\n")
    (q,) = parse_qos(v8)
    assert (q["history"], q["reliability"], q["durability"], q["liveliness"]) == \
        ("unknown", "reliable", "volatile", "automatic")
    assert parse_qos([q]) == [q] == parse_qos(qos_yaml([q]))
    with pytest.raises(BagError):
        parse_qos([{"reliability": "sometimes"}])


def test_cli_info_and_reindex(tmp_path, ts, capsys):
    bag = write_bag(tmp_path / "b", ts, n=5)
    assert bag_cli.main(["info", str(bag)]) == 0
    assert "/ots/tool/quality | Type: fullperc_msgs/msg/TrackingQuality | Count: 5" in capsys.readouterr().out
    assert bag_cli.main(["reindex", str(bag)]) == 0
    assert bag_cli.main(["info", str(tmp_path / "nope")]) == 1
    assert "error:" in capsys.readouterr().err
