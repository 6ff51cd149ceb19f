"""The stamp rules (pipeline/stamp_rules.py): duplicate, late and timeline restart, one implementation for the
synchronizer (ordered processing) and fusion on arrival."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.stamp_rules import (
    DUPLICATE,
    LATE,
    LATE_SOURCE_SPAN_NS,
    OK,
    RESTART,
    StampRules,
)
from fullperc_fusion.pipeline.synchronizer import ApproxSync, Sample, SyncItem

MS = 1_000_000
S = 1000 * MS
NAMES = ("global", "local", "atracsys")


def _take(r: StampRules, stream: int, t: int) -> str:
    v = r.check(stream, t)
    if v in (OK, RESTART):
        r.admit(stream, t)
    return v


def test_duplicate_is_a_stamp_its_stream_has_pending_or_last_released():
    r = StampRules(NAMES)
    assert _take(r, 0, 10) == OK and _take(r, 1, 10) == OK, "equal stamps on two streams pair, no duplicate"
    assert r.check(0, 10) == DUPLICATE
    r.release(SyncItem(10, Sample(10, None), Sample(10, None)))
    assert r.check(0, 10) == DUPLICATE and r.check(1, 10) == DUPLICATE, "the last released one"
    assert r.check(2, 10) == OK


def test_late_is_before_the_horizon_and_a_further_sources_item_never_moves_it_back():
    r = StampRules(NAMES)
    for t in (100, 104, 98):
        _take(r, 0 if t != 98 else 2, t)
    r.release(SyncItem(104, Sample(100, None), None))
    assert r.horizon_ns == 104
    r.release(SyncItem(98, None, Sample(98, None), source=1))   # the further source's lagged item
    assert r.horizon_ns == 104
    assert r.check(1, 103) == LATE and r.check(1, 104) == OK
    assert "processed horizon 104 ns" in r.message(LATE, "OTS tool 'tool'", 103)


def test_restart_only_with_a_history_and_after_a_run_spanning_it():
    """Stamps that go back against their own stream's: a restart once the run spans more than the history."""
    hist = 200 * MS
    for rules, restarts in ((StampRules(NAMES), False), (StampRules(NAMES, history_ns=hist), True)):
        _take(rules, 0, 3600 * S)   # one stamp an hour ahead
        verdicts = [_take(rules, 0, k * 10 * MS) if rules.check(0, k * 10 * MS) != RESTART else RESTART
                    for k in range(1, 40)]
        assert (RESTART in verdicts) is restarts
        if restarts:
            first = verdicts.index(RESTART)
            assert (first - 1) * 10 * MS <= hist < (first + 1) * 10 * MS


def test_a_source_late_but_in_order_restarts_only_after_the_long_span():
    """A source 2 s behind, in its own order: no restart for a second of its stamps; after the global source ran an
    hour ahead and fell silent, a restart once its run spans LATE_SOURCE_SPAN_NS (not the history)."""
    r = StampRules(NAMES, history_ns=200 * MS)
    for k in range(300):
        _take(r, 0, S + k * 10 * MS)                          # the global source on time, 3 s
    assert RESTART not in [r.check(1, S + k * 10 * MS) for k in range(100)]
    r = StampRules(NAMES, history_ns=200 * MS)
    _take(r, 0, 3600 * S)
    got = [r.check(1, S + k * 10 * MS) for k in range(int(LATE_SOURCE_SPAN_NS // (10 * MS)) + 5)]
    assert got.index(RESTART) == LATE_SOURCE_SPAN_NS // (10 * MS) + 1


def test_restart_forgets_the_timeline():
    r = StampRules(NAMES, history_ns=200 * MS)
    _take(r, 0, 5 * S)
    r.release(SyncItem(5 * S, Sample(5 * S, None), None))
    r.restart()
    assert (r.horizon_ns, r.newest_ns, r.released) == (None, None, [None] * 3)
    assert r.check(0, 5 * S) == OK and r.check(0, S) == OK


def test_the_synchronizer_and_fusion_on_arrival_apply_the_same_rules():
    """The same target samples into both pipelines: the same samples are dropped as duplicate (a stamp still
    pending: in the synchronizer, in the history) and as late (before the items already final)."""
    eye = np.eye(4)
    stamps = [k * 10 * MS for k in range(1, 60)]
    bad = [stamps[58], stamps[57], 200 * MS, 205 * MS]   # two duplicates of pending stamps, two late ones
    counts = []
    for P in (TargetPipeline, ArrivalPipeline):
        pipe = P(TargetConfig(filters=("cbkf",), history_ns=60 * MS, delay_ns=52 * MS))
        ok = [pipe.push_omc("tool", S + t, eye) for t in stamps]
        pipe.poll()
        ok += [pipe.push_omc("tool", S + t, eye) for t in bad]
        counts.append((ok, pipe.counts["duplicate"], pipe.counts["late"], pipe.counts["timeline_restart"]))
    assert counts[0] == counts[1]
    assert counts[0][0][-4:] == [False] * 4 and counts[0][1:] == (2, 2, 0)


@pytest.mark.parametrize("cls", [ApproxSync, ArrivalPipeline])
def test_both_hold_stamp_rules(cls):
    obj = cls() if cls is ApproxSync else cls(TargetConfig())
    assert isinstance(obj.rules, StampRules)
    assert (obj.rules.history_ns is None) is (cls is ApproxSync)
