"""Plausibility beyond NaN (issue 40 item 2, pipeline/plausibility.py): a target sample further from its source's last
accepted one than ``jump + max_speed * dt`` is dropped as ``rejected_jump``, the same in ordered processing and on
arrival. Pure: no ROS, no processes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fullperc_common.params import ParameterError
from fullperc_common.testing import load_by_path
from fullperc_fusion import fusion_config as fc
from fullperc_fusion.fusion_health import GLOBAL, HealthParams, TargetHealth
from fullperc_fusion.fusion_verdict import PROBLEM_KEYS, TargetVerdict
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.plausibility import Plausibility

MS = 1_000_000
# test_arrival.py's helpers: test_pipeline.py's device-level streams, pushed through ordered processing and on
# arrival, and received out of order (tests run with --import-mode=importlib: loaded by path)
_ta = load_by_path(Path(__file__).with_name("test_arrival.py"), "_plaus_arrival")
ALL, T0, S, stream = _ta.ALL, _ta.T0, _ta.S, _ta.stream
_push, _ordered, _arrival, _shuffled = _ta._push, _ta._ordered, _ta._arrival, _ta._shuffled


def _T(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    return T


def _moved(T: np.ndarray, off) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += off
    return out


def _same(a, b):
    assert len(a) == len(b) > 100
    for x, y in zip(sorted(a, key=lambda o: (o.t_ns, o.filter)), sorted(b, key=lambda o: (o.t_ns, o.filter)),
                    strict=True):
        assert (x.filter, x.t_ns, x.sources, x.t_global, x.t_local) == (y.filter, y.t_ns, y.sources, y.t_global,
                                                                        y.t_local)
        assert np.array_equal(x.p, y.p) and np.array_equal(x.cov, y.cov)


def _injected(events, off, every: int, dt_ns: int = 4 * MS, dev: str = "omc"):
    """``events`` with a sample ``off`` [m] off the honest one, stamped ``dt_ns`` after it, after every ``every``-th
    target sample of ``dev`` (it arrives right after that one); and the injected ones."""
    out, bad, k = [], [], 0
    for ev in events:
        out.append(ev)
        if ev[0] == dev and ev[1] == "tool":
            k += 1
            if k % every == 0:
                bad.append((dev, "tool", ev[2] + dt_ns, _moved(ev[3], off)))
                out.append(bad[-1])
    return out, bad


# ---- the rule ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("d_mm", "dt_ms", "ok"), [
    (21.9, 4.0, True), (22.1, 4.0, False),        # defaults at 4 ms: 10 mm + 3 m/s x 4 ms = 22 mm
    (9.9, 0.0, True), (10.1, 0.0, False),         # dt 0: the jump alone
    (34.9, 8.333, True), (35.1, 8.333, False),    # one OMC period at 120 Hz
    (309.0, 100.0, True), (311.0, 100.0, False),  # after a 100 ms gap the bound has grown to 310 mm
])
def test_the_bound_is_jump_plus_max_speed_times_dt(d_mm, dt_ms, ok):
    p = Plausibility(1, 3.0, 0.01, 200 * MS)
    p.accept(0, T0, _T([0.1, 0.2, 0.3]))
    why = p.check(0, T0 + round(dt_ms * MS) + (1 if dt_ms == 0 else 0), _T([0.1, 0.2 + d_mm * 1e-3, 0.3]), "OMC x")
    assert (why is None) is ok, why
    if not ok:
        assert why.startswith("OMC x: jumped ") and f"{d_mm:.1f} mm" in why and f"in {dt_ms:.1f} ms" in why


def test_the_first_sample_of_each_source_is_accepted_and_sources_are_separate():
    p = Plausibility(2, 3.0, 0.01, 200 * MS)
    assert p.check(0, T0, _T([5.0, 0, 0]), "g") is None   # nothing to compare with
    p.accept(0, T0, _T([5.0, 0, 0]))
    assert p.check(1, T0 + MS, _T([0.0, 0, 0]), "l") is None, "the local source is not compared with the global one"
    assert p.check(0, T0 + MS, _T([0.0, 0, 0]), "g") is not None


# ---- the scenario: one injected sample among honest ones --------------------------------------------------
@pytest.mark.parametrize(("off_mm", "max_speed"), [(20.0, 2.0), (25.0, 3.0)])
def test_an_injected_sample_is_rejected_and_the_next_honest_one_accepted(off_mm, max_speed):
    """Honest OMC samples at 120 Hz of a moving tool (the Vega does not see it), one sample ``off`` stamped 4 ms
    after an honest one: rejected, counted, named (source, jump in mm, dt in ms); the next honest sample is compared
    with the last accepted one (8.3 ms before) and taken; the fused poses are those without the injected sample.
    With the defaults (2 m/s, 10 mm) the bound at 4 ms is 18 mm; with 3 m/s 22 mm, so 25 mm is rejected there."""
    cfg = TargetConfig(filters=("cbkf", "omc"), max_speed=max_speed)
    honest = stream(duration=2.0, local=(10.0, 10.0))   # OMC only (the OTS sees the base, not the tool)
    k_tool = [i for i, ev in enumerate(honest) if ev[:2] == ("omc", "tool")]
    i = k_tool[120]
    dev, body, ns, T = honest[i]
    bad = (dev, body, ns + 4 * MS, _moved(T, [0.0, 0.0, off_mm * 1e-3]))
    events = [*honest[:i + 1], bad, *honest[i + 1:]]
    pipe = TargetPipeline(cfg)
    outs, taken = [], {}
    for k, ev in enumerate(events):
        taken[k] = _push(pipe, ev)
        outs += pipe.poll()
    outs += pipe.flush()
    assert taken[i] and not taken[i + 1], "the injected sample is dropped"
    assert taken[next(k for k in range(i + 2, len(events)) if events[k][:2] == ("omc", "tool"))], "next honest taken"
    assert pipe.counts["rejected_jump"] == 1
    assert all(taken[k] for k in range(len(events)) if k != i + 1 and events[k][:2] == ("omc", "tool"))
    why = pipe.problems["rejected_jump"]
    assert why.startswith("OMC body 'tool': jumped ") and " mm in 4.0 ms" in why and str(ns) in why
    d = float(why.split("jumped ")[1].split(" mm")[0])
    assert abs(d - off_mm) < 0.5
    ref, _ = _ordered(cfg, honest)
    _same(outs, ref)   # never fused, never paired: as if it had not been sent


def test_the_defaults_reject_20_mm_at_4_ms():
    """The issue's injection with the shipped defaults: 20 mm off, stamped 4 ms after an honest sample, is beyond the
    18 mm bound (10 mm + 2 m/s x 4 ms); 17 mm is within it."""
    cfg = TargetConfig()
    assert (cfg.max_speed, cfg.max_jump) == (2.0, 0.01)
    p = Plausibility(1, cfg.max_speed, cfg.max_jump, cfg.history_ns)
    p.accept(0, T0, _T([0, 0, 0]))
    assert p.check(0, T0 + 4 * MS, _T([0, 0, 0.017]), "x") is None
    assert p.check(0, T0 + 4 * MS, _T([0, 0, 0.020]), "x") is not None


def test_hops_of_a_few_mm_pass():
    """The OMC's marker swaps (a step of a few mm that stays, or one sample off and back) and noise pass: nothing is
    rejected and the fused poses are those of the same stream with plausibility out of reach."""
    rng = np.random.default_rng(3)
    events, k = [], 0
    for ev in stream(duration=3.0, local=(0.5, 2.5)):
        dev, body, ns, T = ev
        if (dev, body) == ("omc", "tool"):
            k += 1
            step = [0.0, 0.006, 0.0] if k > 150 else [0.0, 0.0, 0.0]                # a 6 mm swap that stays
            single = rng.normal(0, 0.004, 3) if k % 37 == 0 else np.zeros(3)       # a single sample off, ~7 mm
            T = _moved(T, np.add(step, single))
        events.append((dev, body, ns, T))
    outs, pipe = _ordered(TargetConfig(filters=ALL), events)
    assert pipe.counts["rejected_jump"] == 0
    ref, _ = _ordered(TargetConfig(filters=ALL, max_jump=1e3), events)
    _same(outs, ref)


def test_after_a_gap_the_bound_grows_and_a_rejected_sample_is_not_compared_with():
    cfg = TargetConfig(filters=("omc",), max_speed=3.0)
    pipe = TargetPipeline(cfg)
    assert pipe.push_omc("tool", T0, _T([0, 0, 0]))
    assert not pipe.push_omc("tool", T0 + 10 * MS, _T([0.05, 0, 0]))   # 50 mm in 10 ms > 40 mm
    # compared with the sample at T0 (accepted): 80 mm in 20 ms > 70 mm; from the rejected one it were 30 mm in 10 ms
    assert not pipe.push_omc("tool", T0 + 20 * MS, _T([0.08, 0, 0]))
    assert pipe.push_omc("tool", T0 + 20 * MS + 1, _T([0.002, 0, 0]))
    # 100 ms of silence: 0.3 m is within 10 mm + 3 m/s x 0.1 s
    assert pipe.push_omc("tool", T0 + 120 * MS + 1, _T([0.302, 0, 0]))
    assert not pipe.push_omc("tool", T0 + 130 * MS, _T([0.402, 0, 0]))
    assert pipe.counts["rejected_jump"] == 3


def test_a_wrong_first_sample_locks_its_source_out_only_until_the_bound_has_grown():
    """The first sample is accepted unchecked; if it is the bad one (1 m off) the honest samples are rejected only
    until dt > (d - jump) / max_speed = 0.33 s, then taken again."""
    pipe = TargetPipeline(TargetConfig(filters=("omc",), max_speed=3.0))
    assert pipe.push_omc("tool", T0, _T([1.0, 0, 0]))
    taken = [pipe.push_omc("tool", T0 + k * 10 * MS, _T([0, 0, 0])) for k in range(1, 60)]
    first = taken.index(True) + 1
    assert not any(taken[:first - 1]) and all(taken[first - 1:])
    assert first * 10 * MS >= (1.0 - 0.01) / 3.0 * S > (first - 1) * 10 * MS


def test_compared_in_the_device_frame_a_new_static_link_is_not_a_jump():
    """A calibration that moves T_omc_base by 0.5 m moves the fused pose by 0.5 m, not the OMC's samples: nothing is
    rejected (the bound is the target's motion in the frame the source measures in)."""
    from fullperc_common.transforms import T_to_pq
    from fullperc_fusion.calibration.se3_stats import Calibration, LinkEstimate

    pipe = TargetPipeline(TargetConfig(filters=("omc",)))
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, np.eye(4))
    outs = []
    for k in range(20):
        assert pipe.push_omc("tool", T0 + 100 * MS + k * 10 * MS, _T([0.1, 0, 0]))
        outs += pipe.poll()
    p, q = T_to_pq(_T([0.5, 0, 0]))
    est = LinkEstimate(p, q, np.eye(6) * 1e-10, 100, 100, 0.1, 0.2, 0.1, 0.2, "test")
    pipe.apply_calibration(Calibration({"T_omc_base": est}, T0, 1.0, "test"), "test")
    for k in range(20, 40):
        assert pipe.push_omc("tool", T0 + 100 * MS + k * 10 * MS, _T([0.1, 0, 0]))
        outs += pipe.poll()
    outs += pipe.flush()
    assert pipe.counts["rejected_jump"] == 0
    xs = [round(float(o.p[0]), 6) for o in outs]
    assert xs[0] == 0.1 and xs[-1] == -0.4, "the fused pose moved with the link"


# ---- out of order ---------------------------------------------------------------------------------------------
def test_a_sample_arriving_out_of_order_is_compared_with_the_accepted_one_before_its_stamp():
    """Only earlier stamps: a late honest sample is compared with the accepted sample just before it, never with a
    later one (there the tool was 0.3 m away legitimately); a late injected one is rejected the same way."""
    pipe = TargetPipeline(TargetConfig(filters=("omc",), max_speed=3.0))
    assert pipe.push_omc("tool", T0, _T([0, 0, 0]))
    assert pipe.push_omc("tool", T0 + 100 * MS, _T([0.3, 0, 0]))         # 3 m/s: just within 310 mm
    assert pipe.push_omc("tool", T0 + 10 * MS, _T([0.001, 0, 0])), "late honest: compared with T0, not T0 + 100 ms"
    assert not pipe.push_omc("tool", T0 + 15 * MS, _T([0.05, 0, 0])), "late injected: 49 mm in 5 ms from T0 + 10 ms"
    assert str(T0 + 10 * MS) in pipe.problems["rejected_jump"]
    assert pipe.counts["rejected_jump"] == 1 and pipe.counts["late"] == 0


def test_only_a_sample_the_pipeline_took_is_compared_with():
    """A plausible sample the synchronizer drops as late (an OTS item made it final) is not accepted: the next OMC
    sample is compared with the one at T0, not with it (0.33 m in 60 ms from it; 0.18 m in 110 ms from T0)."""
    cfg = TargetConfig(filters=("omc",), max_speed=3.0,
                       chain=ChainConfig(T_base_ots=(np.zeros(3), np.array([0, 0, 0, 1.0]))))
    pipe = TargetPipeline(cfg)
    assert pipe.push_omc("tool", T0, _T([0, 0, 0]))
    assert pipe.push_ots("tool", T0 + 100 * MS, _T([0, 0, 0]))
    assert pipe.push_ots("tool", T0 + 300 * MS, _T([0, 0, 0]))
    pipe.poll()
    assert pipe.sync.rules.horizon_ns == T0 + 100 * MS
    assert not pipe.push_omc("tool", T0 + 50 * MS, _T([0.15, 0, 0]))
    assert pipe.counts["late"] == 1 and pipe.counts["rejected_jump"] == 0
    assert pipe.push_omc("tool", T0 + 110 * MS, _T([-0.18, 0, 0]))


def test_a_late_sample_the_synchronizer_still_takes_is_compared_however_far_back():
    """Sparse samples: the item at T0 is final, the one at T0 + 1 s pending; a sample at T0 + 0.5 s is not late. It
    is compared with the accepted sample at T0 (the one before the kept window), not taken unchecked."""
    pipe = TargetPipeline(TargetConfig(filters=("omc",)))
    assert pipe.push_omc("tool", T0, _T([0, 0, 0]))
    assert pipe.push_omc("tool", T0 + S, _T([0.1, 0, 0]))
    pipe.poll()
    assert pipe.sync.rules.horizon_ns == T0
    assert not pipe.push_omc("tool", T0 + S // 2, _T([2.0, 0, 0])), "2 m in 0.5 s > 1.51 m"
    assert pipe.counts["rejected_jump"] == 1 and str(T0) in pipe.problems["rejected_jump"]
    assert pipe.push_omc("tool", T0 + S // 2 + 1, _T([0.05, 0, 0]))


def test_a_sample_older_than_everything_kept_is_left_to_the_stamp_rules():
    """Nothing kept before its stamp: not compared (judged like a first sample); the synchronizer drops it as late."""
    pipe = TargetPipeline(TargetConfig(filters=("omc",)))
    for k in range(100):
        assert pipe.push_omc("tool", T0 + k * 10 * MS, _T([k * 1e-3, 0, 0]))
        pipe.poll()
    assert not pipe.push_omc("tool", T0 + 5 * MS, _T([1.0, 0, 0]))
    assert pipe.counts["late"] == 1 and pipe.counts["rejected_jump"] == 0


# ---- ordered == arrival; rewinds ----------------------------------------------------------------------------------
@pytest.mark.parametrize("reorder_ms", [0, 30])
def test_ordered_and_arrival_reject_the_same_samples_and_give_the_same_estimates(reorder_ms):
    """Injected OMC and OTS samples 0.2 m off among honest 240 Hz / 400 Hz streams, in order and received up to
    30 ms out of order: both processing modes reject exactly the injected ones (each counted once, however often
    arrival rewinds) and their final estimates are bit-identical -- and equal to the streams without them."""
    honest = stream(duration=2.5, local=(0.5, 2.0), omc_hz=240, ots_hz=400)
    events, bad_omc = _injected(honest, [0.0, 0.2, 0.0], every=25)
    events, bad_ots = _injected(events, [0.2, 0.0, 0.0], every=40, dt_ns=MS, dev="ots")
    if reorder_ms:
        events = _shuffled(events, reorder_ms * MS, seed=reorder_ms)
    bad = {id(ev) for ev in (*bad_omc, *bad_ots)}
    cfg = TargetConfig(filters=ALL, chain=ChainConfig(static_links="average"))
    ordered, opipe = _ordered(cfg, events)
    _, final, apipe = _arrival(cfg, events)
    assert opipe.counts["rejected_jump"] == apipe.counts["rejected_jump"] == len(bad) > 20
    _same(final, ordered)
    if reorder_ms:
        assert apipe.counts["rewinds"] > 0
    ref, _ = _ordered(cfg, [ev for ev in events if id(ev) not in bad])   # the same arrival order, none injected
    _same(ordered, ref)


def test_a_rewind_does_not_judge_or_count_again():
    """A late OTS partner rewinds the arrival history over an item whose OMC sample was judged: the count stays 1."""
    cfg = TargetConfig(filters=("cbkf",), chain=ChainConfig(T_base_ots=(np.zeros(3), np.array([0, 0, 0, 1.0]))))
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye)
    for k in range(10):
        assert pipe.push_omc("tool", T0 + 100 * MS + k * 10 * MS, eye)
    assert not pipe.push_omc("tool", T0 + 194 * MS, _moved(eye, [0.1, 0, 0]))
    assert pipe.push_ots("tool", T0 + 152 * MS, eye)          # a partner of the sample at 150 ms: rewinds
    assert pipe.push_omc("tool", T0 + 200 * MS, eye)
    pipe.flush()
    assert pipe.counts["rewinds"] >= 1 and pipe.counts["replayed_items"] >= 1
    assert pipe.counts["rejected_jump"] == 1


# ---- restarts -------------------------------------------------------------------------------------------------
def test_initialize_starts_plausibility_again():
    pipe = TargetPipeline(TargetConfig(filters=("omc",)))
    assert pipe.push_omc("tool", T0, _T([0, 0, 0]))
    assert not pipe.push_omc("tool", T0 + 10 * MS, _T([0.5, 0, 0]))
    pipe.request_initialize()
    assert pipe.push_omc("tool", T0 + 20 * MS, _T([0.5, 0, 0])), "the first sample after ~/initialize"
    assert not pipe.push_omc("tool", T0 + 30 * MS, _T([0.0, 0, 0])), "compared with it from then on"


def test_the_first_sample_after_a_timeline_restart_is_accepted():
    """Arrival: the stamps go back for good (a bag played again) to where the tool was elsewhere. The first sample
    after the restart is accepted as a first one even where an accepted sample of the old timeline is earlier."""
    cfg = TargetConfig(filters=("cbkf",), history_ns=100 * MS)
    pipe = ArrivalPipeline(cfg)
    eye = np.eye(4)
    for k in range(40):
        pipe.push_omc("base", T0 + k * MS, eye)
    for k in range(100):                                   # old timeline: the tool at x = 0, T0 .. T0 + 0.99 s
        assert pipe.push_omc("tool", T0 + k * 10 * MS, eye)
    # played again from T0 + 0.6 s with the tool at x = 0.5 m: late until the run spans the history, then a restart
    taken = [pipe.push_omc("tool", T0 + 600 * MS + k * 10 * MS + 1, _moved(eye, [0.5, 0, 0])) for k in range(30)]
    assert pipe.counts["timeline_restart"] == 1
    first = taken.index(True)
    assert all(taken[first:]) and pipe.counts["rejected_jump"] == 0
    assert pipe.plausibility.check(0, T0 + 600 * MS + 29 * 10 * MS + 2, eye, "x") is not None, \
        "the new timeline's samples are the ones compared with"


# ---- configuration and the verdict --------------------------------------------------------------------------------
def _write(tmp_path, params: dict):
    p = tmp_path / "f.yaml"
    p.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": params}}))
    return p


def test_the_parameters_reach_the_pipeline(tmp_path):
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"plausibility": {"max_speed": 1.5, "jump": 0.004}}))
    assert (cfg.max_speed, cfg.max_jump) == (1.5, 0.004)
    pipe = TargetPipeline(cfg)
    assert (pipe.plausibility.max_speed, pipe.plausibility.jump) == (1.5, 0.004)
    shipped, _ = fc.load_fusion_config()
    assert (shipped.max_speed, shipped.max_jump) == (TargetConfig().max_speed, TargetConfig().max_jump) == (2.0, 0.01)


@pytest.mark.parametrize("value", [-1.0, 0.0, 0.5, 2.0, float("inf"), float("nan")])
@pytest.mark.parametrize(("name", "field"), [("plausibility.max_speed", "max_speed"),
                                             ("plausibility.jump", "max_jump")])
def test_the_node_and_the_dataclass_accept_the_same_values(tmp_path, name, field, value):
    """The table's rule (POSITIVE) and TargetConfig's own check agree; a bad value names the parameter."""
    row = next(p for p in fc.PARAMS if p.name == name)
    try:
        fc.convert(row, value)
        node_ok = True
    except ParameterError as e:
        node_ok = False
        assert name in str(e)
    try:
        TargetConfig(**{field: value})
        dataclass_ok = True
    except ValueError as e:
        dataclass_ok = False
        assert name in str(e)
    assert node_ok == dataclass_ok == (math.isfinite(value) and value > 0)


def test_a_rejected_jump_warns_while_held():
    assert "rejected_jump" in PROBLEM_KEYS
    pipe = TargetPipeline(TargetConfig(filters=("omc",)))
    pipe.push_omc("tool", T0, _T([0, 0, 0]))
    pipe.push_omc("tool", T0 + 4 * MS, _T([0.1, 0, 0]))
    health = TargetHealth("tool", {GLOBAL: "OMC body 'tool'"}, HealthParams())
    v = TargetVerdict("tool", stale_s=1.0, hold_s=10.0)
    _level, msgs, _ = v.evaluate(100.0, pipe, health, {"omc": 100.0, "ots": 100.0}, "omc")
    assert any(m.startswith("rejected_jump x1: OMC body 'tool': jumped 100.0 mm in 4.0 ms") for m in msgs), msgs
    _level, msgs, _ = v.evaluate(111.0, pipe, health, {"omc": 111.0, "ots": 111.0}, "omc")
    assert not any(m.startswith("rejected_jump") for m in msgs), "held for problem_hold, then gone"
