"""ApproxSync: pairing within slop, strict stamp order, no lone sample dropped, bad timing defined."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync

MS = 1_000_000


def _emitted(items):
    """(stream, stamp) of every sample in the emitted items."""
    out = []
    for it in items:
        if it.glob is not None:
            out.append((GLOBAL, it.glob.t_ns))
        if it.local is not None:
            out.append((LOCAL, it.local.t_ns))
    return out


def test_pairs_within_slop_and_lone_samples_go_alone():
    s = ApproxSync(slop_ns=4 * MS, delay_ns=0)
    for t in (0, 10, 20, 30):
        s.push(GLOBAL, t * MS, f"g{t}")
    for t in (2, 25):       # 2 pairs with 0; 25 is 5 ms from 20 and 30: no partner within 4 ms
        s.push(LOCAL, t * MS, f"l{t}")
    items = s.flush()
    kinds = [(it.glob.t_ns // MS if it.glob else None, it.local.t_ns // MS if it.local else None) for it in items]
    assert kinds == [(0, 2), (10, None), (20, None), (None, 25), (30, None)]
    assert items[0].t_ns == 2 * MS                 # processing stamp = newer of the pair
    assert items[0].glob.payload == "g0" and items[0].local.payload == "l2"
    assert s.counts["pairs"] == 1 and s.counts["global_alone"] == 3 and s.counts["local_alone"] == 1


def test_slop_is_strict():
    s = ApproxSync(slop_ns=4 * MS, delay_ns=0)
    s.push(GLOBAL, 0, None)
    s.push(LOCAL, 4 * MS, None)
    assert [(it.glob is not None, it.local is not None) for it in s.flush()] == [(True, False), (False, True)]


def test_nearest_partner_wins_over_earlier_sample():
    # L at 4 is within slop of G at 0 and G at 6, but closer to G at 6
    s = ApproxSync(slop_ns=5 * MS, delay_ns=0)
    s.push(GLOBAL, 0, None)
    s.push(GLOBAL, 6 * MS, None)
    s.push(LOCAL, 4 * MS, None)
    items = s.flush()
    assert [(it.glob.t_ns if it.glob else None, it.local.t_ns if it.local else None) for it in items] == \
        [(0, None), (6 * MS, 4 * MS)]


def test_nothing_is_emitted_before_the_partner_window_and_delay_have_passed():
    slop, delay = 4 * MS, 20 * MS
    s = ApproxSync(slop, delay)
    s.push(GLOBAL, 100 * MS, "g")
    assert s.poll(100 * MS + 2 * slop + delay - 1) == []
    # a partner arriving late (stamp 103 ms, arrival after the first poll) is still paired
    s.push(LOCAL, 103 * MS, "l")
    items = s.poll(100 * MS + 2 * slop + delay)
    assert len(items) == 1 and items[0].glob.payload == "g" and items[0].local.payload == "l"


def test_lone_global_is_processed_when_the_local_stream_is_silent():
    # watermark mode: the global stream alone drives time, so it is never held back forever
    s = ApproxSync(4 * MS, 20 * MS)
    out = []
    for k in range(100):
        s.push(GLOBAL, k * 8 * MS, k)
        out += s.poll()
    assert [it.glob.payload for it in out] == list(range(len(out)))
    assert len(out) >= 100 - (2 * 4 + 20) // 8 - 1
    out += s.flush()
    assert len(out) == 100 and all(it.local is None for it in out)


def test_out_of_order_within_the_delay_is_sorted():
    s = ApproxSync(1 * MS, 30 * MS)
    for t in (0, 20, 10, 30, 5):
        assert s.push(GLOBAL, t * MS, t) == "ok"
    items = s.poll(40 * MS)   # final: t <= 40 - 2 - 30 = 8 ms
    assert [it.glob.payload for it in items] == [0, 5]
    assert [it.glob.payload for it in s.flush()] == [10, 20, 30]


def test_late_samples_are_dropped_and_counted():
    s = ApproxSync(1 * MS, 0)
    s.push(GLOBAL, 10 * MS, None)
    s.push(GLOBAL, 20 * MS, None)
    assert len(s.poll(30 * MS)) == 2
    assert s.push(GLOBAL, 15 * MS, None) == "late"        # time went backwards past the horizon
    assert s.push(LOCAL, 19 * MS, None) == "late"
    assert s.counts["global_late"] == 1 and s.counts["local_late"] == 1
    assert s.push(LOCAL, 20 * MS, None) == "ok"           # equal to the horizon, other stream: fine
    assert s.flush()[0].t_ns == 20 * MS


def test_duplicate_stamps():
    s = ApproxSync(1 * MS, 0)
    assert s.push(GLOBAL, 10 * MS, "first") == "ok"
    assert s.push(GLOBAL, 10 * MS, "second") == "duplicate"      # pending duplicate
    assert s.push(LOCAL, 10 * MS, "local") == "ok"               # same stamp, other stream: pairs
    items = s.flush()
    assert len(items) == 1 and items[0].glob.payload == "first" and items[0].local.payload == "local"
    assert s.push(GLOBAL, 10 * MS, "third") == "duplicate"       # duplicate of an emitted one
    assert s.counts["global_duplicate"] == 2


def test_overflow_forces_samples_out_instead_of_dropping():
    s = ApproxSync(1 * MS, 10**12, max_pending=5)   # a delay that never passes
    for k in range(8):
        s.push(GLOBAL, k * MS, k)
    out = s.poll(8 * MS)
    assert [it.glob.payload for it in out] == [0, 1, 2]
    assert s.counts["forced_by_overflow"] == 3
    assert [it.glob.payload for it in s.flush()] == [3, 4, 5, 6, 7]


def test_realistic_rates_with_occlusion():
    # OMC 120 Hz, OTS 60 Hz offset by 3 ms and visible only between 1 s and 2 s
    s = ApproxSync(4 * MS, 50 * MS)
    rng = np.random.default_rng(0)
    g = [int(k * 1e9 / 120) for k in range(360)]
    loc = [int(3 * MS + k * 1e9 / 60) for k in range(180)]
    loc = [t for t in loc if 1e9 <= t < 2e9]
    ev = [(t + int(rng.integers(0, 10 * MS)), GLOBAL, t) for t in g] + \
         [(t + int(rng.integers(0, 30 * MS)), LOCAL, t) for t in loc]   # arrival jitter
    out = []
    for _, stream, t in sorted(ev):
        assert s.push(stream, t) == "ok"
        out += s.poll()
    out += s.flush()
    assert sorted(_emitted(out)) == sorted([(GLOBAL, t) for t in g] + [(LOCAL, t) for t in loc])
    assert s.counts["pairs"] == len(loc)           # every OTS sample found its OMC partner
    assert all(it.glob is not None for it in out)
    stamps = [it.t_ns for it in out]
    assert stamps == sorted(stamps)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([GLOBAL, LOCAL]), st.integers(0, 200)), min_size=1, max_size=60),
       st.integers(0, 20), st.integers(0, 40))
def test_every_sample_exactly_once_in_stamp_order(samples, slop, delay):
    """Property: whatever the arrival order, nothing accepted is lost, nothing emitted twice,
    processing stamps never decrease, pairs are within slop."""
    s = ApproxSync(slop, delay)
    accepted, out = [], []
    for stream, t in samples:
        if s.push(stream, t) == "ok":
            accepted.append((stream, t))
        out += s.poll()
    out += s.flush()
    assert sorted(_emitted(out)) == sorted(accepted)
    stamps = [it.t_ns for it in out]
    assert stamps == sorted(stamps)
    for it in out:
        if it.glob is not None and it.local is not None:
            assert abs(it.glob.t_ns - it.local.t_ns) < slop
        for x in (it.glob, it.local):
            if x is not None:
                assert x.t_ns <= it.t_ns


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 60), max_size=25, unique=True), st.lists(st.integers(0, 60), max_size=25, unique=True),
       st.integers(0, 8))
def test_pair_of_two_streams_equals_the_synchronizers_flush(g, loc, slop):
    """ApproxSync.pair's two-stream path (read positions, no synchronizer built) makes the same items as pushing
    the samples into an ApproxSync and flushing it -- the rules of the live path -- on stamps dense enough for
    ties, competitors and equal stamps across the streams."""
    from fullperc_fusion.pipeline.synchronizer import Sample

    glob = [Sample(t * MS, ("g", t)) for t in sorted(g)]
    local = [Sample(t * MS, ("l", t)) for t in sorted(loc)]
    sync = ApproxSync(slop_ns=slop * MS, delay_ns=0, max_pending=100)
    for s in glob:
        sync.push(GLOBAL, s.t_ns, s.payload)
    for s in local:
        sync.push(LOCAL, s.t_ns, s.payload)
    assert ApproxSync.pair(glob, local, slop * MS) == sync.flush()
