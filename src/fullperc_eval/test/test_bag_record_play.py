"""Multi-process tests of the installed `record` and `play` executables (issue 8).

A publisher process (this file run as a script: ``python test_bag_record_play.py publish ...``)
publishes N messages of three types (PoseStamped, our TrackingQuality, JointState with
variable-length arrays) at 1 kHz with RELIABLE QoS, after waiting until the recorder's
subscriptions are matched. Message contents are a pure function of the sequence number and the
publish stamp the publisher logs, so the test checks the decoded bag against the publisher's
input, not against anything our bag code computed.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import Procs, claim_domain, installed_exe, side_by_side_fixture, wait_for
from fullperc_eval.bag.replay_timing import envelope_timing

PREFIX = "/fp_test"
TOPICS = {
    f"{PREFIX}/pose": "geometry_msgs/msg/PoseStamped",
    f"{PREFIX}/quality": "fullperc_msgs/msg/TrackingQuality",
    f"{PREFIX}/joints": "sensor_msgs/msg/JointState",
}
N = 1500  # per topic, 1.5 s at 1 kHz
RATE_HZ = 1000.0


# ------------------------------------------------------------------ message contents (the input)

def expected(topic: str, seq: int, stamp_ns: int) -> dict:
    """Field values of message ``seq`` on ``topic`` (what the publisher sends)."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    base = {"sec": sec, "nanosec": nsec}
    if topic.endswith("/pose"):
        yaw = seq * 1e-3
        return {**base, "frame_id": "omc", "p": (seq * 1e-3, -seq * 2e-3, 0.5),
                "q": (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))}
    if topic.endswith("/quality"):
        return {**base, "frame_id": "omc", "body": "tool", "visible": seq % 7 != 0,
                "fit_error": float(np.float32(seq * 1e-5)), "frame_number": seq, "markers_used": seq % 5,
                "latency": float(np.float32(0.002)), "port_status": (seq * 3) % 2**32}
    k = seq % 8  # 0..7 joints: empty and non-empty sequences, strings of varying length
    return {**base, "frame_id": "diana_base", "name": [f"joint_{i}" * (1 + i % 2) for i in range(k)],
            "position": [seq + 0.1 * i for i in range(k)], "velocity": [], "effort": [-0.5 * i for i in range(k)]}


def build_rclpy_msg(topic: str, seq: int, stamp_ns: int):
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState

    from fullperc_msgs.msg import TrackingQuality

    e = expected(topic, seq, stamp_ns)
    if topic.endswith("/pose"):
        m = PoseStamped()
        m.pose.position.x, m.pose.position.y, m.pose.position.z = e["p"]
        q = m.pose.orientation
        q.x, q.y, q.z, q.w = e["q"]
    elif topic.endswith("/quality"):
        m = TrackingQuality(body=e["body"], visible=e["visible"], fit_error=e["fit_error"],
                            frame_number=e["frame_number"], markers_used=e["markers_used"], latency=e["latency"],
                            port_status=e["port_status"])
    else:
        m = JointState(name=e["name"], position=e["position"], velocity=e["velocity"], effort=e["effort"])
    m.header.stamp.sec, m.header.stamp.nanosec = e["sec"], e["nanosec"]
    m.header.frame_id = e["frame_id"]
    return m


def check_decoded(topic: str, msg, seq: int, stamp_ns: int) -> None:
    """Compare a decoded message (rosbags or mcap_ros2 object) with the publisher's input."""
    e = expected(topic, seq, stamp_ns)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (e["sec"], e["nanosec"])
    assert msg.header.frame_id == e["frame_id"]
    if topic.endswith("/pose"):
        p, q = msg.pose.position, msg.pose.orientation
        assert (p.x, p.y, p.z) == e["p"] and (q.x, q.y, q.z, q.w) == e["q"]
    elif topic.endswith("/quality"):
        got = {k: getattr(msg, k) for k in ("body", "visible", "fit_error", "frame_number", "markers_used",
                                             "latency", "port_status")}
        assert {k: (float(v) if isinstance(v, float | np.floating) else v) for k, v in got.items()} == \
            {k: e[k] for k in got}
    else:
        assert list(msg.name) == e["name"]
        for k in ("position", "velocity", "effort"):
            assert [float(x) for x in getattr(msg, k)] == e[k]


# ------------------------------------------------------------------ publisher process

def publisher_main(argv: list[str]) -> int:
    import argparse

    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from fullperc_common.node_main import wait_for_acks

    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=N)
    ap.add_argument("--rate", type=float, default=RATE_HZ)
    ap.add_argument("--log", required=True)
    ap.add_argument("--ack-timeout", type=float, default=60.0, help="[s] wait this long for the readers' acks")
    ap.add_argument("--stop-file", help="stop publishing once this file exists (the log has what was published)")
    args = ap.parse_args(argv)
    stop_file = Path(args.stop_file) if args.stop_file else None
    rclpy.init()
    node = rclpy.create_node("fp_test_publisher")
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.n + 10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pubs = {t: node.create_publisher(type(build_rclpy_msg(t, 0, 0)), t, qos) for t in TOPICS}
    end = time.monotonic() + 60
    while any(p.get_subscription_count() == 0 for p in pubs.values()):
        if time.monotonic() > end:
            print("no subscriber", flush=True)
            return 3
        time.sleep(0.02)
    print("READY", flush=True)
    stamps = []
    t0 = time.monotonic()
    stopped = False
    for seq in range(args.n):
        if stop_file is not None and seq % 10 == 0 and stop_file.exists():
            stopped = True
            break
        left = t0 + seq / args.rate - time.monotonic()
        if left > 0:
            time.sleep(left)
        stamp = time.time_ns()
        for t, p in pubs.items():
            p.publish(build_rclpy_msg(t, seq, stamp))
        stamps.append(stamp)
        if seq == args.n // 2:
            print("HALF", flush=True)
    acked = not wait_for_acks(node, 0.0 if stopped else args.ack_timeout)
    Path(args.log).write_text(json.dumps({"stamps": stamps, "acked": acked}))
    print("DONE", flush=True)
    try:
        while rclpy.ok():
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    return 0


# ------------------------------------------------------------------ helpers

def start_publisher(procs: Procs, log: Path, n: int = N, ack_timeout: float = 60.0, stop_file: Path | None = None):
    return procs.start([sys.executable, str(Path(__file__).resolve()), "publish", "--n", str(n), "--log", str(log),
                        "--ack-timeout", str(ack_timeout), *(["--stop-file", str(stop_file)] if stop_file else [])],
                       name="publisher")


def wait_done(pub, timeout: float = 120.0) -> list[int]:
    wait_for(lambda: "DONE" in Procs.log(pub) or pub.poll() is not None, timeout=timeout, what="publisher DONE")
    assert "DONE" in Procs.log(pub), Procs.log(pub)
    return pub


def read_all(bag: Path) -> dict[str, list[tuple[int, bytes, object]]]:
    """topic -> [(bag time, raw bytes, decoded)] read with rosbags' AnyReader (not our reader)."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([bag]) as r:
        for conn, t, raw in r.messages():
            out.setdefault(conn.topic, []).append((t, bytes(raw), r.deserialize(raw, conn.msgtype)))
    return out


def record_cmd(out: Path, *extra: str) -> list[str]:
    return [installed_exe("fullperc_eval", "record"), "-o", str(out), *extra]


def stop_ok(procs: Procs, p, sig: int = signal.SIGINT) -> None:
    rc = procs.stop(p, sig, timeout=20)
    assert rc == 0, Procs.log(p)
    assert "Traceback" not in Procs.log(p), Procs.log(p)


def run_play(procs: Procs, bag: Path, out: Path, *play_args: str, topics=tuple(TOPICS)) -> tuple[dict, str]:
    """Record what `play bag *play_args` publishes into ``out``; return (read_all(out), play's log)."""
    # queues that hold a whole replay (4,500 messages): a recorder or player behind on a busy machine loses nothing
    rec = procs.start(record_cmd(out, "--topics", *topics, "--subscription-depth", "5000"), name=f"record_{out.name}")
    play = procs.start([installed_exe("fullperc_eval", "play"), str(bag), "--wait-for-subscribers", "60",
                        "--publisher-depth", "5000", *play_args], name=f"play_{out.name}")
    wait_for(lambda: play.poll() is not None, timeout=120, what="play to finish")
    assert play.returncode == 0 and "Traceback" not in Procs.log(play), Procs.log(play)
    stop_ok(procs, rec)
    return read_all(out), Procs.log(play)


# ------------------------------------------------------------------ tests

@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One 1 kHz recording shared by the round-trip and replay tests (own domain id)."""
    tmp = tmp_path_factory.mktemp("recorded")
    lease = claim_domain()
    env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    procs = Procs(env, tmp)
    try:
        bag = tmp / "bag"
        rec = procs.start(record_cmd(bag, "--topics", *TOPICS), name="record")
        pub = start_publisher(procs, tmp / "pub.json")
        wait_done(pub)
        stop_ok(procs, rec)
        log = json.loads((tmp / "pub.json").read_text())
        yield bag, log["stamps"], Procs.log(rec)
    finally:
        procs.stop_all()
        lease.release()


@pytest.fixture(scope="module")
def recorded_data(recorded):
    """read_all of the shared recording, read once (the tests only read it)."""
    return read_all(recorded[0])


@pytest.mark.system
def test_round_trip_counts_and_contents_rosbags(recorded, recorded_data):
    bag, stamps, rec_log = recorded
    data = recorded_data
    assert sorted(data) == sorted(TOPICS)
    for topic, msgs in data.items():
        assert len(msgs) == N, f"{topic}: {len(msgs)} != {N}"
        for seq, (_, _, msg) in enumerate(msgs):  # AnyReader yields in bag-time order = publish order
            check_decoded(topic, msg, seq, stamps[seq])
    assert f"wrote {3 * N} messages" in rec_log


@pytest.mark.system
def test_round_trip_mcap_reader_and_metadata(recorded):
    import yaml
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    bag, stamps, _ = recorded
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["message_count"] == 3 * N
    assert info["relative_file_paths"] == ["bag_0.mcap"]
    share = {p.split(os.sep)[-1]: p for p in os.environ["AMENT_PREFIX_PATH"].split(os.pathsep)}
    for entry in info["topics_with_message_count"]:
        tm = entry["topic_metadata"]
        assert entry["message_count"] == N
        assert tm["type"] == TOPICS[tm["name"]] and tm["serialization_format"] == "cdr"
        # QoS as the publisher offered it (reliable/volatile), v9 names
        (qos,) = tm["offered_qos_profiles"]
        assert qos["reliability"] == "reliable" and qos["durability"] == "volatile"
        # type hash = the rosidl-generated hash in share/<pkg>/msg/<T>.json
        pkg, _, name = tm["type"].split("/")
        jsons = [Path(p) / "share" / pkg / "msg" / f"{name}.json" for p in share.values()]
        j = json.loads(next(p for p in jsons if p.exists()).read_text())
        assert tm["type_description_hash"] == j["type_hashes"][0]["hash_string"]
    counts: dict[str, int] = {}
    with open(bag / "bag_0.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            seq = counts.get(channel.topic, 0)
            check_decoded(channel.topic, decoded, seq, stamps[seq])
            counts[channel.topic] = seq + 1
            assert message.log_time > 0
    assert counts == dict.fromkeys(TOPICS, N)


@pytest.mark.system
def test_bag_writer_serialization_decodes_in_rclpy(recorded, recorded_data):
    """BagWriter.write_msg's CDR (rosbags typestore incl. our fullperc_msgs) decodes with the
    rosidl-generated rclpy code into the published values, so generated datasets replay like
    recordings. Bytes may differ only in alignment padding: Fast DDS does not zero it (seen: a
    leftover 'j' after a JointState name), so byte equality is not required."""
    from rclpy.serialization import deserialize_message

    from fullperc_eval.bag.types import fullperc_typestore

    bag, stamps, _ = recorded
    ts = fullperc_typestore()
    data = recorded_data
    for topic, msgs in data.items():
        cls = type(build_rclpy_msg(topic, 0, 0))
        for seq in (0, 1, 7, N - 1):
            _, raw, msg = msgs[seq]
            ours = bytes(ts.serialize_cdr(msg, TOPICS[topic]))
            assert len(ours) == len(raw)
            check_decoded(topic, deserialize_message(ours, cls), seq, stamps[seq])


def _player_lateness_ms(log: str) -> float:
    """The player's own median lateness (publish time - scheduled time) from its summary line."""
    m = re.search(r"lateness median ([0-9.]+) ms", log)
    assert m, log
    return float(m.group(1))


@pytest.mark.system
@pytest.mark.parametrize("rate", [1.0, 2.0])
def test_replay_reproduces_bytes_and_timing(recorded, recorded_data, procs, tmp_path, rate):
    """Not side by side with the module's other system tests (below): a replay at 1 kHz x 3 topics is the one test
    here whose figures (the player's lateness, the receiving side's envelope) a busy machine moves."""
    bag, _, _ = recorded
    original = recorded_data
    replay, play_log = run_play(procs, bag, tmp_path / f"replay_{rate:g}", "--rate", str(rate))
    # The player judged by its own clock: messages go out when due -- not behind by more than a small part of the
    # replay. A schedule kept relative to the previous message (the overshoots add up) or a player that cannot keep
    # up falls behind steadily, by a large part of it. Not an absolute bound: the player spends ~15 us per message,
    # but on a busy machine its wake-ups come milliseconds late (median 11.9 ms at rate 2 beside this module's other
    # tests; 3 ms beside three busy loops, where a sleeping probe process saw 0.06 ms), which says nothing about its
    # schedule -- the receiving side's envelope below checks that.
    late = _player_lateness_ms(play_log)
    span_ms = 1e3 * np.ptp([m[0] for m in original[next(iter(TOPICS))]]) / 1e9 / rate
    print(f"rate {rate}: player lateness median {late:.3f} ms of a {span_ms:.0f} ms replay")
    assert 0.0 <= late < 0.05 * span_ms, play_log
    sent = _publish_times(tmp_path / f"replay_{rate:g}")
    for topic in TOPICS:
        assert [m[1] for m in replay[topic]] == [m[1] for m in original[topic]], topic
        t_rec = np.array([m[0] for m in original[topic]], dtype=np.int64)
        # the replay's DDS source timestamps (when the player wrote each message, stamped by its writer), not
        # the times the recorder received them: a recorder descheduled on a busy machine stretched its reception
        # times (a CI run under load: slope 1.30 at rate 2 while the player was punctual by its own clock)
        t_play = np.array(sent[topic], dtype=np.int64)
        slope, resid, p90 = envelope_timing(t_rec, t_play, rate)
        print(f"rate {rate}: {topic}: envelope slope*rate={slope:.4f} residual={resid * 1e3:.3f} ms "
              f"p90 jitter={p90 * 1e3:.3f} ms span rec={np.ptp(t_rec) / 1e9:.3f} s play={np.ptp(t_play) / 1e9:.3f} s")
        # The receiving side checks the schedule itself (a player that took its due times from the
        # wrong rate would still be punctual by its own clock): playing at the wrong rate gives
        # slope 2.0 or 0.5 and a timeline error of 750 ms, far outside these bounds.
        assert abs(slope - 1.0) < 0.05, slope
        assert resid < 0.005, resid  # the promptly delivered messages within 5 ms of the line


def _publish_times(bag: Path) -> dict[str, list[int]]:
    """topic -> the messages' publish times (the writer's DDS source timestamp, which record stores as MCAP
    publish_time) in the order read_all gives them (bag time)."""
    from mcap.reader import make_reader

    rows: dict[str, list[tuple[int, int]]] = {}
    (path,) = bag.glob("*.mcap")
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            rows.setdefault(channel.topic, []).append((message.log_time, message.publish_time))
    return {t: [p for _, p in sorted(r)] for t, r in rows.items()}


def _sigkill_loses_at_most_about_one_second(procs, tmp_path):
    from fullperc_eval.bag.errors import BagError
    from fullperc_eval.bag.metadata import load_metadata
    from fullperc_eval.bag.reader import BagReader
    from fullperc_eval.bag.recover import reindex

    bag = tmp_path / "killed"
    n = 4000  # at most 4 s at 1 kHz; the recorder is killed after 2 s, and the publisher stopped then (stop_file)
    rec = procs.start(record_cmd(bag, "--topics", *TOPICS), name="record")
    # the killed recorder never acknowledges: DDS would keep it matched until its lease ran out (~20 s) and the
    # publisher would wait for its acks that long; nothing here needs them
    stop_file = tmp_path / "stop_publishing"
    pub = start_publisher(procs, tmp_path / "pub.json", n=n, ack_timeout=0.5, stop_file=stop_file)

    def flushed_count() -> int:  # the periodic metadata.yaml shows how much is on disk
        try:
            return load_metadata(bag)["message_count"]
        except (BagError, KeyError):
            return 0

    wait_for(lambda: flushed_count() > 0, timeout=120, what="metadata.yaml refreshed while recording")
    # Kill at a moment set by the publisher's progress (seq n/2), unrelated to the flush phase.
    wait_for(lambda: "HALF" in Procs.log(pub), timeout=120, what="publisher half way")
    t_kill = time.time_ns()
    os.killpg(rec.pid, signal.SIGKILL)
    rec.wait(10)
    # what the publisher sends after the kill goes nowhere: it stops and logs every stamp it published (those
    # before the kill among them)
    stop_file.touch()
    wait_done(pub)
    stamps = np.array(json.loads((tmp_path / "pub.json").read_text())["stamps"], dtype=np.int64)

    # Incomplete bag: a clear error first, then reindex makes it readable by third-party readers.
    with pytest.raises(BagError, match="reindex"):
        BagReader(bag).open()
    meta, reports = reindex(bag)
    assert reports[0].recovered and (bag / "killed_0.mcap.orig").exists()
    data = read_all(bag)
    published_before_kill = int(np.sum(stamps < t_kill))
    for topic in TOPICS:
        # the i-th recovered message is exactly published message i: a gap-free prefix
        for seq, (_, _, msg) in enumerate(data[topic]):
            check_decoded(topic, msg, seq, int(stamps[seq]))
        k = len(data[topic])
        lost_s = (t_kill - stamps[k - 1]) / 1e9  # publish time of the last recovered one -> kill
        missing = published_before_kill - k
        print(f"{topic}: recovered {k}, published before kill {published_before_kill}, missing {missing} "
              f"({lost_s:.3f} s)")
        assert entry_count(meta, topic) == k
        assert lost_s <= 1.0, f"{topic}: lost {lost_s:.3f} s of messages"


def entry_count(meta: dict, topic: str) -> int:
    for e in meta["rosbag2_bagfile_information"]["topics_with_message_count"]:
        if e["topic_metadata"]["name"] == topic:
            return e["message_count"]
    raise KeyError(topic)


def _small_bag(path: Path, n: int = 40, dt_ns: int = 10_000_000, storage: str = "mcap") -> Path:
    """A generated two-topic bag (ROS-free writer): /gen/a PoseStamped, /gen/b String, every dt."""
    from fullperc_eval.bag.writer import BagWriter

    with BagWriter(path, storage=storage) as w:
        T = w.typestore.types
        w.add_topic("/gen/a", "geometry_msgs/msg/PoseStamped")
        w.add_topic("/gen/b", "std_msgs/msg/String")
        t0 = 1_700_000_000_000_000_000
        for i in range(n):
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=i, nanosec=0), frame_id="base")
            pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(i), y=0.0, z=0.0),
                                               orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                             w=1.0))
            w.write_msg("/gen/a", t0 + i * dt_ns, T["geometry_msgs/msg/PoseStamped"](header=hdr, pose=pose))
            w.write_msg("/gen/b", t0 + i * dt_ns + dt_ns // 2, T["std_msgs/msg/String"](data=f"msg {i}" * (i % 3)))
    return path


def _play_topics_and_start_offset(procs, tmp_path, storage):
    """--topics selects, --start-offset skips the first 0.2 s; bytes unchanged (both storages)."""
    bag = _small_bag(tmp_path / "gen", storage=storage)
    src = read_all(bag)
    out, _ = run_play(procs, bag, tmp_path / "out", "--topics", "/gen/a", "--start-offset", "0.2",
                      topics=("/gen/a", "/gen/b"))
    assert list(out) == ["/gen/a"]
    t0 = src["/gen/a"][0][0]
    want = [m[1] for m in src["/gen/a"] if m[0] >= t0 + 200_000_000]
    assert len(want) == 20 and [m[1] for m in out["/gen/a"]] == want


def _play_loop_and_clock(procs, tmp_path):
    """--loop repeats the bag; --clock publishes bag time on /clock within the bag's time range."""
    from fullperc_eval.bag.errors import BagError
    from fullperc_eval.bag.metadata import load_metadata

    bag = _small_bag(tmp_path / "gen", n=20, dt_ns=5_000_000)
    src = read_all(bag)
    out = tmp_path / "out"
    rec = procs.start(record_cmd(out, "--topics", "/gen/a", "/clock"), name="record_loop")
    play = procs.start([installed_exe("fullperc_eval", "play"), str(bag), "--loop", "--clock", "100",
                        "--topics", "/gen/a", "--wait-for-subscribers", "60"], name="play_loop")

    def count(topic: str) -> int:
        try:
            info = load_metadata(out)
        except BagError:
            return 0
        return next((e["message_count"] for e in info["topics_with_message_count"]
                     if e["topic_metadata"]["name"] == topic), 0)

    wait_for(lambda: count("/gen/a") >= 3 * 20 and count("/clock") >= 5, timeout=120, what="3 loops recorded")
    stop_ok(procs, play)
    stop_ok(procs, rec, signal.SIGTERM)  # SIGTERM closes the bag as cleanly as SIGINT
    got = read_all(out)
    pattern = [m[1] for m in src["/gen/a"]]
    a = [m[1] for m in got["/gen/a"]]
    assert a[:60] == pattern * 3
    # /clock carries bag time (2023 here), not wall time; it runs from the bag start and jumps
    # back at each loop. The playback clock is wall-driven, so a player delayed by load may run
    # ahead of its last message: the upper bound allows 1 s of that.
    bag_start, bag_end = src["/gen/a"][0][0], src["/gen/a"][-1][0]
    clock = np.array([m[2].clock.sec * 10**9 + m[2].clock.nanosec for m in got["/clock"]], dtype=np.int64)
    assert np.all((clock >= bag_start) & (clock <= bag_end + 1_000_000_000)), (bag_start, bag_end, clock[:5])
    assert np.any(np.diff(clock) < 0) and np.sum(np.diff(clock) > 0) > np.sum(np.diff(clock) < 0)


def _record_all_with_exclude_into_sqlite3(procs, tmp_path, take):
    """--all (graph polling) minus --exclude-regex, sqlite3 storage: the played bag, byte for byte, whichever way
    the recorder takes its messages (``--take``; poll, the default, never runs an executor callback)."""
    import yaml

    bag = _small_bag(tmp_path / "gen")
    src = read_all(bag)
    out = tmp_path / "out"
    rec = procs.start(record_cmd(out, "-s", "sqlite3", "--all", "--exclude-regex", "^/(rosout|parameter_events)$",
                                 "--take", take), name="record_all")
    play = procs.start([installed_exe("fullperc_eval", "play"), str(bag), "--wait-for-subscribers", "60"],
                       name="play_all")
    wait_for(lambda: play.poll() is not None, timeout=120, what="play to finish")
    assert play.returncode == 0, Procs.log(play)
    stop_ok(procs, rec)
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "sqlite3" and info["relative_file_paths"] == ["out_0.db3"]
    got = read_all(out)
    assert sorted(got) == ["/gen/a", "/gen/b"]
    n = sum(len(v) for v in got.values())
    m = re.search(r"; (\d+) through executor callbacks \(--take (\w+)\)", Procs.log(rec))
    assert m and m.group(2) == take, Procs.log(rec)
    assert (int(m.group(1)) == 0) if take == "poll" else (int(m.group(1)) == n if take == "executor" else
                                                           0 < int(m.group(1)) <= n)
    for topic in got:
        assert len(got[topic]) == len(src[topic])
        for (_, played, _), (_, orig, _) in zip(got[topic], src[topic], strict=True):
            # Fast DDS pads a serialized payload to a multiple of 4 bytes on the wire; rosbags'
            # CDR for the generated strings is not padded. Everything else is byte-identical.
            assert played[:len(orig)] == orig and len(played) == len(orig) + (-len(orig)) % 4


def _record_skips_unknown_type_with_clear_error(procs, tmp_path):
    """A topic whose type the recorder cannot import is reported and skipped; the others are kept."""
    env = dict(procs.env)
    # Hide fullperc_msgs from the recorder only (Python path and ament index).
    env["PYTHONPATH"] = os.pathsep.join(p for p in env.get("PYTHONPATH", "").split(os.pathsep)
                                        if "fullperc_msgs" not in p)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
                                               if "fullperc_msgs" not in p)
    probe = subprocess.run([sys.executable, "-c", "import fullperc_msgs.msg"], env=env, capture_output=True)
    if probe.returncode == 0:
        pytest.skip("cannot hide fullperc_msgs from a child process in this environment")
    bag = tmp_path / "partial"
    rec = procs.start(record_cmd(bag, "--topics", *TOPICS), name="record", env=env)
    pub = start_publisher(procs, tmp_path / "pub.json", n=200)
    # the publisher waits for subscribers on all three topics; the quality topic never gets one
    wait_for(lambda: "fullperc_msgs/msg/TrackingQuality" in Procs.log(rec), timeout=60, what="recorder error")
    procs.stop(pub)
    stop_ok(procs, rec)
    assert "not recording /fp_test/quality" in Procs.log(rec)
    shutil.rmtree(bag, ignore_errors=True)


# ------------------------------------------------------------------ the other system tests, side by side
# (each in a domain of its own, started together when the first of them runs: after the replays above)

STORAGES = ["mcap", "sqlite3"]
TAKES = ["poll", "callback", "executor"]
scenarios = side_by_side_fixture(
    _sigkill_loses_at_most_about_one_second, _play_loop_and_clock, _record_skips_unknown_type_with_clear_error,
    **{f"test_play_topics_and_start_offset[{x}]": (_play_topics_and_start_offset, {"storage": x}) for x in STORAGES},
    **{f"test_record_all_with_exclude_into_sqlite3[{x}]": (_record_all_with_exclude_into_sqlite3, {"take": x})
       for x in TAKES})


@pytest.mark.system
def test_sigkill_loses_at_most_about_one_second(scenarios, request):
    scenarios.result(request.node.name)


@pytest.mark.system
@pytest.mark.parametrize("storage", STORAGES)
def test_play_topics_and_start_offset(scenarios, request, storage):
    scenarios.result(request.node.name)


@pytest.mark.system
def test_play_loop_and_clock(scenarios, request):
    scenarios.result(request.node.name)


@pytest.mark.system
@pytest.mark.parametrize("take", TAKES)
def test_record_all_with_exclude_into_sqlite3(scenarios, request, take):
    scenarios.result(request.node.name)


@pytest.mark.system
def test_record_skips_unknown_type_with_clear_error(scenarios, request):
    scenarios.result(request.node.name)


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "publish":
    sys.exit(publisher_main(sys.argv[2:]))
