"""replay(on_time=True) (evaluation/on_time.py): a pose sample the recorder got more than min(history, reorder window)
behind the others is fed where it would have been on time; every other message keeps the bag order; the idle flush
follows the stamps."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fullperc_eval.bag.reader import BagReader
from fullperc_eval.bag.writer import BagWriter
from fullperc_eval.evaluation.on_time import on_time_order

ROOT = Path(__file__).resolve().parents[3]
BAG = ROOT / "bags" / "paper" / "P-G-B"
MS = 1_000_000


class Msg(NamedTuple):
    topic: str
    t_ns: int


def test_a_sample_later_than_the_bound_moves_after_the_last_earlier_stamp():
    bag = [Msg("/a", 0), Msg("/j", 5), Msg("/b", 10), Msg("/a", 300), Msg("/b", 310), Msg("/j", 315), Msg("/a", 320),
           Msg("/b", 20), Msg("/a", 330)]      # /b 20 came 300 ms late; /j (joint states) is not a stream
    out, moved = on_time_order(bag, {"/a", "/b"}, 200)
    assert moved == 1
    assert out == [Msg("/a", 0), Msg("/j", 5), Msg("/b", 10), Msg("/b", 20), Msg("/a", 300), Msg("/b", 310),
                   Msg("/j", 315), Msg("/a", 320), Msg("/a", 330)]


def test_within_the_bound_and_equal_stamps_keep_the_bag_order():
    bag = [Msg("/a", 0), Msg("/a", 100), Msg("/b", 0), Msg("/b", 100), Msg("/a", 250), Msg("/b", 50)]
    out, moved = on_time_order(bag, {"/a", "/b"}, 200)   # /b 0 and 50 are 100 and 200 behind: not beyond the bound
    assert (out, moved) == (bag, 0)
    out, moved = on_time_order(bag, {"/a", "/b"}, 199)   # with a tighter bound, 50 (200 behind 250) moves
    assert moved == 1 and out == [Msg("/a", 0), Msg("/a", 100), Msg("/b", 0), Msg("/b", 50), Msg("/b", 100),
                                  Msg("/a", 250)]


def test_several_late_samples_keep_their_order_among_themselves():
    bag = [Msg("/a", t) for t in (0, 10, 20, 400, 410)] + [Msg("/b", t) for t in (5, 15, 25)] + [Msg("/a", 420)]
    out, moved = on_time_order(bag, {"/a", "/b"}, 200)
    assert moved == 3
    assert [m.t_ns for m in out] == [0, 5, 10, 15, 20, 25, 400, 410, 420]


def _config():
    """The default configuration with the raw OMC and CBKF only: the order is what is tested, not the filters."""
    import dataclasses

    from fullperc_fusion.fusion_config import load_fusion_config

    return dataclasses.replace(load_fusion_config()[0], filters=("cbkf", "omc"))


def _delayed_copy(dst: Path, topic: str, t0_ns: int, span_ns: int, delay_ns: int) -> int:
    """``BAG`` with the receive times of ``topic``'s samples stamped in [t0, t0 + span) put ``delay_ns`` later, as a
    DDS repair at the recorder does (the order of the bag follows the receive times); how many were delayed."""
    n = 0
    with BagReader(BAG) as r, BagWriter(dst) as w:
        for name, info in r.topics.items():
            w.add_topic(name, info.msgtype)
        for m in r.messages(list(r.topics)):
            t = m.timestamp
            if m.topic == topic:
                msg = r.deserialize(m.data, m.msgtype)
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                if t0_ns <= stamp < t0_ns + span_ns:
                    t += delay_ns
                    n += 1
            w.write(m.topic, t, m.data)
    shutil.copy(BAG / "calibration.yaml", dst)
    return n


def _stalled_copy(dst: Path, t0_ns: int, stall_ns: int, lag_ns: int, in_flight_ns: int) -> None:
    """``BAG`` as a recorder that stalled from receive time t0 for ``stall_ns`` records it: everything received in the
    stall arrives in one burst at its end, in stamp order, the target's OMC samples ``lag_ns`` behind the rest (their
    topic's delivery lagged), and so do the target's OMC samples stamped ``in_flight_ns`` before t0 (in flight)."""
    with BagReader(BAG) as r, BagWriter(dst) as w:
        for name, info in r.topics.items():
            w.add_topic(name, info.msgtype)
        rows = []
        for m in r.messages(list(r.topics)):
            t = key = m.timestamp
            if m.topic.endswith("/pose"):
                msg = r.deserialize(m.data, m.msgtype)
                key = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            omc = m.topic == "/omc/tool/pose"
            if t0_ns <= t < t0_ns + stall_ns or (omc and t < t0_ns and key >= t0_ns - in_flight_ns):
                t = t0_ns + stall_ns + (key + (lag_ns if omc else 0) - t0_ns + 200 * MS) // 1000
            rows.append((m.topic, t, m.data))
        for topic, t, data in rows:
            w.write(topic, t, data)
    shutil.copy(BAG / "calibration.yaml", dst)


def _same(a, b) -> None:
    for f in a.outputs:
        assert np.array_equal(a.outputs[f]["t_ns"], b.outputs[f]["t_ns"]), f
        assert np.array_equal(a.outputs[f]["p"], b.outputs[f]["p"]), f


def test_samples_the_recorder_got_late_are_fused_on_time(tmp_path):
    """The committed bag replays on time as by default (nothing moves). A copy with 50 ms of the target's OMC samples,
    10 s into the task, received 3 s late: the bag-order replay drops them as late (its outputs miss their stamps);
    on time, the copy's replay equals the original's output for output."""
    from fullperc_eval.evaluation.replay import replay

    with BagReader(BAG) as r:
        start = r.start_time
    bag = tmp_path / "P-G-B"
    n = _delayed_copy(bag, "/omc/tool/pose", start + 10_000 * MS, 50 * MS, 3_000 * MS)
    assert n == 6   # 50 ms of a 120 Hz stream
    cfg = _config()
    orig = replay(BAG, cfg, progress=False, on_time=True)
    assert not [w for w in orig.warnings if w.startswith("on time")]
    _same(replay(BAG, cfg, progress=False), orig)
    late = replay(bag, cfg, progress=False)
    assert any("late" in w for w in late.warnings), late.warnings
    assert len(late.outputs["omc"]["t_ns"]) == len(orig.outputs["omc"]["t_ns"]) - n
    fixed = replay(bag, cfg, progress=False, on_time=True)
    assert [w for w in fixed.warnings if w.startswith("on time")] == [
        f"on time: {n} samples the recorder got over 0.058 s behind newer ones fed where they would have been on time"]
    _same(orig, fixed)


def test_a_recorder_stall_does_not_flush_the_on_time_replay(tmp_path):
    """The recorder stalls 0.8 s, 20 s into the task (the Vega sees the tool then), and delivers the stall's messages
    in one burst, the OMC's 20 ms behind the Vega's. The bag-order replay sees a receive gap longer than ``idle_flush``
    (0.5 s), flushes, and drops the OMC samples stamped before the flushed ones as late; on time, the idle flush
    follows the stamps, which did not pause, and the copy replays as the original output for output. (With the flush
    on the receive times, the on-time replay still drops one.)"""
    from fullperc_eval.evaluation.replay import replay

    with BagReader(BAG) as r:
        start = r.start_time
    bag = tmp_path / "P-G-B"
    _stalled_copy(bag, start + 20_000 * MS, 800 * MS, 20 * MS, 40 * MS)
    cfg = _config()
    late = replay(bag, cfg, progress=False)
    assert any("late" in w for w in late.warnings), late.warnings
    fixed = replay(bag, cfg, progress=False, on_time=True)
    assert not any("late" in w for w in fixed.warnings), fixed.warnings
    _same(replay(BAG, cfg, progress=False), fixed)
