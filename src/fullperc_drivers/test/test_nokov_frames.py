"""FramePipeline and body validity: frame accounting, sentinels, units and the stamp modes."""

import math

import numpy as np
import pytest

from fullperc_drivers.clock_sync import ClockSync
from fullperc_drivers.nokov.frames import FramePipeline, RawBody, RawFrame, body_validity

MS = 1_000_000


def _body(pos=(1000.0, -2000.0, 500.5), q=(0.0, 0.0, 0.0, 1.0), flag=True, err=0.3):
    return RawBody(7, "tool", pos, q, err, flag, 5)


def _frame(fno, dev_ts=10**12, lat=0.004, recv=None, bodies=None):
    recv = recv if recv is not None else dev_ts + 4 * MS + 100_000
    return RawFrame(fno, dev_ts, lat, recv, bodies if bodies is not None else [_body()])


@pytest.mark.parametrize("pos", [(999999.9999, 999999.9999, 999999.9999), (99999.0, 0, 0), (0, -9999999.999999, 0),
                                 (float("nan"), 0, 0), (0, float("inf"), 0)])
def test_sentinels_and_non_finite_positions_are_not_tracked(pos):
    ok, why = body_validity(_body(pos=pos))
    assert not ok and why in ("sentinel", "non-finite")


@pytest.mark.parametrize("q, ok", [((0, 0, 0, 0), False), ((0, 0, 0, 2.0), False), ((0.6, 0, 0, 0.8), True),
                                   ((0.6, 0, 0, 0.8001), True)])
def test_quaternion_norm_check(q, ok):
    assert body_validity(_body(q=q))[0] is ok


def test_device_flag_and_real_positions():
    assert body_validity(_body(flag=False)) == (False, "device flag")
    assert body_validity(_body(pos=(-15000.0, 20000.0, 3000.0))) == (True, "")  # 20 m room is still real


def test_units_and_normalised_quaternion():
    f = FramePipeline().process(_frame(1, bodies=[_body(q=(0.6, 0, 0, 0.8001))]))
    b = f.bodies[0]
    np.testing.assert_allclose(b.position_m, [1.0, -2.0, 0.5005])
    assert b.mean_error_m == pytest.approx(0.3e-3) and b.markers == 5
    assert np.linalg.norm(b.quat_xyzw) == pytest.approx(1.0, abs=1e-15)
    lost = FramePipeline().process(_frame(1, bodies=[_body(pos=(999999.9999,) * 3)])).bodies[0]
    assert not lost.tracked and lost.position_m is None and lost.quat_xyzw is None and lost.reason == "sentinel"


def test_frame_gaps_duplicates_restarts_and_wraparound():
    p = FramePipeline(restart_gap=1000)
    t = 10**12
    seq = [5, 6, 9, 9, 8, 10, 4_000_000, 50, 51]  # gap of 2; dup; old; restart far back; ...
    out = [p.process(_frame(n, dev_ts=t + i * MS, recv=t + i * MS + 5 * MS)) for i, n in enumerate(seq)]
    assert [o is not None for o in out] == [True, True, True, False, False, True, True, True, True]
    c = p.counters
    assert (c.dropped, c.duplicates, c.restarts) == (2 + 4_000_000 - 11, 2, 1)
    w = FramePipeline()
    assert w.process(_frame(2**32 - 1, dev_ts=t, recv=t + 5 * MS)) is not None
    assert w.process(_frame(1, dev_ts=t + MS, recv=t + 6 * MS)) is not None  # wrapped: 0 was dropped
    assert w.counters.dropped == 1 and w.counters.restarts == 0


def test_capture_vs_send_timestamp_semantics():
    offset, lat, delay = 123 * MS, 0.004, 50_000
    cap_host = 10**15
    cap_dev = cap_host - offset
    recv = cap_host + int(lat * 1e9) + delay
    # device stamps capture time
    f = FramePipeline(ClockSync()).process(_frame(1, dev_ts=cap_dev, lat=lat, recv=recv))
    assert f.stamp_ns == cap_host + delay
    # device stamps send time
    f = FramePipeline(ClockSync(), device_stamp="send").process(
        _frame(1, dev_ts=cap_dev + int(lat * 1e9), lat=lat, recv=recv))
    assert f.stamp_ns == cap_host + delay


def test_receive_mode_no_device_time_and_latency_switches():
    recv = 10**15
    assert FramePipeline(stamp_source="receive").process(_frame(1, lat=0.004, recv=recv)).stamp_ns == recv - 4 * MS
    p = FramePipeline()
    assert p.process(_frame(1, dev_ts=0, lat=0.004, recv=recv)).stamp_ns == recv - 4 * MS
    assert p.counters.no_device_time == 1
    p = FramePipeline(stamp_source="receive", latency_compensation=False)
    assert p.process(_frame(1, lat=0.004, recv=recv)).stamp_ns == recv
    for bad in (float("nan"), -0.1, 5.0):
        p = FramePipeline(stamp_source="receive")
        assert p.process(_frame(1, lat=bad, recv=recv)).stamp_ns == recv
        assert p.counters.bad_latency == 1


def test_stamps_never_go_backwards_or_after_arrival():
    p = FramePipeline()
    t = 10**15
    f1 = p.process(_frame(1, dev_ts=t, lat=0.0, recv=t + 2 * MS))
    # host clock stepped back by 1 s between frames: the mapped stamp would go backwards -> dropped, counted
    f2 = p.process(_frame(2, dev_ts=t + 10 * MS, lat=0.0, recv=t + 2 * MS - 10**9 + 10 * MS))
    assert f1 is not None and f2 is None and p.counters.stamp_not_increasing == 1
    assert all(math.isfinite(x) for x in f1.bodies[0].position_m)
    assert f1.stamp_ns <= f1.recv_ns


@pytest.mark.parametrize("kw", [dict(device_stamp="middle"), dict(stamp_source="gps")])
def test_bad_modes_rejected(kw):
    with pytest.raises(ValueError):
        FramePipeline(**kw)
