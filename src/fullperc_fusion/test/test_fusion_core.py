"""FusionCore: fusion_node's decisions without ROS -- made-up monotonic times stepped by the test, synthetic stamps.

The scene is static: the base marker, the OTS and the tool never move, so the links are known after
``init_samples`` frames and every decision is seen on its own (routing, flush, calibration, verdict, links)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.testing import wait_for
from fullperc_common.transforms import T_to_pq, inv_T, make_T
from fullperc_fusion.fusion_config import read_values
from fullperc_fusion.fusion_core import DIAG_EVAL_PERIOD_S, FusionCore
from fullperc_fusion.fusion_health import OK, WARN
from fullperc_fusion.fusion_verdict import LOSS_SILENCE_S
from fullperc_fusion.pipeline.ordered import TargetPipeline

S = 1_000_000_000
T0 = 1_700_000_000 * S
HZ = 100.0
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_OTS = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
T_BASE_TOOL = make_T([0.5, 0.1, 0.3], Rot.from_euler("x", 10, degrees=True).as_quat())
SHIFT = make_T([0.005, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])   # a 5 mm bump of the OTS (the monitor's limit: 2 mm)


def make_core(**over) -> FusionCore:
    """A core with the parameter table's defaults but ``over`` (fast links: average of 3 frames)."""
    over = {"static_links": "average", "init_samples": 3, **over}
    return FusionCore(read_values(lambda n, d: over.get(n, d)), now=0.0)


def sighting(dev: str, body: str, bump: np.ndarray | None = None) -> np.ndarray:
    """T_<device>_<body> of the static scene (``bump``: the OTS moved by it); every body but the base is the tool."""
    T_ots_omc = inv_T(T_OMC_OTS if bump is None else T_OMC_OTS @ bump)
    T = {("omc", "base"): T_OMC_BASE, ("omc", "tool"): T_OMC_BASE @ T_BASE_TOOL,
         ("ots", "base"): T_ots_omc @ T_OMC_BASE, ("ots", "tool"): T_ots_omc @ T_OMC_BASE @ T_BASE_TOOL}
    return T[("omc" if dev == "omc" else "ots", "base" if body == "base" else "tool")]


def push(core: FusionCore, dev: str, body: str, k: int, now: float, clock_ns: int = 0, T=None) -> list[str]:
    p, q = T_to_pq(sighting(dev, body) if T is None else T)
    return core.on_pose(dev, body, T0 + int(k * S / HZ), p, q, now, clock_ns)


def frames(core: FusionCore, k0: int, n: int, bodies=(("omc", "base"), ("omc", "tool"), ("ots", "base"),
                                                   ("ots", "tool")), bump=None) -> float:
    """Frames k0 .. k0+n-1 of ``bodies`` at ``now`` = stamp - T0, one input callback each (a live feed) -> last now."""
    now = 0.0
    for k in range(k0, k0 + n):
        now = k / HZ
        for dev, body in bodies:
            push(core, dev, body, k, now, T=sighting(dev, body, bump if dev == "ots" else None))
        for t in core.targets:
            core.poll(t, None)
        core.input_done([(T0 + int(k * S / HZ), dev, body) for dev, body in bodies], None, 0, now)
    return now


def status(core: FusionCore, now: float, target: str = "tool", published: int = 0) -> tuple[int, str, dict]:
    statuses = {name: (level, msg, values) for name, level, msg, values in core.diagnostics(now, published)}
    return statuses[f"target {target}"]


# ---- routing --------------------------------------------------------------------------------------------------------
def test_a_target_sample_counts_for_its_target_a_link_sample_only_feeds_the_pipeline():
    c = make_core()
    assert push(c, "omc", "base", 0, now=0.3) == ["tool"]
    assert c.last_rx["tool"]["omc"] is None and c.last_target_rx == 0.0   # a link body: no target sample
    assert c.pipes["tool"].counts["global_in"] == 0
    assert push(c, "omc", "tool", 0, now=0.5) == ["tool"]
    assert c.last_rx["tool"] == {"omc": 0.5, "ots": None} and c.last_target_rx == 0.5
    assert push(c, "ots", "tool", 0, now=0.6) == ["tool"]
    assert c.last_rx["tool"]["ots"] == 0.6


def test_a_body_no_target_uses_is_routed_nowhere():
    c = make_core()
    before = dict(c.pipes["tool"].counts)
    assert push(c, "omc", "stranger", 0, now=1.0) == []
    assert push(c, "vega2", "tool", 0, now=1.0) == []
    assert dict(c.pipes["tool"].counts) == before and c.last_target_rx == 0.0


def test_targets_share_the_streams_of_the_link_bodies():
    c = make_core(targets=["a", "b"])
    assert push(c, "omc", "base", 0, now=0.1) == ["a", "b"]
    assert push(c, "omc", "a", 0, now=0.1) == ["a"]
    assert c.last_rx["a"]["omc"] == 0.1 and c.last_rx["b"]["omc"] is None
    topics = [topic for _d, _b, topic in c.pose_topics()]
    assert sorted(topics) == sorted(set(topics))   # one subscription per topic
    assert set(topics) == {"/omc/a/pose", "/omc/b/pose", "/omc/base/pose", "/omc/ots_rig/pose", "/ots/a/pose",
                           "/ots/b/pose", "/ots/base/pose"}
    assert c.quality_topics == {("omc", "a"): "/omc/a/quality", ("ots", "a"): "/ots/a/quality",
                                ("omc", "b"): "/omc/b/quality", ("ots", "b"): "/ots/b/quality"}


def test_a_batch_has_a_link_sample_before_the_target_sample_of_the_same_stamp():
    c = make_core()
    batch = [(5, "omc", "tool"), (5, "omc", "base"), (4, "ots", "tool"), (5, "ots", "base")]
    assert sorted(batch, key=c.batch_key) == [(4, "ots", "tool"), (5, "omc", "base"), (5, "ots", "base"),
                                              (5, "omc", "tool")]


def test_the_time_guard_uses_the_node_clock_once_it_started():
    c = make_core()
    hour_ahead = T0 - 3600 * S   # the node clock an hour behind the sample's stamp
    push(c, "omc", "tool", 0, now=0.1, clock_ns=hour_ahead)
    assert c.pipes["tool"].counts["rejected_future"] == 1
    assert c.health["tool"].values(0.1)["global_rejected_run_s"] == 0.0   # a run of rejections started
    assert c.health["tool"]._run_count["global"] == 1
    push(c, "omc", "tool", 1, now=0.2, clock_ns=0)   # sim time not started: nothing checked
    assert c.pipes["tool"].counts["rejected_future"] == 1


# ---- flush policy ---------------------------------------------------------------------------------------------------
def test_arrival_history_is_flushed_when_idle_and_not_before():
    c = make_core(filters=["kf"])
    last = frames(c, 0, 10)
    pipe = c.pipes["tool"]
    assert pipe.pending > 0
    assert list(c.due_outputs(last + c.idle_flush, None)) == []   # idle means *more* than idle_flush
    out = list(c.due_outputs(last + c.idle_flush + 1e-3, None))
    assert [t for t, _ in out] == ["tool"] and pipe.pending == 0
    final = c.final_outputs("tool")
    assert final and {o.filter for o in final} == {"cbkf"}   # the side-by-side kf has its own topics
    assert list(c.due_outputs(last + 5.0, None)) == []       # nothing pending, nothing to do


def test_a_sample_waiting_for_its_partner_goes_out_on_the_timer_once_its_wait_is_over():
    """The OMC sample of frame 10 waits for the OTS sample due at its stamp (partner_wait, pipeline/partner_hold.py),
    which never comes: the node's timer (due_outputs) polls the target while it waits, and gets its estimate once
    the host clock passed partner_wait -- not before."""
    c = make_core(filters=["kf"])
    last = frames(c, 0, 10)
    pipe = c.pipes["tool"]
    host = {"ns": 0}
    pipe.hold.clock = lambda: host["ns"]
    push(c, "omc", "tool", 10, last + 0.01)
    assert pipe.waiting == 1 and c.poll("tool", None) == []
    assert [(t, o) for t, o in c.due_outputs(last + 0.01, None)] == [("tool", [])]
    host["ns"] += int(c.pipes["tool"].config.partner_wait_ns)
    out = list(c.due_outputs(last + 0.01, None))
    assert [(t, [o.t_ns for o in outs if o.filter == "cbkf"]) for t, outs in out] == [("tool", [T0 + int(10 * S / HZ)])]
    assert pipe.waiting == 0 and c.pipes["tool"].config.partner_wait_ns == 4_000_000   # the node's default


def test_a_link_sample_does_not_postpone_the_idle_flush():
    c = make_core()
    last = frames(c, 0, 10)
    frames(c, 10, 60, bodies=(("omc", "base"), ("ots", "base")))   # 0.6 s of base sightings only
    assert c.last_target_rx == last
    assert [t for t, _ in c.due_outputs(last + c.idle_flush + 1e-3, None)] == ["tool"]


def test_ordered_stamps_polls_by_the_stamps_then_flushes_when_idle():
    c = make_core(processing="ordered")
    last = frames(c, 0, 10)
    pipe = c.pipes["tool"]
    waiting = pipe.sync.pending
    assert waiting > 0   # the newest items wait for reorder_delay of newer stamps
    assert [(t, o) for t, o in c.due_outputs(last + 0.1, None)] == [("tool", [])]
    assert pipe.sync.pending == waiting
    out = list(c.due_outputs(last + c.idle_flush + 1e-3, None))
    assert pipe.sync.pending == 0 and out[0][1]


def test_ordered_host_clock_polls_with_the_node_clock_and_never_flushes():
    c = make_core(processing="ordered", clock="host")
    assert c.needs_clock and not make_core().needs_clock
    last = frames(c, 0, 10)
    pipe = c.pipes["tool"]
    waiting = pipe.sync.pending
    list(c.due_outputs(last + 10.0, T0))   # idle, but the node clock is before the pending stamps
    assert pipe.sync.pending == waiting
    out = list(c.due_outputs(last + 10.0, T0 + 10 * S))
    assert pipe.sync.pending == 0 and out[0][1]


def test_shutdown_flushes_every_target_with_something_pending():
    c = make_core(targets=["a", "b"])
    assert list(c.flush_all()) == []
    push(c, "omc", "a", 0, now=0.0)
    assert [t for t, _ in c.flush_all()] == ["a"]


# ---- health bookkeeping ---------------------------------------------------------------------------------------------
def test_local_samples_the_chain_skipped_count_as_rejected():
    c = make_core()
    c.pipes["tool"].counts["local_skipped"] += 3
    c.note_skipped("tool", now=2.0)
    c.note_skipped("tool", now=2.5)   # no new skip: the run stays as it was
    assert c.health["tool"]._run_count["local"] == 3
    assert c.health["tool"].values(2.5)["local_rejected_run_s"] == 0.5


def test_primary_outputs_feed_the_health_and_publish_errors_the_pipeline():
    c = make_core()
    frames(c, 0, 5)
    o = c.pipes["tool"].last_output["cbkf"]
    c.primary_output("tool", 1.0, replace(o, bias=np.array([0.0, 0.0, 0.5])))   # |b| 0.5 m > alarm.bias_max
    assert any(a.rule == "bias" for a in c.health["tool"].alarms(1.0))
    c.publish_error("tool", o, "non-finite pose")
    assert c.pipes["tool"].counts["publish_error"] == 1
    level, msg, _ = status(c, 1.0)
    assert level == WARN and "publish_error x1: cbkf: non-finite pose" in msg


# ---- calibration ----------------------------------------------------------------------------------------------------
def _until(fn):
    """fn() until truthy (a worker thread's result: fullperc_common.background); a liveness bound."""
    return wait_for(fn, 60.0, 0.01, what="the worker")


def test_calibrate_collects_then_swaps_the_links_of_every_target_and_writes_the_file(tmp_path):
    out = tmp_path / "cal.yaml"
    c = make_core(targets=["a", "b"], **{"calibration.duration": 0.5, "calibration.output": str(out)})
    assert not c.calibrating
    started, line = c.start_calibration(now=0.0)
    assert started and "collecting 0.5 s of sightings for ['T_omc_base', 'T_base_ots']" in line
    assert c.start_calibration(now=0.1) == (False, "a calibration is already running; call again when it has "
                                                   "answered")
    bodies = (("omc", "base"), ("ots", "base"), ("omc", "a"), ("ots", "a"))
    frames(c, 0, 20, bodies=bodies)
    assert c.finish_calibration(now=0.2) is None   # 0.2 s of stamps: not done
    frames(c, 20, 60, bodies=bodies)
    assert c.finish_calibration(now=0.8) is None   # the collection is complete: this poll starts the means
    done = _until(lambda: c.finish_calibration(now=0.8))
    assert done is not None and done.ok and done.level == "info", done
    assert "links of ['a', 'b'] swapped; written to" in done.message and out.exists()
    assert not c.calibrating
    for pipe in c.pipes.values():
        assert "~/calibrate" in "; ".join(pipe.chain.links.sources.values())


def test_calibrate_without_sightings_is_refused_after_the_timeout_and_keeps_the_links():
    c = make_core(**{"calibration.duration": 1.0, "calibration.timeout": 2.0})
    frames(c, 0, 5)
    links = c.static_links()
    c.start_calibration(now=10.0)
    assert c.finish_calibration(now=12.9) is None   # duration + timeout not over
    done = c.finish_calibration(now=13.0)
    assert done is not None and not done.ok and done.level == "warning"
    assert done.message.startswith("calibration refused, links unchanged: too few sightings")
    assert not c.calibrating
    assert all(np.array_equal(a[2], b[2]) for a, b in zip(links, c.static_links(), strict=True))


def test_calibrate_whose_file_cannot_be_written_keeps_the_links(tmp_path):
    (tmp_path / "a_file").write_text("")
    c = make_core(**{"calibration.duration": 0.5, "calibration.output": str(tmp_path / "a_file" / "cal.yaml")})
    c.start_calibration(now=0.0)
    frames(c, 0, 80)
    assert c.finish_calibration(now=0.8) is None   # the collection is complete: this poll starts the means
    done = _until(lambda: c.finish_calibration(now=0.8))
    assert done is not None and not done.ok and done.level == "error"
    assert done.message.startswith("calibration not applied, links unchanged: cannot write")
    assert "~/calibrate" not in "; ".join(c.pipes["tool"].chain.links.sources.values())


def test_initialize_re_estimates_the_links_of_every_target():
    c = make_core(targets=["a", "b"])
    msg = c.initialize()
    assert msg == ("re-estimating static links of ['a', 'b'] from the next 3 samples per body; the previous links "
                   "stay in use until then")
    assert all(p.chain.links.collecting for p in c.pipes.values())


# ---- diagnostics verdict --------------------------------------------------------------------------------------------
def test_at_start_the_target_is_initializing_and_waits_for_its_global_source():
    level, msg, values = status(make_core(), 0.0)
    assert level == WARN
    assert msg.startswith("initializing: ") and "no OMC (global) sample received yet" in msg
    assert values["global_link"] == "waiting"


def test_a_ready_target_with_fresh_samples_is_ok():
    c = make_core()
    last = frames(c, 0, 10)
    level, msg, values = status(c, last + 0.1)
    assert (level, msg) == (OK, "ok")
    assert values["last_stamp_ns"] == T0 + int(9 * S / HZ) and values["bias_mm"] == [0.0, 0.0, 0.0]


def test_a_silent_global_source_warns_a_silent_local_one_is_named_only():
    c = make_core()
    last = frames(c, 0, 10)
    stale = 1.0   # stale_timeout's default
    assert status(c, last + stale)[0] == OK   # silent for *more* than stale_timeout
    push(c, "omc", "tool", 10, now=last + stale)
    level, msg, _ = status(c, last + stale + 0.2)
    assert level == OK and msg == ("no OTS (local) sample for 1.2 s (target occluded or out of the OTS volume: global "
                                   "only, bias compensated)")
    level, msg, _ = status(c, last + 3.0)
    assert level == WARN and "no OMC (global) sample for 2.0 s" in msg


def test_a_problem_warns_for_problem_hold_after_its_count_last_rose():
    c = make_core()
    frames(c, 0, 10)
    c.on_pose("omc", "tool", T0 + S, np.array([np.nan, 0, 0]), np.array([0, 0, 0, 1.0]), 1.0, 0)
    frames(c, 100, 1)
    level, msg, _ = status(c, 1.0)
    assert level == WARN and "rejected_nonfinite x1: " in msg
    frames(c, 1100, 1)   # keep the sources fresh
    assert "rejected_nonfinite" in status(c, 1.0 + 10.0 - 1e-6)[1]   # problem_hold 10 s
    level, msg, _ = status(c, 11.0)
    assert "rejected_nonfinite" not in msg


def _callbacks(c: FusionCore, lags_s: list[float], now: float) -> None:
    for i, lag in enumerate(lags_s):
        stamp = T0 + i * S // 100
        c.input_done([(stamp, "omc", "base", None)], 0, stamp + int(lag * S), now)


def test_overload_warns_when_the_lag_stayed_above_lag_warn_for_a_whole_period():
    c = make_core()
    frames(c, 0, 10)
    status(c, 0.09)   # the end of the period of the frames' callbacks (no lag: the node clock not started)
    _callbacks(c, [0.25, 0.3, 0.21], now=0.1)   # lag_warn 0.2 s
    level, msg, values = status(c, 0.1, published=1)
    assert level == WARN and "overload: processing lag 210 ms or more" in msg
    assert values["lag_min_ms"] == 210.0 and values["lag_max_ms"] == 300.0 and values["input_callbacks"] == 3
    _callbacks(c, [0.25, 0.19, 0.3], now=0.6)   # one callback caught up: a busy machine, no overload
    assert "overload" not in status(c, 0.6, published=2)[1]
    _callbacks(c, [0.2], now=1.1)               # at lag_warn: no overload either
    assert "overload" not in status(c, 1.1, published=3)[1]


def test_the_load_report_adds_up_the_periods_until_one_is_published():
    c = make_core()
    _callbacks(c, [0.0, 0.0], now=0.1)
    assert status(c, 0.1, published=0)[2]["input_callbacks"] == 2
    _callbacks(c, [0.0], now=0.6)
    assert status(c, 0.6, published=0)[2]["input_callbacks"] == 3   # the last report was not sent: added
    _callbacks(c, [0.0], now=1.1)
    assert status(c, 1.1, published=1)[2]["input_callbacks"] == 1   # it went out: a new report


def test_the_diagnostics_evaluation_is_due_from_the_input_path_two_periods_late():
    c = make_core()
    c.diagnostics(5.0, 0)
    assert c.diag_eval_at == 5.0
    assert not c.input_done([(T0, "omc", "base", None)], None, 0, 5.0 + 2 * DIAG_EVAL_PERIOD_S - 1e-3)
    assert c.input_done([(T0, "omc", "base", None)], None, 0, 5.0 + 2 * DIAG_EVAL_PERIOD_S)


def test_lost_samples_warn_for_problem_hold():
    c = make_core()
    last = frames(c, 0, 10)
    key = ("omc", "tool")
    c.quality_rx(key, last)
    for k in range(10):
        c.quality(key, k + 1 if k < 5 else k + 4, T0 + int(k * S / HZ), True, 0.1, 4.0)   # 3 frames lost
    level, msg, values = status(c, last)
    assert level == WARN and "lost samples of the OMC body 'tool': 3 poses never arrived" in msg
    assert values["omc_frames_lost"] == 3 and values["omc_samples_lost"] == 3
    c.input_done([(T0, "omc", "base", None)], None, 0, last + 5.0)
    frames(c, 1000, 1)
    assert "lost samples" in status(c, last + 10.0 - 1e-6)[1]
    assert "lost samples" not in status(c, last + 10.0)[1]


def test_a_visible_frame_whose_pose_never_came_is_lost_once_the_stream_was_silent():
    c = make_core()
    frames(c, 0, 10)
    key = ("omc", "tool")
    c.quality_rx(key, 1.0)
    c.quality(key, 11, T0 + int(10 * S / HZ), True, 0.1, 4.0)   # frame 10: visible, its pose never comes
    assert status(c, 1.0 + LOSS_SILENCE_S)[2]["omc_samples_lost"] == 0   # silent for *more* than 4 s
    assert status(c, 1.0 + LOSS_SILENCE_S + 0.1)[2]["omc_samples_lost"] == 1
    c2 = make_core()
    c2.quality_rx(key, 1.0)
    c2.quality(key, 1, T0, True, 0.1, 4.0)
    c2.input_done([(T0, "omc", "base", None)], None, T0 + 5 * S, 1.0)   # the node is 5 s behind: poses queue
    later = 1.0 + LOSS_SILENCE_S + 0.1
    c2.input_done([(T0 + S, "omc", "base", None)], None, T0 + 6 * S, later - 0.5)   # and still catching up
    assert status(c2, later)[2]["omc_samples_lost"] == 0
    c2.end_of_streams()
    assert status(c2, later)[2]["omc_samples_lost"] == 1


def test_a_lag_frozen_at_the_last_callback_does_not_hold_the_loss_count_off_for_good():
    """The stream ended while the node was 15 s behind: its last input callback measured that lag and no callback
    ran after it. Once none has run for stale_timeout the node's queue is empty, so the visible frame whose pose
    never came is counted lost (a 1 kHz run never counted 1,466 lost OTS poses this way)."""
    c = make_core()
    key = ("omc", "tool")
    c.quality_rx(key, 1.0)
    c.quality(key, 1, T0, True, 0.1, 4.0)
    c.input_done([(T0 - S, "omc", "base", None)], None, T0 + 15 * S, 1.0)
    assert c.book.catching_up(1.5)
    assert status(c, 1.0 + LOSS_SILENCE_S + 0.1)[2]["omc_samples_lost"] == 1
    assert not c.book.catching_up(1.0 + LOSS_SILENCE_S + 0.1)


# ---- link watch and /tf_static --------------------------------------------------------------------------------------
def test_a_link_bump_is_logged_once_warns_then_clears_after_the_hold():
    c = make_core()
    frames(c, 0, 150)   # 1.5 s: the monitor's window checked the link
    assert c.watch_links("tool", 1.5) == []
    logs = []
    for k in range(150, 350, 10):   # 2 s of the OTS moved by 5 mm, watched as the node does after each input
        frames(c, k, 10, bump=SHIFT)
        logs += c.watch_links("tool", k / HZ)
    assert [lvl for lvl, _ in logs] == ["warning"] and "static link T_base_ots bumped" in logs[0][1]
    level, msg, values = status(c, 3.5)
    assert level == WARN and "bumped" in msg and values["link_bumped"] is True
    for k in range(350, 550, 10):   # back where it was
        frames(c, k, 10)
        logs += c.watch_links("tool", k / HZ)
    assert [lvl for lvl, _ in logs] == ["warning", "info"] and "within its calibration" in logs[1][1]
    bump_seen = c.verdicts["tool"].bump[0]
    frames(c, 1300, 1)
    msg = status(c, bump_seen + 9.0)[1]
    assert "bumped" in msg and "(cleared 9.0 s ago)" in msg
    frames(c, 1400, 1)
    assert "bumped" not in status(c, bump_seen + 10.0)[1]


def test_static_links_are_sent_when_first_known_and_again_when_one_changes():
    c = make_core()
    assert c.static_links_to_send() is None   # nothing known yet
    frames(c, 0, 5)
    links = c.static_links_to_send()
    assert [(p, ch) for p, ch, _ in links] == [("omc", "base"), ("base", "ots")]
    assert np.allclose(links[0][2], T_OMC_BASE) and np.allclose(links[1][2], inv_T(T_OMC_BASE) @ T_OMC_OTS)
    assert c.static_links_to_send() is None   # unchanged
    c.initialize()
    frames(c, 5, 5, bump=SHIFT)
    moved = c.static_links_to_send()
    assert moved is not None and np.allclose(moved[1][2], inv_T(T_OMC_BASE) @ T_OMC_OTS @ SHIFT)


def test_a_tracked_ots_has_no_static_base_ots_link_and_diana_base_is_sent_from_the_start():
    c = make_core(**{"tf.diana_base": [0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0]})
    links = c.static_links_to_send()
    assert [(p, ch) for p, ch, _ in links] == [("base", "diana_base")]
    assert np.allclose(links[0][2][:3, 3], [0.1, 0.2, 0.3])
    t = make_core(local_chain="tracked")
    frames(t, 0, 5, bodies=(("omc", "base"), ("omc", "ots_rig"), ("ots", "base"), ("omc", "tool")))
    assert t.pipes["tool"].chain.links.T_base_ots is not None   # known, but the OTS moves: not static
    assert [(p, ch) for p, ch, _ in t.static_links()] == [("omc", "base")]


def test_final_outputs_of_ordered_processing_are_none():
    c = make_core(processing="ordered")
    frames(c, 0, 10)
    assert type(c.pipes["tool"]) is TargetPipeline and c.final_outputs("tool") == []


def test_the_core_imports_no_ros():
    code = ("import sys, fullperc_fusion.fusion_core; "
            "print(' '.join(m for m in ('rclpy', 'geometry_msgs', 'fullperc_msgs') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", out.stdout


def test_startup_message_names_targets_filters_and_links():
    assert make_core().startup_message() == (
        "fusing targets ['tool'] with cbkf (side by side: none), local chain 'static', clock 'stamps', static "
        "links: others: average of the first 3 samples")


# ---- publisher identity (input_guard) -------------------------------------------------------------------------------
def test_a_closed_input_topics_samples_never_reach_the_pipeline_nor_the_health_nor_the_calibration():
    c = make_core()
    honest, intruder = ("/omc_driver", "01" * 12 + "00000001"), ("/intruder", "02" * 12 + "00000001")
    frames(c, 0, 5)                              # before any check: open (no graph, as offline)
    n_in = c.pipes["tool"].counts["global_in"]
    assert n_in == 5
    c.publishers_seen("/omc/tool/pose", [honest], 0.05)
    c.publishers_seen("/omc/tool/pose", [honest, intruder], 0.06)
    last_rx = c.last_rx["tool"]["omc"]
    assert push(c, "omc", "tool", 5, now=0.07) == [], "routed nowhere"
    assert c.pipes["tool"].counts["global_in"] == n_in and c.last_rx["tool"]["omc"] == last_rx
    assert c.guard.dropped["/omc/tool/pose"] == 1
    assert push(c, "omc", "base", 5, now=0.07) == ["tool"], "the other topics stay open"
    c.quality(("omc", "tool"), 6, T0 + 6 * S // 100, True, 0.1, 5.0)   # its quality topic is open: taken
    assert c.guard.dropped["/omc/tool/quality"] == 0
    c.publishers_seen("/omc/tool/quality", [honest], 0.08)
    c.publishers_seen("/omc/tool/quality", [honest, intruder], 0.08)   # a quality topic closes the same way
    loss = c.book.loss[("omc", "tool")]
    before = (loss.frames_lost, loss.pending)
    c.quality(("omc", "tool"), 500, T0 + S, True, 0.1, 5.0)
    assert (loss.frames_lost, loss.pending) == before and c.guard.dropped["/omc/tool/quality"] == 1
    c.publishers_seen("/omc/tool/pose", [honest], 0.1)   # gone: open once the queue is discarded (the node's part)
    assert push(c, "omc", "tool", 6, now=0.1) == []
    c.guard.settle(0.1)
    assert push(c, "omc", "tool", 7, now=0.11) == ["tool"] and c.pipes["tool"].counts["global_in"] == n_in + 1
    c.start_calibration(0.2)                     # nor does a closed topic feed ~/calibrate
    c.publishers_seen("/omc/base/pose", [honest], 0.2)
    c.publishers_seen("/omc/base/pose", [honest, intruder], 0.2)
    push(c, "omc", "base", 8, now=0.2)
    assert c._cal.collector.last_ns is None
    push(c, "ots", "base", 8, now=0.2)
    assert c._cal.collector.last_ns is not None


def test_a_closed_input_is_an_error_of_every_target_reading_it_naming_topic_node_and_gid():
    c = make_core(targets=["tool", "probe"], **{"probe.omc_body": "probe", "probe.ots_tool": "probe"})
    intruder_gid = "02" * 12 + "00000001"
    frames(c, 0, 20, bodies=(("omc", "base"), ("omc", "tool"), ("omc", "probe"), ("ots", "base"), ("ots", "tool"),
                             ("ots", "probe")))
    c.publishers_seen("/omc/tool/pose", [("/omc_driver", "01" * 12 + "00000001")], 0.2)
    assert status(c, 0.2)[0] < 2
    c.publishers_seen("/omc/tool/pose", [("/omc_driver", "01" * 12 + "00000001"), ("/intruder", intruder_gid)], 0.3)
    level, msg, values = status(c, 0.3)
    assert level == 2 and "/omc/tool/pose" in msg and "/intruder" in msg and intruder_gid in msg, msg
    assert msg.startswith("input /omc/tool/pose closed"), "named first: it explains the rest"
    assert values["inputs_closed"] == "/omc/tool/pose"
    p_level, p_msg, p_values = status(c, 0.3, "probe")
    assert "/intruder" not in p_msg and p_values["inputs_closed"] == "none", "probe does not read /omc/tool/pose"


def test_samples_of_a_publisher_not_named_yet_are_held_then_used_when_it_is_named_and_accepted_else_dropped():
    c = make_core()
    nameless = [("/_NODE_NAME_UNKNOWN_", "01" * 12 + "00000001")]
    honest = [("/omc_driver", "01" * 12 + "00000001")]
    for topic in c.guard.topics:                 # a driver's first samples come before discovery names it
        c.publishers_seen(topic, nameless, 0.0)
    assert push(c, "omc", "base", 0, now=0.01) == [] and push(c, "omc", "tool", 0, now=0.01) == []
    assert c.pipes["tool"].counts["global_in"] == 0 and c.guard.dropped["/omc/tool/pose"] == 0, "held, not used"
    for topic in c.guard.topics:
        c.publishers_seen(topic, honest, 0.02)
    assert push(c, "omc", "tool", 1, now=0.03) == ["tool"]
    assert c.pipes["tool"].counts["global_in"] == 2, "the held sample first, then this one"
    c.publishers_seen("/omc/tool/pose", [*honest, ("/_NODE_NAME_UNKNOWN_", "02" * 12 + "00000001")], 0.1)
    push(c, "omc", "tool", 2, now=0.11)
    c.publishers_seen("/omc/tool/pose", [*honest, ("/intruder", "02" * 12 + "00000001")], 0.12)
    push(c, "omc", "tool", 3, now=0.13)
    assert c.pipes["tool"].counts["global_in"] == 2 and c.guard.dropped["/omc/tool/pose"] == 2, "named, refused"


def test_while_one_publisher_has_no_name_every_input_waits_and_then_goes_in_stamp_order():
    """A driver's first Vega samples come before discovery names it. Holding only its topics put them behind OMC
    samples they preceded, and the static links averaged from the first samples differed from the bag's offline
    evaluation (a demo: 0.056 mm in one column). Every input waits instead (at most the guard's 1 s), and what waited
    goes in stamp order, as offline processing takes it."""
    c = make_core()
    honest = {"omc": [("/omc_driver", "01" * 12 + "00000001")], "ots": [("/ndi_driver", "02" * 12 + "00000001")]}
    for topic in c.guard.topics:
        c.publishers_seen(topic, honest["omc"] if topic.startswith("/omc") else
                          [("/_NODE_NAME_UNKNOWN_", "02" * 12 + "00000001")], 0.0)
    order: list[tuple[str, int]] = []
    pipe = c.pipes["tool"]
    for name in ("push_omc", "push_local"):
        real = getattr(pipe, name)
        setattr(pipe, name, lambda *a, real=real, name=name, **kw: (order.append((name, a[-2])), real(*a, **kw))[1])
    for k in range(3):   # the OTS sample of frame k arrives after the OMC sample of frame k + 1
        push(c, "omc", "base", k + 1, now=0.01)
        push(c, "ots", "base", k, now=0.01)
    assert order == [] and pipe.counts["global_in"] == 0, "the open OMC topic waits too"
    for topic in c.guard.topics:
        if topic.startswith("/ots"):
            c.publishers_seen(topic, honest["ots"], 0.02)
    push(c, "omc", "base", 4, now=0.03)
    stamps = [t for _, t in order]
    assert stamps == sorted(stamps) and len(order) == 7, order
    assert [n for n, _ in order][:2] == ["push_local", "push_omc"], "frame 0's OTS sample before frame 1's OMC one"


def _tool_at(t: float) -> np.ndarray:
    """T_base_tool of a tool waved irregularly (no single period: one cross-correlation peak)."""
    T = T_BASE_TOOL.copy()
    T[:3, 3] += 0.08 * np.array([np.sin(2.1 * t) + 0.5 * np.sin(5.3 * t + 1), np.sin(1.3 * t + 2),
                                 0.4 * np.sin(4.1 * t + 0.3)])
    return T


def test_vega_stamps_late_by_more_than_half_the_slop_warn_on_the_targets_status():
    """The core feeds every accepted target sample (stamp, position in its device's frame) to the health's
    stamp-offset watch: a tool moving irregularly, the Vega's stamps 8 ms late (slop 4 ms) -> a WARN naming it."""
    c = make_core(slop=0.004)
    now = 0.0
    for k in range(int(12 * HZ)):
        now = t = k / HZ
        for dev, body in (("omc", "base"), ("omc", "tool"), ("ots", "base"), ("ots", "tool")):
            T_dev_base = T_OMC_BASE if dev == "omc" else inv_T(T_OMC_OTS) @ T_OMC_BASE
            # the Vega saw its tool pose 8 ms before the stamp it gives it: its stamps are late
            T = T_dev_base if body == "base" else T_dev_base @ _tool_at(t - 0.008 if dev == "ots" else t)
            push(c, dev, body, k, now, T=T)
        c.poll("tool", None)
        if k % int(HZ) == 0:
            status(c, now)   # the diagnostics timer: starts the estimate once 10 s of stamps are in
    job = c.health["tool"].offset._job   # the estimate runs on the worker thread: its result at a later status
    _until(lambda: not job.running or job.ready or None)
    level, msg, values = status(c, now)
    assert level == WARN and "stamps are late by" in msg, msg
    assert abs(values["stamp_offset_ms"] - 8.0) < 0.5, values
