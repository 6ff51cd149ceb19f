"""ArrivalPipeline: fused on arrival, final estimates equal to ordered processing; late / duplicate / bad stamps."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import load_by_path
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.registry import make_filter
from fullperc_fusion.pipeline.arrival import ArrivalPipeline, make_pipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync, Sample

MS = 1_000_000
# the device-level synthetic streams of test_pipeline.py (tests run with --import-mode=importlib: load by path)
_tp = load_by_path(Path(__file__).with_name("test_pipeline.py"), "_pipeline_streams")
ALL, T0, S, stream = _tp.ALL, _tp.T0, _tp.S, _tp.stream


def _push(pipe, ev, now_ns=None):
    dev, body, ns, T = ev
    return (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, T, now_ns=now_ns)


def _ordered(cfg, events):
    pipe = TargetPipeline(cfg)
    outs = []
    for ev in events:
        _push(pipe, ev)
        outs += pipe.poll()
    return outs + pipe.flush(), pipe


def _arrival(cfg, events):
    pipe = ArrivalPipeline(cfg)
    live, final = [], []
    for ev in events:
        _push(pipe, ev)
        live += pipe.poll()
        final += pipe.take_final()
    live += pipe.flush()
    return live, final + pipe.take_final(), pipe


def _by_key(outs):
    d = {(o.filter, o.t_ns): o for o in outs}
    assert len(d) == len(outs), "one output per filter and stamp"
    return d


def _shuffled(events, max_delay_ns, seed):
    """The events received up to ``max_delay_ns`` late each (random), i.e. out of stamp order."""
    rng = np.random.default_rng(seed)
    recv = [ev[2] + int(rng.uniform(0, max_delay_ns)) for ev in events]
    return [ev for _, ev in sorted(zip(recv, events, strict=True), key=lambda x: x[0])]


@pytest.fixture(scope="module")
def arrival_run():
    """(cfg, events, (live, final, pipe)) of the stream below through ArrivalPipeline, per (chain, reorder_ms): one
    run, read by the two tests that follow (the final outputs against ordered processing, the live stamps). Each
    test only reads it; the run is the same one either test made for itself before."""
    runs = {}

    def get(chain: str, reorder_ms: int):
        if (chain, reorder_ms) not in runs:
            events = stream(duration=2.5, local=(0.5, 2.0), omc_hz=240, ots_hz=400)
            if reorder_ms:
                events = _shuffled(events, reorder_ms * MS, seed=reorder_ms)
            cfg = TargetConfig(filters=ALL, chain=ChainConfig(local_chain=chain, static_links="average"))
            runs[chain, reorder_ms] = cfg, events, _arrival(cfg, events)
        return runs[chain, reorder_ms]
    return get


@pytest.mark.parametrize("chain", ["static", "tracked", "direct"])
@pytest.mark.parametrize("reorder_ms", [0, 30])
def test_final_estimates_equal_ordered_processing(chain, reorder_ms, arrival_run):
    """Every filter, every output: same stamps and the same numbers (exactly) as the ordered pipeline, with the
    static links estimated mid-stream (average of the first samples) and samples out of order within the delay."""
    cfg, events, (live, final, apipe) = arrival_run(chain, reorder_ms)
    ordered, opipe = _ordered(cfg, events)
    do, da = _by_key(ordered), _by_key(final)
    assert len(do) > 1000 and do.keys() == da.keys()
    for k, o in do.items():
        a = da[k]
        assert np.array_equal(o.p, a.p) and np.array_equal(o.cov, a.cov) and np.array_equal(o.bias, a.bias), k
        assert (o.sources, o.t_global, o.t_local, o.hop) == (a.sources, a.t_global, a.t_local, a.hop), k
    assert apipe.counts["items"] == opipe.counts["items"]
    assert apipe.counts["late"] == opipe.counts["late"] == 0
    if reorder_ms:
        assert apipe.counts["rewinds"] > 0


@pytest.mark.parametrize("chain", ["static", "tracked", "direct"])
@pytest.mark.parametrize("reorder_ms", [0, 30])
def test_live_output_stamps_strictly_increase(chain, reorder_ms, arrival_run):
    """What fusion_node publishes on pose / pose_cov / tf (the live outputs of the primary) never repeats or goes
    back in stamp -- also while the static links are estimated mid-stream and items are re-run with them."""
    _cfg, _events, (live, _final, _pipe) = arrival_run(chain, reorder_ms)
    stamps = np.array([o.t_ns for o in live if o.filter == ALL[0]])
    assert stamps.size > 300   # reordered by 30 ms, items older than one already published are not published live
    assert np.all(np.diff(stamps) > 0), np.flatnonzero(np.diff(stamps) <= 0)


def test_a_partner_the_chain_cannot_map_does_not_republish_the_same_estimate():
    """The OTS partner of an already-published OMC sample arrives while the local link is not known yet: the item
    is re-run as a pair, the local sample is skipped (waiting for links), and the estimate is the one already
    published -- it must not go out a second time with the same stamp (CI: a repeated stamp on /fullperc/tool/pose
    in the demo's first second, before the Vega had seen the base marker)."""
    cfg = TargetConfig(filters=("cbkf",), chain=ChainConfig(init_samples=3, static_links="average"))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(3):
        pipe.push_omc("base", T0 + k, eye)
    assert pipe.chain.links.global_ready and not pipe.chain.links.local_ready
    live = []
    for k in range(20):
        t = T0 + 10 * MS + k * 4 * MS
        pipe.push_omc("tool", t, eye)
        live += pipe.poll()
        pipe.push_ots("tool", t + MS, eye)      # its partner (within slop), one millisecond later, arriving after
        live += pipe.poll()
    stamps = [o.t_ns for o in live]
    assert pipe.counts["rewinds"] > 0 and len(stamps) == 20
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False)), stamps


def test_each_sample_is_fused_when_it_arrives():
    """After every accepted target sample the newest item is output at once, stamped with that sample's stamp;
    stamps on the live output strictly increase."""
    cfg = TargetConfig(filters=("cbkf",))
    pipe = ArrivalPipeline(cfg)
    last = None
    fused = 0
    for ev in stream(duration=3.0, local=(0.5, 2.5)):
        before = last
        ok = _push(pipe, ev)
        outs = pipe.poll()
        for o in outs:
            assert last is None or o.t_ns > last
            last = o.t_ns
        newest = before is None or ev[2] > before   # (the OTS arrives 15 ms late: most of its samples are not)
        if ok and newest and ev[1] == "tool" and pipe.chain.links.global_ready and pipe.chain.links.local_ready:
            assert outs and outs[-1].t_ns == ev[2], "the sample that just arrived is in the output"
            fused += 1
    assert fused > 100


def test_partner_arriving_after_rewinds_into_a_pair():
    """An OMC sample fused alone is re-fused as a pair when its OTS partner (within slop) arrives after it."""
    cfg = TargetConfig(filters=("cbkf",), chain=ChainConfig(T_base_ots=(np.zeros(3), np.array([0, 0, 0, 1.0]))))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):   # base samples: the global link
        pipe.push_omc("base", T0 + k * MS, eye)
    t = T0 + 100 * MS
    pipe.push_omc("tool", t, eye)
    first = pipe.poll()
    assert [o.sources for o in first] == [SOURCE_GLOBAL]
    pipe.push_ots("tool", t + 2 * MS, eye)
    second = pipe.poll()
    assert [o.sources for o in second] == [SOURCE_GLOBAL | SOURCE_LOCAL]
    assert pipe.counts["rewinds"] == 1 and pipe.counts["items"] == 1, "the lone item was replaced, not counted twice"
    assert pipe.flush() == []
    final = pipe.take_final()
    assert [(o.t_global, o.t_local) for o in final] == [(t, t + 2 * MS)]


def test_older_than_the_history_is_dropped_counted_and_named():
    cfg = TargetConfig(filters=("cbkf",), history_ns=100 * MS)
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye)
    for k in range(50):
        assert pipe.push_omc("tool", T0 + k * 10 * MS, eye)
    old = T0 + 200 * MS + 5 * MS   # 0.285 s behind the newest (0.49 s): beyond the 0.1 s history
    assert not pipe.push_omc("tool", old, eye)
    assert pipe.counts["late"] == 1
    msg = pipe.problems["late"]
    assert "OMC body 'tool'" in msg and str(old) in msg and "history" in msg
    assert pipe.push_omc("tool", T0 + 485 * MS, eye), "within the history: still fused"
    assert not pipe.push_omc("tool", T0 + 485 * MS, eye)
    assert pipe.counts["duplicate"] == 1 and str(T0 + 485 * MS) in pipe.problems["duplicate"]


def test_future_stamp_never_stalls_and_ten_minutes_of_silence_resume():
    """A stamp an hour ahead of the caller's clock is rejected and named; the next samples are fused. After ten
    minutes without data (stamps jump ahead) the output resumes at once."""
    cfg = TargetConfig(filters=("cbkf",))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye, now_ns=T0 + k * MS)
    assert not pipe.push_omc("tool", T0 + 3600 * S, eye, now_ns=T0 + 40 * MS)
    assert "ahead of the clock" in pipe.problems["rejected_future"]
    assert str(T0 + 3600 * S) in pipe.problems["rejected_future"]
    assert pipe.push_omc("tool", T0 + 50 * MS, eye, now_ns=T0 + 50 * MS)
    assert [o.t_ns for o in pipe.poll()] == [T0 + 50 * MS]
    t = T0 + 600 * S
    assert pipe.push_omc("tool", t, eye, now_ns=t)
    outs = pipe.poll()
    assert [o.t_ns for o in outs] == [t] and outs[0].reset, "re-initialised after the gap, output at once"
    final = [o.t_ns for o in pipe.take_final()]
    assert final == [T0 + 50 * MS], "the item before the gap left the history"


def test_links_set_after_target_samples_replays_them():
    """Target samples that arrived before the global link was known are fused once it is (as ordered processing
    does for the samples it still holds), not lost."""
    cfg = TargetConfig(filters=("kf",), chain=ChainConfig(init_samples=3, static_links="average"))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    pipe.push_omc("tool", T0, eye)
    pipe.push_omc("tool", T0 + 5 * MS, eye)
    assert pipe.poll() == [] and pipe.counts["waiting_for_links"] == 2
    for k in range(3):
        pipe.push_omc("base", T0 + 5 * MS + k, eye)
    assert pipe.chain.links.global_ready
    assert [o.t_ns for o in pipe.poll()] == [T0, T0 + 5 * MS]
    assert pipe.counts["waiting_for_links"] == 0, "the replay rolled the count back"


def test_make_pipeline_and_config_checks():
    assert type(make_pipeline(TargetConfig())) is ArrivalPipeline
    assert type(make_pipeline(TargetConfig(processing="ordered"))) is TargetPipeline
    with pytest.raises(ValueError, match="processing"):
        TargetConfig(processing="later")
    with pytest.raises(ValueError, match="history"):
        TargetConfig(history_ns=0)


@pytest.mark.parametrize("name", ALL)
def test_snapshot_restore_gives_the_same_continuation(name):
    """restore(snapshot()) then the same steps = the same results, bit for bit, and a snapshot stays valid."""
    rng = np.random.default_rng(3)
    f = make_filter(name)

    def step(k):
        t = T0 + k * 4 * MS
        ms = [Measurement(t, SOURCE_GLOBAL, rng.normal(0, 1e-3, 3) + [0.1 * k * 4e-3, 0, 0])]
        if k % 3 == 0:
            cov = None if k % 2 else np.diag([1e-8, 2e-8, 3e-8, 1e-4, 1e-4, 1e-4]) + (k % 4 == 0) * 1e-9
            ms.append(Measurement(t - MS, SOURCE_LOCAL, rng.normal(0, 1e-4, 3), cov=cov))
        f.predict(t)
        st = f.update(*ms)
        return None if st is None else (st.p.copy(), st.pos_cov.copy())

    for k in range(30):
        step(k)
    snap = f.snapshot()
    state = copy.deepcopy(rng.bit_generator.state)
    first = [step(k) for k in range(30, 60)]
    for _ in range(2):
        f.restore(snap)
        rng.bit_generator.state = copy.deepcopy(state)
        again = [step(k) for k in range(30, 60)]
        for a, b in zip(first, again, strict=True):
            assert (a is None) == (b is None)
            if a is not None:
                assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_pair_equals_push_and_flush():
    rng = np.random.default_rng(5)
    g = sorted(set(int(x) for x in rng.integers(0, 400 * MS, 100)))
    loc = sorted(set(int(x) for x in rng.integers(0, 400 * MS, 160)))
    sync = ApproxSync(4 * MS, 50 * MS)
    for t, s in sorted([(t, GLOBAL) for t in g] + [(t, LOCAL) for t in loc]):
        sync.push(s, t, t)
    want = sync.flush()
    got = ApproxSync.pair([Sample(t, t) for t in g], [Sample(t, t) for t in loc], 4 * MS)
    assert got == want


def test_stamps_going_back_for_good_restart_the_timeline_instead_of_stalling():
    """One stamp an hour ahead with no clock to check it (or a bag played again): the following samples are late
    for a history's worth of their stamps, then the history ends, the filters restart and fusion goes on."""
    cfg = TargetConfig(filters=("cbkf",))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye)
    assert pipe.push_omc("tool", T0 + 3600 * S, eye)     # no now_ns: nothing checks it
    pipe.poll()
    out = []
    for k in range(1, 40):
        pipe.push_omc("tool", T0 + k * 10 * MS, eye)
        out.append(pipe.poll())
    first = next(i for i, o in enumerate(out) if o)
    assert not any(out[:first]) and all(out[first:]), "stalled, then an output per sample again"
    assert (first - 1) * 10 * MS <= cfg.history_ns < (first + 1) * 10 * MS, "resumed after one history"
    assert pipe.counts["timeline_restart"] == 1 and str(T0 + 3600 * S) in pipe.problems["timeline_restart"]
    assert out[-1][-1].t_ns == T0 + 39 * 10 * MS
    assert pipe.counts["filter_error"] == 0


def test_fullperc_primary_with_quality_after_its_pose_equals_ordered():
    """fullperc as the primary filter uses the OMC's TrackingQuality (by stamp); a quality that arrives after its
    pose was fused replays the item, so the final estimates still equal ordered processing."""
    events = stream(duration=2.0, local=(0.5, 1.5), omc_hz=240, ots_hz=400)
    rng = np.random.default_rng(7)
    feed = []
    for ev in events:
        feed.append(("pose", ev))
        if ev[0] == "omc" and ev[1] == "tool":
            feed.insert(len(feed) - int(rng.integers(0, 3)) if len(feed) > 3 else len(feed),   # before or after
                        ("quality", ("tool", ev[2], {"fit_error": float(rng.uniform(1e-4, 5e-4)),
                                                     "markers_used": 4.0})))
    cfg = TargetConfig(filters=("fullperc", "cbkf"), chain=ChainConfig(static_links="average"))
    results = []
    for P in (TargetPipeline, ArrivalPipeline):
        pipe = P(cfg)
        outs = []
        for kind, x in feed:
            if kind == "pose":
                _push(pipe, x)
            else:
                pipe.push_omc_quality(*x)
            polled = pipe.poll()
            outs += pipe.take_final() if P is ArrivalPipeline else polled
        flushed = pipe.flush()
        outs += pipe.take_final() if P is ArrivalPipeline else flushed
        results.append(_by_key(outs))
    do, da = results
    assert len(do) > 500 and do.keys() == da.keys()
    for k, o in do.items():
        assert np.array_equal(o.p, da[k].p) and np.array_equal(o.cov, da[k].cov), k


def test_a_restart_between_two_polls_does_not_stall_the_output():
    """The node polls after a burst of callbacks; on a busy machine the hour-ahead sample, the late run behind it
    and the restart can all fall between two polls. The live outputs from before the restart (the hour-ahead one
    among them) go out with that poll, gated against the old timeline; the outputs after it are not held back by
    the hour-ahead stamp (before the fix: the hour-ahead output was published after the restart and every later
    output, an hour older, was suppressed for good -- the time-guard system test's 2 poses after the pause)."""
    cfg = TargetConfig(filters=("cbkf",))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye)
    pipe.push_omc("tool", T0, eye)
    assert [o.t_ns for o in pipe.poll()] == [T0]
    assert pipe.push_omc("tool", T0 + 3600 * S, eye)
    for k in range(1, 40):                                # no poll in between: one burst
        pipe.push_omc("tool", T0 + k * 10 * MS, eye)
    assert pipe.counts["timeline_restart"] == 1
    burst = [o.t_ns for o in pipe.poll()]
    assert T0 + 3600 * S in burst and burst.count(T0 + 3600 * S) == 1, "the hour-ahead output went out once"
    assert burst[-1] == T0 + 39 * 10 * MS, "the outputs after the restart went out too"
    after = []
    for k in range(40, 60):
        pipe.push_omc("tool", T0 + k * 10 * MS, eye)
        after += [o.t_ns for o in pipe.poll()]
    assert after == [T0 + k * 10 * MS for k in range(40, 60)], "one output per sample after the burst"


def test_a_source_that_comes_late_but_in_order_is_dropped_not_a_restart():
    """One source's driver starved on a busy machine delivers its samples a second late, in order: they are dropped
    as late (counted), the timeline is not restarted -- a restart put the output a second back in time (a demo run with
    three busy loops beside: /fullperc/instrument/pose went 1.08 s back). A source whose late run lasts
    LATE_SOURCE_SPAN_NS of its own stamps still restarts it (no stall if the other source fell silent)."""
    from fullperc_fusion.pipeline.arrival import LATE_SOURCE_SPAN_NS

    cfg = TargetConfig(filters=("cbkf",))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye)
        pipe.push_ots("base", T0 + k * MS, eye)
    for k in range(300):                                  # 3 s of OMC at 100 Hz, on time
        pipe.push_omc("tool", T0 + k * 10 * MS, eye)
    out = [o.t_ns for o in pipe.poll()]
    for k in range(100):                                  # the OTS's first second comes now, 2 s late, in order
        pipe.push_ots("tool", T0 + k * 10 * MS, eye)
    out += [o.t_ns for o in pipe.poll()]
    assert pipe.counts["timeline_restart"] == 0 and pipe.counts["local_late"] == 100
    assert np.all(np.diff(out) > 0)
    pipe2 = ArrivalPipeline(cfg)
    for k in range(40):
        pipe2.push_omc("base", T0 + k * MS, eye)
        pipe2.push_ots("base", T0 + k * MS, eye)
    pipe2.push_omc("tool", T0 + 3600 * S, eye)            # the OMC an hour ahead, then silent
    n = int(LATE_SOURCE_SPAN_NS // (10 * MS)) + 5
    for k in range(n):                                    # the OTS goes on in order: after the span, a restart
        pipe2.push_ots("tool", T0 + k * 10 * MS, eye)
    assert pipe2.counts["timeline_restart"] == 1
