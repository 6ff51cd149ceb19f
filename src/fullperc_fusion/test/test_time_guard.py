"""The time guard (issue 16 item 2): a sample stamped more than ``max_future`` ahead of the caller's clock is
rejected, counted and named, and one such stamp never stalls the output (pipeline level; fusion_node's wiring is
tested across processes in test_fusion_node.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.params import ParameterError
from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion import fusion_config as fc
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

S = 1_000_000_000
T0 = 1_700_000_000 * S
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_RIG = make_T([3.0, 1.0, 1.5], Rot.from_euler("z", 150, degrees=True).as_quat())
HOUR = 3600 * S


def stream(duration=8.0):
    """('omc'|'ots', body, t_ns, T) in stamp order: OMC tool/base/rig at 120 Hz, OTS base/tool at 60 Hz."""
    rng = np.random.default_rng(0)
    ev = []
    for k in range(int(duration * 120)):
        ns = T0 + round(k / 120 * S)
        Tt = make_T([0.5 + 0.05 * np.cos(k / 120), 0.05 * np.sin(k / 120), 0.3])
        Tm = T_OMC_BASE @ Tt
        Tm[:3, 3] += rng.normal(0, 3e-4, 3)
        ev += [("omc", "base", ns, T_OMC_BASE), ("omc", "ots_rig", ns, T_OMC_RIG), ("omc", "tool", ns, Tm)]
        if k % 2 == 0:
            T_ots_base = inv_T(T_OMC_RIG) @ T_OMC_BASE
            ev += [("ots", "base", ns + 3_000_000, T_ots_base), ("ots", "tool", ns + 3_000_000, T_ots_base @ Tt)]
    return ev
ARRIVAL = 20_000_000          # the caller's clock reads 20 ms after a sample's acquisition stamp
BAD_AT, PAUSE = 3.0, (4.0, 4.8)


def _feed(guard: bool):
    """stream() with one OMC tool sample stamped an hour ahead at 3 s, and a 0.8 s input pause at 4 s, during which
    the node (clock 'stamps', idle_flush 0.5 s) flushes the pipeline. Returns the pipeline and its outputs."""
    pipe = TargetPipeline(TargetConfig(filters=("cbkf",)))
    outs, injected, flushed = [], False, False
    for dev, body, ns, T in stream():
        t = (ns - T0) / S
        if PAUSE[0] <= t < PAUSE[1]:
            if not flushed:
                outs += pipe.flush()     # fusion_node's idle flush
                flushed = True
            continue
        now = ns + ARRIVAL if guard else None
        if not injected and dev == "omc" and body == "tool" and t >= BAD_AT:
            injected = True
            pipe.push_omc("tool", ns + HOUR, T, now_ns=now)
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, T, now_ns=now)
        outs += pipe.poll()
    return pipe, outs


def test_one_sample_an_hour_ahead_is_rejected_named_and_does_not_stall_the_output():
    pipe, outs = _feed(guard=True)
    assert pipe.counts["rejected_future"] == 1
    msg = pipe.problems["rejected_future"]
    bad_ns = T0 + round(BAD_AT * S) + HOUR
    assert msg.startswith(f"OMC body 'tool': stamp {bad_ns} ns is 3599.980 s ahead of the clock"), msg
    assert pipe.counts["late"] == 0
    after = [o for o in outs if (o.t_ns - T0) / S > PAUSE[1] + 0.1]
    assert len(after) > 100 and max(o.t_ns for o in outs) < T0 + 9 * S
    # everything else went through: the same outputs as without the bad sample, up to the pause
    assert all(o.t_ns < T0 + HOUR for o in outs)


def test_without_the_guard_the_same_stream_stalls():
    """What the guard prevents (and what makes the test above able to fail): the hour-ahead stamp becomes the
    synchronizer's watermark, the idle flush moves the horizon an hour ahead, and every later sample is late."""
    pipe, outs = _feed(guard=False)
    assert pipe.counts["rejected_future"] == 0 and pipe.counts["late"] > 100
    assert not [o for o in outs if PAUSE[1] + 0.1 < (o.t_ns - T0) / S < 9]


def test_the_limit_is_max_future_and_a_missing_clock_checks_nothing():
    pipe = TargetPipeline(TargetConfig(filters=("kf",), max_future_ns=100_000_000))
    _, _, ns, T = next(e for e in stream() if e[1] == "tool")
    now = ns - 100_000_000
    assert pipe.push_omc("tool", ns, T, now_ns=now)                 # exactly max_future ahead: accepted
    assert not pipe.push_omc("tool", ns + 1_000_001, T, now_ns=now - 1_000_000)   # 0.102 s ahead: rejected
    assert pipe.counts["rejected_future"] == 1 and "0.102 s ahead" in pipe.last_problem
    assert pipe.push_ots("tool", ns + HOUR, T)                      # no clock given (offline replay): no check
    assert not pipe.push_ots("tool", ns + 2 * HOUR, T, now_ns=now)  # the OTS is guarded the same way
    assert "OTS tool 'tool'" in pipe.problems["rejected_future"]


def test_max_future_parameter():
    assert fc.spec("max_future").default == 0.1 and fc.spec("max_future").unit == "s"
    cfg = fc.target_config(lambda n, d: 0.25 if n == "max_future" else d, "tool")
    assert cfg.max_future_ns == 250_000_000
    assert fc.target_config(lambda n, d: d, "tool").max_future_ns == TargetConfig().max_future_ns == 100_000_000
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ParameterError, match="'max_future'"):
            fc.target_config(lambda n, d, bad=bad: bad if n == "max_future" else d, "tool")
    with pytest.raises(ValueError, match="max_future"):
        TargetConfig(max_future_ns=0)
