"""fusion_health: the alarm rules on made-up times (no clock, no ROS)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from fullperc_common.testing import wait_for
from fullperc_fusion.fusion_health import ERROR, GLOBAL, LOCAL, WARN, HealthParams, StampOffsetWatch, TargetHealth

SOURCES = {GLOBAL: "OMC body 'tool'", LOCAL: "OTS tool 'tool'"}
Z = np.zeros(3)
G_BIT, L_BIT, BOTH = 1, 2, 3     # FusionStatus.sources bits


def _h(**kw) -> TargetHealth:
    return TargetHealth("tool", SOURCES, HealthParams(**kw))


def _stream(h, t0, t1, rate=120.0, hop_at=(), bias=Z, sources=BOTH):
    """Primary outputs at ``rate`` Hz from t0 to t1 (both sources accepted and used), hops at the given times."""
    hops = sorted(hop_at)
    for k in range(int(round((t1 - t0) * rate))):
        t = t0 + k / rate
        for s in (GLOBAL, LOCAL):
            h.accepted(s, t)
        hop = bool(hops) and t >= hops[0]
        if hop:
            hops.pop(0)
        h.output(t, sources, hop, bias)


def test_defaults_are_the_documented_ones():
    assert HealthParams() == HealthParams(hop_window_s=2.0, hop_max=5, bias_max_m=0.02, reject_timeout_s=1.0,
                                          hold_s=10.0)


@pytest.mark.parametrize("kw", [dict(hop_window_s=0.0), dict(hop_max=0), dict(hop_max=2.5), dict(bias_max_m=-1.0),
                                dict(reject_timeout_s=math.nan), dict(hold_s=math.inf), dict(hop_max=True)])
def test_bad_parameters_are_refused(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        HealthParams(**kw).validate()


def test_a_single_hop_is_no_alarm():
    """A hop when the set of seeing cameras changes is normal: FusionStatus only (and a count on diagnostics)."""
    h = _h()
    _stream(h, 0.0, 10.0, hop_at=[3.0, 7.5])
    assert h.alarms(10.0) == []
    assert h.values(10.0)["hops_total"] == 2


def test_hop_max_hops_in_the_window_is_still_no_alarm_one_more_is():
    h = _h(hop_window_s=2.0, hop_max=5)
    _stream(h, 0.0, 1.9, hop_at=[0.1, 0.5, 0.9, 1.3, 1.7])      # 5 within 2 s: allowed
    assert h.alarms(1.9) == []
    _stream(h, 1.9, 2.2, hop_at=[2.15])                         # 0.1 is out of the window at 2.15: still 5
    assert h.alarms(2.2) == []
    _stream(h, 2.2, 2.6, hop_at=[2.3])                          # 0.5 .. 2.3: 6 within 2 s
    [a] = h.alarms(2.6)
    assert a.level == WARN and a.rule == "hop_rate" and a.source == GLOBAL
    assert "'tool'" in a.message and "OMC body 'tool'" in a.message and "6 hops within 2 s" in a.message


def test_a_sustained_hop_rate_warns_and_the_warning_is_held_then_clears():
    h = _h(hold_s=10.0)
    _stream(h, 0.0, 3.0, hop_at=[0.2 * k for k in range(1, 15)])   # 5 hops/s
    assert [a.rule for a in h.alarms(3.0)] == ["hop_rate"]
    _stream(h, 3.0, 12.0)                                           # calm again (the last hop was at ~2.8 s)
    # the condition ends when the 6th newest hop (~1.8 s) leaves the 2 s window, ~3.8 s; held 10 s after that
    [a] = h.alarms(12.0)
    assert "cleared" in a.message                                   # held, and says so
    assert h.alarms(13.7) != []
    assert h.alarms(13.9) == []


def test_an_implausible_compensation_warns_naming_target_and_source():
    h = _h(bias_max_m=0.02)
    _stream(h, 0.0, 1.0, bias=np.array([0.0, 0.0, 0.0199]))
    assert h.alarms(1.0) == []
    h.output(1.0, BOTH, False, np.array([0.012, 0.0, 0.016]))      # |b| = 20.0 mm: not above
    assert h.alarms(1.0) == []
    h.output(1.01, BOTH, False, np.array([0.0, -1.0, 0.0]))
    [a] = h.alarms(1.01)
    assert a.level == WARN and a.rule == "bias" and a.source == GLOBAL
    assert "'tool'" in a.message and "OMC body 'tool'" in a.message and "1000.0 mm > 20.0 mm" in a.message
    h.output(1.02, BOTH, False, np.array([np.nan, 0, 0]))          # a non-finite bias is implausible too
    assert h.values(1.02)["bias_norm_mm"] == math.inf


def test_a_one_metre_jump_warns_on_the_first_output_with_the_learned_bias():
    """What issue 14 saw: one hop, then b = 1 m. The bias rule fires without waiting for a hop rate."""
    h = _h()
    _stream(h, 0.0, 5.0, bias=np.array([1e-3, 0, 0]))
    h.output(5.0, BOTH, True, np.array([0.3, 0, 0]))               # the gain moved part of the step into b
    assert [a.rule for a in h.alarms(5.0)] == ["bias"]


def test_every_sample_rejected_for_longer_than_the_timeout_is_an_error():
    h = _h(reject_timeout_s=1.0)
    _stream(h, 0.0, 2.0)
    t = 2.0
    while t < 2.99:                     # 120 Hz of NaN poses; outputs of earlier samples still come out meanwhile
        h.rejected(GLOBAL, t, "OMC body 'tool': non-finite pose")
        h.output(t + 0.05, L_BIT | (G_BIT if t < 2.1 else 0), False, Z)
        h.accepted(LOCAL, t)
        t += 1 / 120
    assert h.alarms(2.99) == []         # 0.99 s of rejections
    h.rejected(GLOBAL, 3.0, "OMC body 'tool': non-finite pose")
    [a] = h.alarms(3.0)
    assert a.level == ERROR and a.rule == "rejected" and a.source == GLOBAL
    assert "'tool'" in a.message and "OMC body 'tool'" in a.message and "non-finite pose" in a.message
    assert h.values(3.0)["global_rejected_run_s"] == pytest.approx(1.0)
    # the local source is fine and is not named
    assert all(a.source == GLOBAL for a in h.alarms(3.0))


def test_a_run_taken_in_one_burst_lasts_as_long_as_its_stamps():
    """A node behind takes 2 s of a source's refused samples in 0.1 s (the CI failure: no ERROR for 2.5 s of NaN
    poses): by its clock the run never lasts the timeout, by the samples' stamps it does. Without stamps (the caller
    passes none for a sample refused for its stamp) only the clock counts."""
    S, T0 = 1_000_000_000, 1_700_000_000_000_000_000

    def burst(stamps: bool) -> TargetHealth:
        h = _h(reject_timeout_s=1.0)
        for k in range(240):
            h.rejected(GLOBAL, 5.0 + k * 0.1 / 240, "OMC body 'tool': non-finite pose",
                       t_ns=T0 + k * S // 120 if stamps else None)
        return h

    h = burst(stamps=True)
    [a] = h.alarms(5.2)
    assert a.rule == "rejected" and "rejected for 2.0 s (240 samples" in a.message
    assert h.values(5.2)["global_rejected_run_s"] == round(239 / 120, 3)
    assert burst(stamps=False).alarms(5.2) == []
    assert burst(stamps=False).values(5.2)["global_rejected_run_s"] == pytest.approx(0.2)
    # a run's stamps are its own: after a used sample the next run starts from its own first stamp
    h.accepted(GLOBAL, 5.3)
    h.output(5.3, G_BIT, False, Z)
    h.rejected(GLOBAL, 5.4, "x", t_ns=T0 + 10 * S)
    assert h.values(5.4)["global_rejected_run_s"] == 0.0


def test_a_few_rejected_samples_between_good_ones_are_no_error():
    h = _h(reject_timeout_s=1.0)
    for k in range(600):               # 5 s at 120 Hz, every 10th sample rejected
        t = k / 120
        if k % 10 == 0:
            h.rejected(GLOBAL, t, "late")
        else:
            h.accepted(GLOBAL, t)
            h.output(t, G_BIT, False, Z)
    assert h.alarms(5.0) == []


def test_one_rejection_then_silence_is_no_error():
    """A source that sent one bad sample and then nothing is silent (the node says so), not 'all rejected'."""
    h = _h(reject_timeout_s=1.0)
    h.rejected(LOCAL, 1.0, "non-unit quaternion")
    assert h.alarms(1.5) == [] and h.alarms(2.5) == [] and h.alarms(30.0) == []


def test_the_error_ends_with_a_used_sample_and_is_held():
    h = _h(reject_timeout_s=1.0, hold_s=10.0)
    for k in range(240):
        h.rejected(LOCAL, k / 120, "local sample skipped: no rig pose near this stamp")
    assert [a.level for a in h.alarms(2.0)] == [ERROR]
    h.output(2.01, BOTH, False, Z)      # a local sample accepted before the run is no recovery
    assert h.values(2.01)["local_rejected_run_s"] > 0
    h.accepted(LOCAL, 2.02)
    h.output(2.05, BOTH, False, Z)      # used after the run started: the run ends
    assert h.values(2.05)["local_rejected_run_s"] == 0.0
    [a] = h.alarms(3.0)
    assert a.level == ERROR and "cleared" in a.message
    assert h.alarms(2.0 + 10.0 + 1e-6) == []


def test_alarms_are_sorted_most_severe_first():
    h = _h(reject_timeout_s=0.5)
    h.output(0.0, BOTH, False, np.array([0.5, 0, 0]))
    for k in range(100):
        h.rejected(LOCAL, 0.01 * k, "x")
    assert [a.level for a in h.alarms(1.0)] == [ERROR, WARN]


# ---- overload: lost samples and input load (issue 16 item 5) --------------------------------------------------
def test_source_loss_counts_frame_gaps_and_visible_frames_without_pose():
    from fullperc_fusion.fusion_verdict import SourceLoss

    loss = SourceLoss(match_ns=100)
    for fn in (1, 2, 3, 7, 8):            # quality of frames 4-6 missing
        loss.quality(fn, fn * 10, visible=fn != 8)
    for fn in (1, 3, 5):                  # poses of frames 1, 3 and 5 arrived; 2 and 7 did not (yet), 8 not visible
        loss.pose(fn * 10)
    assert loss.frames_lost == 3 and loss.samples_lost == 3 - 1, "gap frames 4 and 6: no pose either"
    loss.quality(30, 300, visible=True)   # quality of 9-29 missing; pose 50's quality is overdue (an orphan)
    assert loss.frames_lost == 3 + 21 and loss.samples_lost == 0 + (3 + 21 - 1), "2 and 7 wait for a newer pose"
    loss.pose(300)                        # a pose 100 stamp-ns past them: the poses of 2 and 7 are overdue
    assert loss.frames_lost == 3 + 21 and loss.samples_lost == 2 + (3 + 21 - 1)
    loss.quality(1, 310, visible=False)   # counter restarted: a new count, no gap
    assert loss.frames_lost == 24


def test_source_loss_pose_before_its_quality_is_not_lost():
    from fullperc_fusion.fusion_verdict import SourceLoss

    loss = SourceLoss(match_ns=100)
    loss.pose(10)
    loss.quality(1, 10, visible=True)
    loss.quality(2, 500, visible=False)
    assert loss.lost == 0 and loss.frames_lost == 0


def test_source_loss_with_the_quality_seconds_ahead_of_the_poses_counts_nothing_lost():
    """A node lagging in its pose callbacks takes the quality messages seconds ahead of the poses of the same frames
    (each topic in order): a visible frame is overdue only once a pose match_ns newer came, not a quality message.
    Settled by either topic's newest stamp, the demo on a busy machine counted 678 of its fused OMC samples lost."""
    from fullperc_fusion.fusion_verdict import SourceLoss

    loss = SourceLoss(match_ns=100)
    for fn in range(1, 51):               # 500 stamp-ns of quality first (5 x match_ns)
        loss.quality(fn, fn * 10, visible=True)
    assert (loss.samples_lost, loss.pending) == (0, 50)
    for fn in range(1, 51):               # then the poses of the same frames, frame 30's missing
        if fn != 30:
            loss.pose(fn * 10)
    assert (loss.samples_lost, loss.frames_lost, loss.pending) == (1, 0, 0), "only frame 30's pose, once 410 came"


def test_source_loss_settles_the_tail_of_a_stream_when_the_caller_says_it_ended():
    """A pose lost in a stream's last match_ns is counted only once the caller says the source went silent: no
    later sample would ever settle it (1 kHz test: the node's last /diagnostics never accounted for every sample)."""
    from fullperc_fusion.fusion_verdict import SourceLoss

    loss = SourceLoss(match_ns=100)
    for fn in range(1, 6):
        loss.quality(fn, fn * 10, visible=True)
        if fn != 4:                       # the pose of frame 4 (stamp 40) never comes
            loss.pose(fn * 10)
    loss.pose(60)                         # a pose whose quality never comes
    assert (loss.samples_lost, loss.pending) == (0, 2), "nothing is 100 stamp-ns overdue yet"
    loss.end_of_stream()
    assert (loss.samples_lost, loss.frames_lost, loss.pending) == (1, 0, 0)
    loss.quality(6, 60, visible=True)     # the stream resumes: counting goes on from there
    loss.pose(70)
    loss.quality(7, 70, visible=True)
    loss.quality(8, 300, visible=True)
    loss.pose(300)                        # a pose 100 stamp-ns newer than frame 6's stamp settles it
    assert (loss.samples_lost, loss.frames_lost) == (2, 0), "frame 6's pose came before the silence: now unmatched"


def test_input_load_keeps_the_period_maximum():
    from fullperc_fusion.fusion_verdict import InputLoad

    load = InputLoad()
    load.callback(3, 2_000_000, 40_000_000)
    load.callback(0, None, 5_000_000)
    load.callback(1, 1_000_000, None)     # no clock yet: lag unknown
    assert (load.depth_max, load.lag_min_ns) == (3, 5_000_000)   # the window, for the overload verdict
    load.begin_report(previous_published=True)
    v = load.values()
    assert (v["queue_depth"], v["queue_depth_max"], v["lag_ms"], v["lag_min_ms"], v["lag_max_ms"],
            v["callback_delay_max_ms"], v["input_callbacks"]) == (1, 3, 5.0, 5.0, 40.0, 2.0, 3)
    load.reset_period()
    assert (load.depth_max, load.lag_min_ns) == (0, None)
    load.begin_report(previous_published=True)
    assert load.values()["lag_max_ms"] is None and load.values()["lag_ms"] == 5.0


def test_input_load_reports_every_window_until_a_report_is_published():
    """The node evaluates every 0.5 s and /diagnostics goes out every 1 s: a burst in a window whose report was
    replaced before it was published must still show in the next report (it used to be lost: a node catching up
    after a stall could report no lag at all)."""
    from fullperc_fusion.fusion_verdict import InputLoad

    load = InputLoad()
    load.callback(50, 3_000_000, 900_000_000)            # the burst
    load.begin_report(previous_published=False)
    load.reset_period()
    load.callback(0, 1_000_000, 2_000_000)               # quiet window; the burst's report was never published
    load.begin_report(previous_published=False)
    v = load.values()
    assert (v["queue_depth_max"], v["lag_max_ms"], v["lag_min_ms"], v["callback_delay_max_ms"],
            v["input_callbacks"]) == (50, 900.0, 2.0, 3.0, 2)
    assert (load.depth_max, load.lag_min_ns) == (0, 2_000_000)   # the verdict still looks at its own window only
    load.reset_period()
    load.begin_report(previous_published=True)           # that report went out: the next starts afresh
    v = load.values()
    assert (v["queue_depth_max"], v["lag_max_ms"], v["input_callbacks"]) == (0, None, 0)


def test_input_load_reports_each_stage():
    """InputLoad's report: callback delay, the wake-up's own work and their sum, per callback; a callback without
    rclpy's message info (the events executor) adds no delay and no sum, only its work."""
    from fullperc_fusion.fusion_verdict import InputLoad

    load = InputLoad()
    load.callback(0, 2_000_000, None, 500_000)
    load.callback(0, None, None, 8_000_000)
    load.callback(1, 1_000_000, None, 1_000_000)
    load.begin_report(previous_published=True)
    v = load.values()
    assert v["callback_delay_max_ms"] == 2.0 and v["wakeup_max_ms"] == 8.0 and v["received_to_published_max_ms"] == 2.5
    assert 1.0 <= v["callback_delay_p50_ms"] <= 1.0 * 1.22          # of 1 and 2 ms: the 1 ms one's bin
    assert 1.0 <= v["wakeup_p50_ms"] <= 1.22 and v["wakeup_p99_ms"] == 8.0
    assert 2.0 <= v["received_to_published_p50_ms"] <= 2.0 * 1.22   # of 2.0 and 2.5 ms
    # an unpublished report keeps its callbacks: the next one adds them (as for the other figures)
    load.reset_period()
    load.callback(0, 50_000_000, None, 100_000)
    load.begin_report(previous_published=False)
    v = load.values()
    assert v["callback_delay_max_ms"] == 50.0 and v["input_callbacks"] == 4 and v["wakeup_max_ms"] == 8.0


# ------------------------------------------------------------------------------------------- stamp offset
def _waving(t: np.ndarray) -> np.ndarray:
    """An irregular hand-like motion [m] (no single period: the cross-correlation has one peak)."""
    return 0.08 * np.stack([np.sin(2.1 * t) + 0.5 * np.sin(5.3 * t + 1), np.sin(1.3 * t + 2) * np.cos(3.7 * t),
                            0.4 * np.sin(4.1 * t + 0.3)], axis=1)


def _feed(h: TargetHealth, late_s: float, seconds: float = 12.0, seed: int = 0) -> None:
    """OMC 120 Hz (0.2 mm noise) and Vega 60 Hz (0.1 mm, its own frame: rotated and shifted) of one motion, the
    Vega's stamps ``late_s`` late; alarms asked for once a second as the node's diagnostics timer does."""
    rng = np.random.default_rng(seed)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    tg, tl = np.arange(0, seconds, 1 / 120), np.arange(0.003, seconds, 1 / 60)
    pg = _waving(tg) + rng.normal(0, 2e-4, (tg.size, 3))
    pl = _waving(tl) @ R.T + [1.0, 2.0, 0.5] + rng.normal(0, 1e-4, (tl.size, 3))
    ev = sorted([(t, GLOBAL, p) for t, p in zip(tg, pg, strict=True)]
                + [(t + late_s, LOCAL, p) for t, p in zip(tl, pl, strict=True)], key=lambda e: e[0])
    next_diag = 1.0
    for t, s, p in ev:
        h.accepted(s, t, int(round(t * 1e9)), p)
        if t >= next_diag:
            h.alarms(t)
            next_diag += 1.0


@pytest.mark.parametrize("late_ms", [10.0, -6.0])
def test_vega_stamps_off_by_more_than_half_the_slop_are_a_warn_naming_the_offset(late_ms):
    h = _h(offset_warn_s=0.002, offset_window_s=10.0, offset_period_s=10.0)
    _feed(h, late_ms * 1e-3)
    [a] = [a for a in h.alarms(12.0) if a.rule == "stamp_offset"]
    assert a.level == WARN and a.source == LOCAL
    word = "late" if late_ms > 0 else "early"
    m = re.search(rf"stamps are {word} by ([0-9.]+) ms", a.message)
    assert m and abs(float(m[1]) - abs(late_ms)) < 0.5 and "time_align" in a.message, a.message
    v = h.values(12.0)
    assert abs(v["stamp_offset_ms"] - late_ms) < 0.5 and v["stamp_offset_sigma_ms"] < 0.5, v


def test_stamps_within_half_the_slop_raise_nothing_and_still_report_the_offset():
    h = _h(offset_warn_s=0.002, offset_window_s=10.0, offset_period_s=10.0)
    _feed(h, 0.001)
    assert not [a for a in h.alarms(12.0) if a.rule == "stamp_offset"]
    assert abs(h.values(12.0)["stamp_offset_ms"] - 1.0) < 0.5


def test_a_still_target_gives_no_estimate_and_no_alarm():
    h = _h(offset_warn_s=0.002)
    for k in range(1500):
        t = k / 120
        h.accepted(GLOBAL, t, int(t * 1e9), np.zeros(3))
        h.accepted(LOCAL, t + 0.01, int((t + 0.01) * 1e9), np.ones(3))
        if k % 120 == 0:
            h.alarms(t)
    assert not [a for a in h.alarms(13.0) if a.rule == "stamp_offset"]
    assert "stamp_offset_ms" not in h.values(13.0)


def test_a_late_sample_is_skipped_and_a_restarted_timeline_starts_the_window_anew():
    h = _h()
    w = h.offset
    for k in range(10):
        w.add(GLOBAL, k * 10_000_000, np.full(3, k))
    w.add(GLOBAL, 45_000_000, np.zeros(3))          # late (arrived after 90 ms): not put out of order
    w.add(GLOBAL, 92_000_000, np.zeros(3))          # 2 ms after the newest: above 250 Hz, skipped
    assert [t for t, _ in w.rings[GLOBAL]] == [k * 10_000_000 for k in range(10)]
    w.add(LOCAL, 95_000_000, np.zeros(3))
    w.add(GLOBAL, 100_000_000 - 20_000_000_000, np.zeros(3))   # 20 s back: a new timeline
    assert [t for t, _ in w.rings[GLOBAL]] == [-19_900_000_000] and not w.rings[LOCAL]


def _wait_for(job) -> None:
    """Until ``job``'s worker call has finished (a liveness bound, not a time limit on the work)."""
    wait_for(lambda: not job.running or job.ready, 60.0, 0.01, what="the background estimate")


def test_in_the_background_the_estimate_comes_at_a_later_call_and_equals_the_one_made_at_once():
    """fusion_node's form (background=True): the call that starts the estimate returns None at once (the input
    path is not held for it); a call after the worker finished gives the same Alignment the synchronous form
    gives, once; a TargetHealth made with background raises the same alarm from it."""
    rng = np.random.default_rng(0)
    t = np.arange(0, 10.5, 1 / 120)
    p = _waving(t) + rng.normal(0, 2e-4, (t.size, 3))
    watches = [StampOffsetWatch(10.0, 10.0), StampOffsetWatch(10.0, 10.0, background=True)]
    for w in watches:
        for tk, pk in zip(t, p, strict=True):
            w.add(GLOBAL, int(round(tk * 1e9)), pk)
            w.add(LOCAL, int(round((tk + 0.01) * 1e9)), pk + 1.0)
    sync, bg = watches
    a = sync.estimate()
    assert a is not None and abs(a.offset_s - 0.01) < 5e-4
    assert bg.estimate() is None and bg._job.running
    _wait_for(bg._job)
    b = bg.estimate()
    assert b is not None and b.offset_s == a.offset_s and bg.last is b
    assert bg.estimate() is None and not bg._job.running      # given once; the next is due 10 s of stamps later

    h = TargetHealth("tool", SOURCES, HealthParams(offset_warn_s=0.002, offset_window_s=10.0,
                                                    offset_period_s=10.0), background=True)
    assert h.offset._job.background
    _feed(h, 0.010)
    _wait_for(h.offset._job)
    [al] = [x for x in h.alarms(12.0) if x.rule == "stamp_offset"]
    m = re.search(r"late by ([0-9.]+) ms", al.message)
    assert al.level == WARN and m and abs(float(m[1]) - 10.0) < 0.5, al.message


# ---- the node's core: which stamps time a run ------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["nan_pose", "hour_ahead"])
def test_the_core_times_a_run_by_the_stamps_of_samples_refused_for_their_pose_only(bad):
    """fusion_core passes the stamp of a sample the pipeline refused for its pose (NaN: its stamp is good) and not
    of one refused for its stamp (an hour ahead of the node clock: the stamp says nothing about when it was sent)."""
    from fullperc_fusion.fusion_config import read_values
    from fullperc_fusion.fusion_core import FusionCore

    S, T0 = 1_000_000_000, 1_700_000_000_000_000_000
    c = FusionCore(read_values(lambda n, d: {"alarm.reject_timeout": 1.0}.get(n, d)), now=0.0)
    p, q = np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 0.0, 1.0])
    for k in range(240):   # 2 s of samples at 120 Hz, taken in a burst of 0.1 s
        t = T0 + k * S // 120
        c.on_pose("omc", "tool", t, np.full(3, np.nan) if bad == "nan_pose" else p, q, k * 0.1 / 240,
                  t - 3600 * S if bad == "hour_ahead" else 0)
    assert c.pipes["tool"].counts["rejected_nonfinite" if bad == "nan_pose" else "rejected_future"] == 240
    rules = [a.rule for a in c.health["tool"].alarms(0.2)]
    assert rules == (["rejected"] if bad == "nan_pose" else [])
