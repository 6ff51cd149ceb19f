"""ArrivalPipeline.defer_side (fusion_node): the side-by-side filters' work waits until the node asks for it with
side_outputs (after the wake-up's live outputs went out, an item at a time while no input waits) or until a fusion
finds it more than side_lag behind the history. Only when it is computed moves: every output, live, side-by-side
and final, is the undeferred pipeline's bit for bit -- with the node's polls every sample, in bursts (a node behind
takes many samples per wake-up), asking for all of the work, one item of it, or none (a node short of CPU: the
fusions do it, side_lag late), with samples out of order, with a quality record after its pose, across a timeline
restart and at the end (flush)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import load_by_path
from fullperc_fusion.pipeline.arrival import SIDE_LAG_MAX_NS, ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig

MS = 1_000_000
_ta = load_by_path(Path(__file__).with_name("test_arrival.py"), "_arrival_helpers")
T0, S, stream, _push, _shuffled = _ta.T0, _ta.S, _ta.stream, _ta._push, _ta._shuffled
_fc = load_by_path(Path(__file__).with_name("test_fusion_core.py"), "_fusion_core_helpers")


def _feed(events, quality: bool, seed: int = 7) -> list[tuple[str, tuple]]:
    """The events, and with ``quality`` a TrackingQuality per OMC tool sample, before or after its pose."""
    rng = np.random.default_rng(seed)
    feed: list[tuple[str, tuple]] = []
    for ev in events:
        feed.append(("pose", ev))
        if quality and ev[0] == "omc" and ev[1] == "tool":
            feed.insert(len(feed) - int(rng.integers(0, 3)) if len(feed) > 3 else len(feed),
                        ("quality", ("tool", ev[2], {"fit_error": float(rng.uniform(1e-4, 5e-4)),
                                                     "markers_used": 4.0})))
    return feed


def _run(cfg: TargetConfig, feed, defer: bool, burst: int, most: int | None = None) -> tuple[list, list, list]:
    """(live, side, final) outputs, each in the order handed out, polling as fusion_node does every ``burst`` inputs:
    poll, then (deferred) side_outputs of at most ``most`` items, then take_final."""
    pipe = ArrivalPipeline(cfg)
    pipe.defer_side = defer
    live, side, final = [], [], []
    primary = cfg.filters[0]

    def take(outs):
        live.extend(o for o in outs if o.filter == primary)
        side.extend(o for o in outs if o.filter != primary)

    for k, (kind, x) in enumerate(feed):
        if kind == "pose":
            _push(pipe, x)
        else:
            pipe.push_omc_quality(*x)
        if (k + 1) % burst == 0:
            take(pipe.poll())
            take(pipe.side_outputs(most))
            final += pipe.take_final()
    take(pipe.flush())
    take(pipe.side_outputs())
    return live, side, final + pipe.take_final()


def _key(o) -> tuple:
    return (o.filter, o.t_ns, o.p.tobytes(), o.q.tobytes(), o.cov.tobytes(), o.bias.tobytes(), o.sources, o.hop)


@pytest.mark.parametrize(("burst", "most"), [(1, None), (7, None), (1, 1), (3, 0)])
@pytest.mark.parametrize("case", ["in_order", "reordered", "fullperc_quality", "restart"])
def test_deferred_side_by_side_work_gives_the_same_outputs(case, burst, most):
    events = stream(duration=2.0, local=(0.5, 1.5), omc_hz=240, ots_hz=400)
    if case == "reordered":
        events = _shuffled(events, 30 * MS, seed=3)
    if case == "restart":   # one sample an hour ahead: the history ends, the filters start again (a restart)
        mid = len(events) // 2
        events = [*events[:mid], ("omc", "tool", events[mid][2] + 3600 * S, events[mid][3]), *events[mid:]]
    filters = ("fullperc", "cbkf", "kf") if case == "fullperc_quality" else ("cbkf", "ckf", "bkf", "kf", "omc")
    cfg = TargetConfig(filters=filters, chain=ChainConfig(static_links="average"))
    feed = _feed(events, quality=case == "fullperc_quality")
    now_live, now_side, now_final = _run(cfg, feed, defer=False, burst=burst)
    d_live, d_side, d_final = _run(cfg, feed, defer=True, burst=burst, most=most)
    assert len(now_side) > 300 and len(now_final) > len(now_side)
    assert [_key(o) for o in d_live] == [_key(o) for o in now_live]
    # the side-by-side outputs in the same order; the deferral only hands them out no earlier than undeferred
    assert [_key(o) for o in d_side] == [_key(o) for o in now_side]
    assert [_key(o) for o in d_final] == [_key(o) for o in now_final]


def test_deferred_work_waits_for_side_outputs_or_falls_side_lag_behind():
    """Deferred: an item that left the history has no side-by-side output until side_outputs (the node, after
    publishing; ``most`` items of it) -- or until a fusion finds it more than side_lag behind the history, which
    does it first."""
    cfg = TargetConfig(filters=("cbkf", "kf"), chain=ChainConfig(static_links="average"))
    events = stream(duration=1.5, local=(0.2, 1.2), omc_hz=240, ots_hz=400)
    pipe = ArrivalPipeline(cfg)
    pipe.defer_side = True
    assert pipe._side_lag_ns == min(cfg.history_ns, SIDE_LAG_MAX_NS) == 100 * MS
    for k in range(400):   # 0.4 s: the links known, the side-by-side lane fusing
        _push(pipe, events[k])
        pipe.poll()
        pipe.side_outputs()
    k = 400
    while pipe.side_backlog < 3:   # until three items left the history with their side-by-side work deferred
        _push(pipe, events[k])
        k += 1
    assert not [o for o in pipe.poll() if o.filter == "kf"]   # the live poll does none of it
    assert pipe.pending >= pipe.side_backlog   # counted as pending: the node's idle flush would do it
    first = pipe._side_due[0]
    got = pipe.side_outputs(1)   # the oldest item only
    assert [o.t_ns for o in got if o.filter == "kf"] == [first.item.t_ns] and pipe.side_backlog == 2
    first = pipe._side_due[0]
    while first in pipe._side_due:   # fusions leave it until it is side_lag behind the history
        assert first.te >= pipe.rules.newest_ns - cfg.history_ns - pipe._side_lag_ns - 10 * MS
        _push(pipe, events[k])
        k += 1
    assert first.te < pipe.rules.newest_ns - cfg.history_ns - pipe._side_lag_ns, "a fusion did it once due"
    assert pipe.side_backlog > 10   # the newer items still wait
    assert [o for o in pipe.poll() if o.filter == "kf"]


def test_deferred_side_by_side_work_is_counted_and_done_an_item_at_a_time_or_on_the_timer():
    """Items that left the history wait for their side-by-side work (arrival.py, defer_side): side_backlog names
    the target with their count, side_outputs(t, 1) does the oldest one, and the timer (due_outputs) does the rest
    when no input came to do it."""
    c = _fc.make_core(filters=["kf"])
    _fc.frames(c, 0, 60)   # 0.6 s at 100 Hz: items left the 0.2 s history, none of their kf work done (never asked)
    n = c.side_backlog()["tool"]
    assert n > 2
    one = [o for o in c.side_outputs("tool", 1) if o.filter == "kf"]
    assert len(one) == 1 and c.side_backlog() == {"tool": n - 1}
    out = dict(c.due_outputs(0.6, None))   # not idle: the timer does the deferred work
    assert len([o for o in out["tool"] if o.filter == "kf"]) == n - 1 and c.side_backlog() == {}
    assert [o.t_ns for o in one] < [o.t_ns for o in out["tool"] if o.filter == "kf"][:1]
