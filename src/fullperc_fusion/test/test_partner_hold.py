"""Hold-for-partner (pipeline/partner_hold.py): which sample waits, what ends the wait, and that fusion on arrival with
waiting fuses each pair once yet still ends in exactly the ordered pipeline's estimates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import load_by_path
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.partner_hold import PartnerHold
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL

MS = 1_000_000
US = 1_000
_tp = load_by_path(Path(__file__).with_name("test_pipeline.py"), "_pipeline_streams_hold")
ALL, T0, stream = _tp.ALL, _tp.T0, _tp.stream


class Clock:
    """A host clock the test moves by hand."""

    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def _hold(wait_ms: float = 4.0) -> tuple[PartnerHold, Clock]:
    clock = Clock()
    return PartnerHold(4 * MS, int(wait_ms * MS), clock), clock


def _prime(h: PartnerHold) -> None:
    """Three periods of OMC (240 Hz: 4,167 us) and OTS (400 Hz: 2,500 us) samples in stamp order, each released."""
    for t in sorted([(GLOBAL, k * 4167 * US) for k in range(-3, 0)] + [(LOCAL, k * 2500 * US) for k in range(-5, 0)],
                    key=lambda x: x[1]):
        h.offer(*t, None)
    h.due(everything=True)


# ---------------------------------------------------------------------------------------------------- the rule
def test_the_first_sample_of_a_pair_waits_and_its_partner_releases_both_in_one_batch():
    """OTS at 0 ms: the OMC's next sample is due at 0.0 ms + (its newest -4.167 ms + 4.167 ms) -- nearer than any
    OMC sample here, and nearer to it than the OTS's neighbours: it waits. The OMC sample then releases it and,
    having its nearest partner here already, is fused with it at once."""
    h, _ = _hold()
    _prime(h)
    assert h.offer(LOCAL, 0, "ots0") == [] and len(h) == 1
    assert h.offer(GLOBAL, 300 * US, "omc0") == [(LOCAL, 0, "ots0"), (GLOBAL, 300 * US, "omc0")]
    assert len(h) == 0 and h.waited == 1


def test_a_sample_that_is_not_the_due_partners_nearest_does_not_wait():
    """OTS at 2.5 ms: the OMC sample due at 4.467 ms is nearer to the next OTS (5.0 ms) -- it will pair with that
    one, so this sample is fused at once. The OMC sample at 4.467 ms then waits for the OTS at 5.0 ms."""
    h, _ = _hold()
    _prime(h)
    h.offer(LOCAL, 0, "ots0")
    h.offer(GLOBAL, 300 * US, "omc0")
    assert h.offer(LOCAL, 2500 * US, "ots1") == [(LOCAL, 2500 * US, "ots1")]
    assert h.offer(GLOBAL, 4467 * US, "omc1") == []
    assert h.offer(LOCAL, 5000 * US, "ots2") == [(GLOBAL, 4467 * US, "omc1"), (LOCAL, 5000 * US, "ots2")]


def test_a_stream_that_missed_its_sample_is_not_waited_for():
    """The OMC silent for 20 ms (occluded): its predicted sample is long overdue, the OTS samples do not wait."""
    h, _ = _hold()
    _prime(h)
    for k in range(8):
        assert h.offer(LOCAL, 20 * MS + k * 2500 * US, k) == [(LOCAL, 20 * MS + k * 2500 * US, k)]
    assert h.waited == 0


def test_out_of_order_and_unprimed_samples_never_wait():
    h, _ = _hold()
    assert h.offer(LOCAL, 0, "a") == [(LOCAL, 0, "a")]   # no period known yet
    _prime(h)
    assert h.offer(LOCAL, -1 * MS, "old") == [(LOCAL, -1 * MS, "old")]   # older than its stream's newest


def test_a_newer_sample_of_its_own_stream_releases_it():
    h, _ = _hold()
    _prime(h)
    h.offer(LOCAL, 0, "ots0")
    assert h.offer(LOCAL, 2500 * US, "ots1")[0] == (LOCAL, 0, "ots0")


def test_the_host_clock_ends_a_wait_and_flush_ends_every_wait():
    h, clock = _hold(wait_ms=4.0)
    _prime(h)
    h.offer(LOCAL, 0, "ots0")
    clock.ns += 4 * MS - 1
    assert h.due() == [] and len(h) == 1
    clock.ns += 1
    assert h.due() == [(LOCAL, 0, "ots0")] and len(h) == 0
    h.offer(LOCAL, 5000 * US, "x")   # the OMC's next (predicted 4.167 ms... 4.167 + 4.167 ms) is nearer
    assert h.due(everything=True) in ([], [(LOCAL, 5000 * US, "x")]) and len(h) == 0


def test_no_wait_when_off_and_further_sources_pass_straight_through():
    h, _ = _hold(wait_ms=0.0)
    _prime(h)
    assert h.offer(LOCAL, 0, "ots0") == [(LOCAL, 0, "ots0")] and h.waited == 0
    h, _ = _hold()
    _prime(h)
    h.offer(LOCAL, 0, "ots0")
    assert h.offer(2, 100 * US, "extra") == [(2, 100 * US, "extra")] and len(h) == 1   # does not release it
    with pytest.raises(ValueError, match="partner_wait"):
        PartnerHold(4 * MS, -1)
    with pytest.raises(ValueError, match="partner_wait"):
        TargetConfig(partner_wait_ns=150 * MS)   # more than half the history (0.2 s)


# ---------------------------------------------------------------------------------------------------- in fusion
def _in_stamp_order(events, jitter_ns: int, seed: int):
    """The device samples of test_pipeline.stream received in stamp order, each up to ``jitter_ns`` late (random):
    both devices with the same transport delay, as bench/e2e_publisher.py publishes them."""
    rng = np.random.default_rng(seed)
    recv = [ev[2] + int(rng.uniform(0, jitter_ns)) if jitter_ns else ev[2] for ev in events]
    return [ev for _, _, ev in sorted(zip(recv, range(len(events)), events, strict=True))]


def _push(pipe, ev):
    dev, body, ns, T = ev
    (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, T)


def _run(cfg, events, clock=None, step_ns: int = 0):
    pipe = ArrivalPipeline(cfg) if clock is not None or cfg.processing == "arrival" else TargetPipeline(cfg)
    if clock is not None:
        pipe.hold.clock = clock
    live, final = [], []
    for ev in events:
        _push(pipe, ev)
        if clock is not None:
            clock.ns += step_ns
        live += pipe.poll()
        final += pipe.take_final() if clock is not None else []
    live += pipe.flush()
    final += pipe.take_final() if clock is not None else []
    return live, final, pipe


@pytest.fixture(scope="module")
def streams():
    return {j: _in_stamp_order(stream(duration=2.5, local=(0.5, 2.0), omc_hz=240, ots_hz=400), j * US, seed=j)
            for j in (0, 500, 3000)}


@pytest.mark.parametrize("chain", ["static", "direct"])
@pytest.mark.parametrize("jitter_us", [0, 500, 3000])
@pytest.mark.parametrize("step_us", [0, 700])
def test_waiting_ends_in_the_ordered_estimates(chain, jitter_us, step_us, streams):
    """Every filter, every final output exactly as ordered processing, whether or not samples waited, with jitter
    that reorders the streams now and then, and with a host clock that ends some waits (700 us per input)."""
    events = streams[jitter_us]
    cfg = TargetConfig(filters=ALL, chain=ChainConfig(local_chain=chain, static_links="average"),
                       partner_wait_ns=2 * MS)
    _live, final, pipe = _run(cfg, events, Clock(), step_us * US)
    ordered = TargetPipeline(cfg)
    outs = []
    for ev in events:
        _push(ordered, ev)
        outs += ordered.poll()
    outs += ordered.flush()
    do, da = {(o.filter, o.t_ns): o for o in outs}, {(o.filter, o.t_ns): o for o in final}
    assert len(do) > 1000 and do.keys() == da.keys()
    for k, o in do.items():
        a = da[k]
        assert np.array_equal(o.p, a.p) and np.array_equal(o.cov, a.cov) and np.array_equal(o.bias, a.bias), k
        assert (o.sources, o.t_global, o.t_local) == (a.sources, a.t_global, a.t_local), k
    assert pipe.pending == 0 and pipe.stats()["partner_waits"] > 100


def test_waiting_fuses_each_pair_once_and_publishes_fewer_outputs(streams):
    """240 + 400 Hz in stamp order: without waiting nearly every pair rewinds (the OTS sample is fused, then again
    with its OMC partner); with it almost none does, and the live outputs drop by the pairs' first halves."""
    events = streams[0]
    runs = {}
    for wait in (0, 4 * MS):
        cfg = TargetConfig(filters=("cbkf",), chain=ChainConfig(static_links="average"), partner_wait_ns=wait)
        live, _final, pipe = _run(cfg, events, Clock())
        runs[wait] = len(live), pipe.counts["items"], pipe.counts["rewinds"]
    (n0, items0, rew0), (n1, items1, rew1) = runs[0], runs[4 * MS]
    assert items0 == items1 > 800
    assert rew0 > 0.4 * items0 and rew1 < 0.02 * items1, runs
    assert n1 < 0.8 * n0, runs


def test_live_stamps_still_strictly_increase_when_samples_wait(streams):
    cfg = TargetConfig(filters=ALL, chain=ChainConfig(static_links="average"), partner_wait_ns=4 * MS)
    live, _final, _pipe = _run(cfg, streams[500], Clock(), 300 * US)
    stamps = np.array([o.t_ns for o in live if o.filter == ALL[0]])
    assert stamps.size > 500 and np.all(np.diff(stamps) > 0)


def test_a_sample_whose_partner_never_comes_is_fused_when_its_wait_is_over(streams):
    """The OTS sample waits; nothing else arrives: poll() gives nothing until the host clock passes the wait, then
    its estimate; the node's timer polls while ``waiting`` (fusion_core.due_outputs)."""
    events = [ev for ev in streams[0] if (ev[2] - T0) < 1.0e9]
    cfg = TargetConfig(filters=("cbkf",), chain=ChainConfig(static_links="average"), partner_wait_ns=4 * MS)
    clock = Clock()
    pipe = ArrivalPipeline(cfg)
    pipe.hold.clock = clock
    for ev in events:
        _push(pipe, ev)
        pipe.poll()
    # the next OTS tool sample, stamped just before the OMC's next one is due, which never comes
    nxt = max(ev[2] for ev in events if ev[0] == "omc") + 4_167 * US - 500 * US
    T = next(ev[3] for ev in reversed(events) if ev[:2] == ("ots", "tool"))
    pipe.push_ots("tool", nxt, T)
    assert pipe.waiting == 1 and pipe.poll() == []
    clock.ns += 4 * MS
    out = pipe.poll()
    assert pipe.waiting == 0 and [o.t_ns for o in out] == [nxt]
