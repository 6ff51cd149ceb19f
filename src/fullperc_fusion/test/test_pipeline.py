"""TargetPipeline end to end on device-level synthetic streams (what the node and the evaluator run)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import T_to_pq, inv_T, make_T
from fullperc_fusion.filters.paper_family import SOURCE_GLOBAL, SOURCE_LOCAL
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

S = 1_000_000_000
T0 = 1_700_000_000 * S   # a realistic host-clock epoch

T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_RIG = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
T_RIG_OTS = make_T([0.05, 0.0, -0.1], Rot.from_euler("x", 5, degrees=True).as_quat())
T_OMC_OTS = T_OMC_RIG @ T_RIG_OTS
OMC_OFFSET = np.array([3e-3, -2e-3, 1e-3])   # systematic OMC error of the tool, in omc axes
HOP_T, HOP = 6.5, np.array([0, 0, 3e-3])     # OMC hop during the global-only phase


def truth(t):
    """T_base_tool: an arc at 5 cm/s, slowly turning."""
    w = 0.25
    p = [0.5 + 0.2 * np.cos(w * t), 0.2 * np.sin(w * t), 0.3]
    return make_T(p, Rot.from_euler("z", 10 * t, degrees=True).as_quat())


def stream(duration=8.0, local=(1.0, 5.0), seed=0, omc_hz=120, ots_hz=60):
    """Device samples in arrival order: ('omc'|'ots', body, t_ns, T)."""
    rng = np.random.default_rng(seed)
    ev = []
    for k in range(int(duration * omc_hz)):
        t = k / omc_hz
        ns = T0 + round(t * S)
        Tm = T_OMC_BASE @ truth(t)
        Tm[:3, 3] += OMC_OFFSET + (HOP if t >= HOP_T else 0) + rng.normal(0, 3e-4, 3)
        ev.append((ns + 2_000_000, "omc", "tool", ns, Tm))        # arrives 2 ms after acquisition
        ev.append((ns + 2_000_000, "omc", "base", ns, T_OMC_BASE))
        ev.append((ns + 2_000_000, "omc", "ots_rig", ns, T_OMC_RIG))
    for k in range(int(duration * ots_hz)):
        t = 0.003 + k / ots_hz
        ns = T0 + round(t * S)
        ev.append((ns + 15_000_000, "ots", "base", ns, inv_T(T_OMC_OTS) @ T_OMC_BASE))
        if local[0] <= t < local[1]:
            Tl = inv_T(T_OMC_OTS) @ T_OMC_BASE @ truth(t)
            Tl[:3, 3] += rng.normal(0, 1e-4, 3)
            ev.append((ns + 15_000_000, "ots", "tool", ns, Tl))   # the OTS is 15 ms late
    ev.sort(key=lambda e: e[0])
    return [e[1:] for e in ev]


def run(pipe, events, as_pq=False):
    outs = []
    for dev, body, ns, T in events:
        pose = T_to_pq(T) if as_pq else T
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, pose)
        outs += pipe.poll()
    return outs + pipe.flush()


def err_mm(outs, name, t0, t1, at_rest=False):
    e = [np.linalg.norm(o.p - truth(0 if at_rest else (o.t_ns - T0) / S)[:3, 3]) for o in outs
         if o.filter == name and t0 <= (o.t_ns - T0) / S < t1]
    assert e, f"no outputs of {name} in [{t0}, {t1})"
    return 1e3 * float(np.mean(e))


ALL = ("cbkf", "ckf", "bkf", "kf", "omc")


@pytest.fixture(scope="module")
def b_to_p():
    pipe = TargetPipeline(TargetConfig(filters=ALL))
    return pipe, run(pipe, stream())


def test_b_to_p_case_compensated_filters_keep_the_offset(b_to_p):
    _, outs = b_to_p
    offset_base = T_OMC_BASE[:3, :3].T @ OMC_OFFSET   # the OMC error seen in base axes
    off_mm = 1e3 * np.linalg.norm(offset_base)
    for name in ("cbkf", "ckf"):
        assert err_mm(outs, name, 2.0, 5.0) < 0.4                 # B: both present
        assert err_mm(outs, name, 5.2, 6.5) < 0.6                 # P: local gone, offset still removed
        assert err_mm(outs, name, 6.6, 8.0) < 1.0                 # P after the hop: absorbed
        b = [o.bias for o in outs if o.filter == name and 4.5 < (o.t_ns - T0) / S < 5.0]
        assert np.linalg.norm(np.mean(b, axis=0) - offset_base) < 0.3e-3
    for name in ("kf", "bkf"):
        assert err_mm(outs, name, 5.2, 6.5) > 0.8 * off_mm        # follows the biased OMC
    assert err_mm(outs, "omc", 2.0, 8.0) > 0.9 * off_mm


def test_stamps_are_input_acquisition_stamps_and_order_is_kept(b_to_p):
    _, outs = b_to_p
    omc_stamps = {ns for dev, body, ns, _ in stream() if dev == "omc" and body == "tool"}
    ots_stamps = {ns for dev, body, ns, _ in stream() if dev == "ots" and body == "tool"}
    for name in ALL:
        mine = [o for o in outs if o.filter == name]
        ts = [o.t_ns for o in mine]
        assert ts == sorted(ts)
        for o in mine:
            assert o.t_global is None or o.t_global in omc_stamps
            assert o.t_local is None or o.t_local in ots_stamps
            assert o.t_ns == max(x for x in (o.t_global, o.t_local) if x is not None)


def test_sources_and_orientation_source(b_to_p):
    _, outs = b_to_p
    cb = [o for o in outs if o.filter == "cbkf"]
    in_b = [o for o in cb if 1.2 < (o.t_ns - T0) / S < 4.8]
    assert sum(o.sources == SOURCE_GLOBAL | SOURCE_LOCAL for o in in_b) > 100   # pairs
    for o in cb:
        if o.sources & SOURCE_LOCAL:
            assert o.orientation_source == SOURCE_LOCAL
            # local orientation = the true one (OTS chain is exact up to noise-free rotation here)
            R = Rot.from_quat(o.q).as_matrix()
            t = (o.t_local - T0) / S
            assert np.allclose(R, truth(t)[:3, :3], atol=1e-9)
        else:
            assert o.orientation_source == SOURCE_GLOBAL
    assert all(o.orientation_source == SOURCE_GLOBAL for o in outs if o.filter == "omc")
    p_phase = [o for o in cb if (o.t_ns - T0) / S > 5.5]
    assert all(o.sources == SOURCE_GLOBAL for o in p_phase)
    assert p_phase[-1].time_since_local > 2.5


def test_hop_flagged_in_status(b_to_p):
    _, outs = b_to_p
    hops = [(o.t_ns - T0) / S for o in outs if o.filter == "cbkf" and o.hop]
    assert any(abs(t - HOP_T) < 0.02 for t in hops)


def test_side_by_side_filters_one_output_each_per_item(b_to_p):
    pipe, outs = b_to_p
    per = {n: [o.t_ns for o in outs if o.filter == n] for n in ALL}
    assert per["cbkf"] == per["kf"] == per["ckf"] == per["bkf"]
    # the pass-through reports every item with a global sample, stamped with that sample
    with_global = [o.t_global for o in outs if o.filter == "cbkf" and o.t_global is not None]
    assert per["omc"] == with_global


def test_covariance_is_finite_and_positive(b_to_p):
    _, outs = b_to_p
    for o in outs:
        assert o.cov.shape == (6, 6)
        assert np.all(np.isfinite(o.cov))
        assert np.all(np.linalg.eigvalsh(o.cov) > -1e-15)


def test_pq_input_gives_the_same_result_as_matrices():
    ev = stream(duration=2.0)
    a = run(TargetPipeline(TargetConfig(filters=("cbkf",))), ev)
    b = run(TargetPipeline(TargetConfig(filters=("cbkf",))), ev, as_pq=True)
    assert len(a) == len(b)
    assert max(np.linalg.norm(x.p - y.p) for x, y in zip(a, b, strict=True)) < 1e-9


def test_eq1_tracked_chain_gives_the_same_fusion_as_static():
    ev = stream(duration=3.0)
    a = run(TargetPipeline(TargetConfig(filters=("ckf",))), ev)
    b = run(TargetPipeline(TargetConfig(filters=("ckf",), chain=ChainConfig(local_chain="tracked"))), ev)
    assert [o.t_ns for o in a] == [o.t_ns for o in b]
    assert max(np.linalg.norm(x.p - y.p) for x, y in zip(a, b, strict=True)) < 1e-6
    assert {o.local_equation for o in b if o.t_local} == {"eq1"}


# ------------------------------------------------------------------------------------------ bad input

def _bad_stream():
    """Tool samples no. 150 (OMC) and 100 (OTS) NaN / non-unit; OMC tool no. 250 repeated 0.5 s back."""
    ev = stream(duration=3.0, local=(0.5, 3.0))
    out = []
    n = {"omc": 0, "ots": 0}
    for dev, body, ns, T in ev:
        if body == "tool":
            n[dev] += 1
        if body == "tool" and dev == "omc" and n[dev] == 150:
            out.append((dev, body, ns, "nan"))
        elif body == "tool" and dev == "ots" and n[dev] == 100:
            out.append((dev, body, ns, "nonunit"))
        else:
            out.append((dev, body, ns, T))
        if body == "tool" and dev == "omc" and n[dev] == 250:
            out.append((dev, body, ns - 500_000_000, T))   # time goes backwards by 0.5 s
    return out


def test_bad_input_no_exception_no_nan_and_a_reason():
    pipe = TargetPipeline(TargetConfig(filters=ALL))
    outs, problems = [], set()
    for dev, body, ns, T in _bad_stream():
        if isinstance(T, str):
            p, q = T_to_pq(stream(duration=0.01)[0][3])
            pose = ([np.nan, p[1], p[2]], q) if T == "nan" else (p, q * 1.5)
        else:
            pose = T
        push = pipe.push_omc if dev == "omc" else pipe.push_ots
        push(body, ns, pose)
        problems.add(pipe.last_problem)
        outs += pipe.poll()
    outs += pipe.flush()
    assert outs
    for o in outs:
        assert np.all(np.isfinite(o.p)) and np.all(np.isfinite(o.q)) and np.all(np.isfinite(o.cov))
    text = " | ".join(problems)
    assert "non-finite pose" in text
    assert "non-unit quaternion" in text
    assert "older than the processed horizon" in text
    assert pipe.counts["rejected_nonfinite"] == 1 and pipe.counts["rejected_nonunit"] == 1
    assert pipe.counts["late"] == 1
    assert err_mm(outs, "cbkf", 1.5, 3.0) < 0.5        # and fusion carried on


@pytest.mark.parametrize("bad_t", [0, -5, "soon", None])
def test_bad_stamps_are_rejected(bad_t):
    pipe = TargetPipeline(TargetConfig())
    assert not pipe.push_omc("tool", bad_t, T_OMC_BASE)
    assert "stamp" in pipe.last_problem


def test_unknown_bodies_are_ignored_quietly():
    pipe = TargetPipeline(TargetConfig())
    assert not pipe.push_omc("someone_else", T0, np.full((4, 4), np.nan))
    assert pipe.last_problem == ""


def test_sources_silent_for_minutes():
    """OTS silent for 3 minutes (only OMC), then everything silent for 3 minutes, then both back."""
    rng = np.random.default_rng(5)
    pipe = TargetPipeline(TargetConfig(filters=("cbkf", "kf")))
    T_ots_base = inv_T(T_OMC_OTS) @ T_OMC_BASE
    outs = []

    def omc(t):
        ns = T0 + round(t * S)
        Tm = T_OMC_BASE @ truth(0)   # target at rest
        Tm[:3, 3] += OMC_OFFSET + rng.normal(0, 3e-4, 3)
        pipe.push_omc("base", ns, T_OMC_BASE)
        pipe.push_omc("tool", ns, Tm)

    def ots(t):
        ns = T0 + round(t * S) + 3_000_000
        pipe.push_ots("base", ns, T_ots_base)
        Tl = T_ots_base @ truth(0)
        Tl[:3, 3] += rng.normal(0, 1e-4, 3)
        pipe.push_ots("tool", ns, Tl)

    for k in range(240):                       # 2 s of both at 120/60 Hz
        omc(k / 120)
        if k % 2 == 0:
            ots(k / 120)
        outs += pipe.poll()
    for k in range(int(180 * 20)):             # 3 minutes of OMC only, at 20 Hz
        omc(2 + k / 20)
        outs += pipe.poll()
    # 3 minutes of silence, then both sources again for 2 s
    for k in range(240):
        t = 362 + k / 120
        omc(t)
        if k % 2 == 0:
            ots(t)
        outs += pipe.poll()
    outs += pipe.flush()
    assert all(np.all(np.isfinite(o.p)) and np.all(np.isfinite(o.cov)) for o in outs)
    cb = [o for o in outs if o.filter == "cbkf"]
    at_3min = [o for o in cb if 170 < (o.t_ns - T0) / S < 182]
    assert max(o.time_since_local for o in at_3min) > 170
    # after 3 minutes without the OTS the compensation still holds for a target at rest
    assert err_mm(at_3min, "cbkf", 170, 182, at_rest=True) < 1.0
    assert err_mm(outs, "kf", 170, 182, at_rest=True) > 2.5
    resumed = [o for o in cb if (o.t_ns - T0) / S > 361]
    assert resumed[0].reset                    # the 3-minute gap re-initialised p and v
    assert err_mm(outs, "cbkf", 363, 364, at_rest=True) < 0.5


def test_reinitialize_request_re_estimates_the_base_link():
    pipe = TargetPipeline(TargetConfig(chain=ChainConfig(init_samples=10, static_links="average")))
    run(pipe, stream(duration=1.0))
    g0 = pipe.chain.links.generation
    pipe.request_initialize()
    assert pipe.stats()["collecting"]
    run(pipe, [(d, b, ns + 2 * S, T) for d, b, ns, T in stream(duration=1.0)])
    assert pipe.chain.links.generation > g0 and not pipe.stats()["collecting"]


def test_invalid_target_config_is_named():
    with pytest.raises(ValueError, match="ukf"):
        TargetConfig(filters=("ukf",))
    with pytest.raises(ValueError, match="duplicate"):
        TargetConfig(filters=("kf", "kf"))


def test_the_stages_of_push_give_what_push_gives():
    """push_* = validation (pose_to_T) + observe_* (links, link monitor) + enqueue (synchronizer, stamp rules): the
    stages the batched evaluator runs after validating a whole bag at once give exactly push_*'s outputs."""
    from fullperc_fusion.pipeline.frame_chain import pose_to_T
    from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL

    ev = stream(duration=3.0)
    cfg = TargetConfig(filters=ALL, chain=ChainConfig(static_links="average"))
    pushed = run(TargetPipeline(cfg), ev)
    pipe = TargetPipeline(cfg)
    c = cfg.chain
    staged = []
    for dev, body, ns, T in ev:
        T = pose_to_T(T)
        if dev == "omc":
            pipe.observe_omc(body, ns, T)
            if body == c.omc_target:
                assert pipe.enqueue(GLOBAL, ns, (T, None), f"OMC body '{body}'") == "ok"
        else:
            pipe.observe_ots(body, ns, T)
            if body == c.ots_target:
                assert pipe.enqueue(LOCAL, ns, (T, None), f"OTS tool '{body}'") == "ok"
        staged += pipe.poll()
    staged += pipe.flush()
    assert len(staged) == len(pushed) > 1000
    for a, b in zip(pushed, staged, strict=True):
        assert (a.filter, a.t_ns, a.sources) == (b.filter, b.t_ns, b.sources)
        assert np.array_equal(a.p, b.p) and np.array_equal(a.cov, b.cov) and np.array_equal(a.q, b.q)
    assert pipe.enqueue(GLOBAL, ev[0][2], (np.eye(4), None), "OMC body 'tool'") == "late"
    assert pipe.counts["late"] == 1 and "OMC body 'tool'" in pipe.problems["late"]
