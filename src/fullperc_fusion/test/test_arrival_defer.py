"""ArrivalPipeline.defer_side (fusion_node): the side-by-side filters' work waits until the node asks for it with
side_outputs (after the wake-up's live outputs went out) or until the next fusion. Only when it is computed moves:
every output, live, side-by-side and final, is the undeferred pipeline's bit for bit -- with the node's polls
every sample, in bursts (a node behind takes many samples per wake-up), with samples out of order, with a quality
record after its pose, across a timeline restart and at the end (flush)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import load_by_path
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig

MS = 1_000_000
_ta = load_by_path(Path(__file__).with_name("test_arrival.py"), "_arrival_helpers")
T0, S, stream, _push, _shuffled = _ta.T0, _ta.S, _ta.stream, _ta._push, _ta._shuffled


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


def _run(cfg: TargetConfig, feed, defer: bool, burst: int) -> tuple[list, list, list]:
    """(live, side, final) outputs, each in the order handed out, polling as fusion_node does every ``burst`` inputs:
    poll, then (deferred) side_outputs, then take_final."""
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
            take(pipe.side_outputs())
            final += pipe.take_final()
    take(pipe.flush())
    take(pipe.side_outputs())
    return live, side, final + pipe.take_final()


def _key(o) -> tuple:
    return (o.filter, o.t_ns, o.p.tobytes(), o.q.tobytes(), o.cov.tobytes(), o.bias.tobytes(), o.sources, o.hop)


@pytest.mark.parametrize("burst", [1, 7])
@pytest.mark.parametrize("case", ["in_order", "reordered", "fullperc_quality", "restart"])
def test_deferred_side_by_side_work_gives_the_same_outputs(case, burst):
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
    d_live, d_side, d_final = _run(cfg, feed, defer=True, burst=burst)
    assert len(now_side) > 300 and len(now_final) > len(now_side)
    assert [_key(o) for o in d_live] == [_key(o) for o in now_live]
    # the side-by-side outputs in the same order; the deferral only hands them out no earlier than undeferred
    assert [_key(o) for o in d_side] == [_key(o) for o in now_side]
    assert [_key(o) for o in d_final] == [_key(o) for o in now_final]


def test_deferred_work_waits_for_side_outputs_or_the_next_fusion():
    """Deferred: an item that left the history has no side-by-side output until side_outputs (the node, after
    publishing) -- or the next sample's fusion, which does the work first."""
    cfg = TargetConfig(filters=("cbkf", "kf"), chain=ChainConfig(static_links="average"))
    events = stream(duration=1.0, local=(0.2, 0.8), omc_hz=240, ots_hz=400)
    pipe = ArrivalPipeline(cfg)
    pipe.defer_side = True
    for k in range(400):   # 0.4 s: the links known, the side-by-side lane fusing
        _push(pipe, events[k])
        pipe.poll()
        pipe.side_outputs()
    k = 400
    _push(pipe, events[k])
    k += 1
    while not pipe._side_due:   # until an item leaves the history with its side-by-side work deferred
        _push(pipe, events[k])
        k += 1
    due = len(pipe._side_due)
    assert not [o for o in pipe.poll() if o.filter == "kf"]   # the live poll does none of it
    assert pipe.pending >= due   # counted as pending: the node's idle flush would do it
    got = pipe.side_outputs()
    assert len([o for o in got if o.filter == "kf"]) == due and not pipe._side_due
    while not pipe._side_due:
        _push(pipe, events[k])
        k += 1
    first_due, end = pipe._side_due[0], k + 20
    while first_due in pipe._side_due and k < end:   # a link body's sample or one waiting for its partner fuses nothing
        _push(pipe, events[k])
        k += 1
    assert first_due not in pipe._side_due, "the next fusion did the deferred work"
    assert [o for o in pipe.poll() if o.filter == "kf"]
