"""The local chain's frame in fullperc's output (issue 18): the link's covariance in the reported pose covariance,
and the estimate moved with the frame when the calibrated link replaces the bridge average.

Device-level synthetic streams (OMC 120 Hz, Vega 60 Hz). The Vega's sightings of the base marker are noisy in
rotation (5 mrad per axis), so the bridge link (the mean of the first 30 sightings) and the calibrated link (2 s of
sightings) differ by a millimetre or more at the tool: the two frames are told apart far above the OMC's noise.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fullperc_common.transforms import inv_T, mean_T
from fullperc_fusion.calibration.monitor import MonitorParams
from fullperc_fusion.calibration.se3_stats import se3_retract
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.measurement_models import link_covariance_at
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

sys.path.insert(0, str(Path(__file__).parent))
from test_pipeline_links import BUMP, T0, T_OMC_BASE, T_OMC_OTS, S, run, truth  # noqa: E402  (the same OR and path)

SIG_BASE = np.array([0.05e-3, 0.05e-3, 0.15e-3, 5e-3, 5e-3, 5e-3])   # the Vega's sightings of the base marker
OMC_BIAS = np.array([1.5e-3, -1.0e-3, 0.5e-3])                       # the OMC's error at the tool (the bias b)


def stream(seconds, tool_seen_until, seed=3, bump_at=None):
    """(device, body, t_ns, T) in stamp order; the Vega sees the tool until ``tool_seen_until`` s (the base marker
    all the time), the OMC both all the time; from ``bump_at`` s on the Vega stands 3 mm further along its x."""
    rng = np.random.default_rng(seed)
    ev = []
    for k in range(int(seconds * 120)):
        t = k / 120
        ns = T0 + round(t * S)
        ev.append(("omc", "base", ns, T_OMC_BASE))
        Tm = T_OMC_BASE @ truth(t)
        Tm[:3, 3] += T_OMC_BASE[:3, :3] @ OMC_BIAS + rng.normal(0, 1e-4, 3)
        ev.append(("omc", "tool", ns, Tm))
        if k % 2 == 0:
            nl = ns + 3_000_000
            ots = T_OMC_OTS @ BUMP if bump_at is not None and t >= bump_at else T_OMC_OTS
            ev.append(("ots", "base", nl, se3_retract(inv_T(ots) @ T_OMC_BASE, rng.normal(size=6) * SIG_BASE)))
            if t < tool_seen_until:
                ev.append(("ots", "tool", nl, inv_T(ots) @ T_OMC_BASE @ truth(t + 0.003)))
    return ev


class Recording(FullpercFilter):
    """fullperc, keeping the pose covariance of each step it returned (what the filter itself reports)."""

    def __init__(self, params=None) -> None:
        super().__init__(params)
        self.pose_covs: dict[int, np.ndarray] = {}

    def update(self, *ms):
        st = super().update(*ms)
        self.pose_covs[st.t_ns] = st.pose_cov
        return st


def _pipe(cls=TargetPipeline, monitor=None, **chain):
    chain = {"static_links": "calibrate", "calibration_duration_s": 2.0, **chain}
    kw = {} if monitor is None else {"monitor": monitor}
    return cls(TargetConfig(chain=ChainConfig(**chain), filters=("fullperc", "cbkf"), **kw))


def test_the_output_covariance_adds_the_links_own_covariance_at_the_tool():
    """C_out = P_pose + J(l) C_link J(l)^T with l from the link's origin to the estimate, for fullperc only."""
    pipe = _pipe(calibration_duration_s=10.0)           # the bridge average all along
    rec = pipe.filters["fullperc"] = Recording(pipe.config.params)
    outs = [o for o in run(pipe, stream(1.5, tool_seen_until=1.5)) if o.filter == "fullperc"]
    L = pipe.chain.links
    est, T = L.estimates["T_base_ots"], L.T_base_ots
    assert est.n_samples == 30 and "average of 30" in L.sources["T_base_ots"]
    after = [o for o in outs if o.t_local is not None and o.t_ns > T0 + round(0.6 * S)]
    assert len(after) > 40
    for o in after:
        extra = link_covariance_at(est.cov, o.p - T[:3, 3])
        np.testing.assert_allclose(o.cov, rec.pose_covs[o.t_ns] + extra, rtol=1e-12, atol=1e-18)
    # the term is what dominates where the Vega sees the tool: a noisy 30-sample link is ~mm at 2-3 m
    o = after[-1]
    assert np.trace(o.cov[:3, :3]) > 4 * np.trace(rec.pose_covs[o.t_ns][:3, :3])


def test_no_link_covariance_without_a_link_estimate():
    """A link given as a parameter has no covariance: the output's covariance is the filter's."""
    T_base_ots = inv_T(T_OMC_BASE) @ T_OMC_OTS
    pipe = _pipe(T_base_ots=T_base_ots)
    rec = pipe.filters["fullperc"] = Recording(pipe.config.params)
    outs = [o for o in run(pipe, stream(1.0, tool_seen_until=1.0)) if o.filter == "fullperc"]
    assert "T_base_ots" not in pipe.chain.links.estimates and len(outs) > 100
    for o in outs:
        np.testing.assert_array_equal(o.cov, rec.pose_covs[o.t_ns])


def _frame_errors(outs, name, T_link, t_from):
    """Mean distance [mm] of the filter's outputs from the truth expressed through the link T_link (the position
    the local chain would report with that link)."""
    T_ots_base = inv_T(T_OMC_OTS) @ T_OMC_BASE
    d = []
    for o in outs:
        if o.filter == name and o.t_ns >= T0 + round(t_from * S):
            p_true = T_link @ T_ots_base @ truth((o.t_ns - T0) / S)
            d.append(np.linalg.norm(o.p - p_true[:3, 3]) * 1e3)
    return float(np.mean(d))


def test_the_estimate_moves_with_the_frame_when_the_calibrated_link_replaces_the_bridge():
    """The Vega loses the tool at 1.2 s, the calibrated link replaces the bridge at 2 s: fullperc's OMC-only outputs
    follow the new frame (b learnt against the old one is carried over), CBKF's stay in the old one."""
    ev = stream(4.0, tool_seen_until=1.2)
    pipe = _pipe()
    outs = run(pipe, ev)
    L = pipe.chain.links
    assert "robust mean over 2 s" in L.sources["T_base_ots"]
    assert pipe.counts["frame_moves"] == 1
    bridge = mean_T([inv_T(T) for d, b, _, T in ev if (d, b) == ("ots", "base")][:30])
    calibrated = L.T_base_ots
    tool = (inv_T(T_OMC_OTS) @ T_OMC_BASE @ truth(3.0))[:, 3]
    apart = np.linalg.norm((calibrated - bridge) @ tool) * 1e3
    assert apart > 0.35                           # [mm] the frames differ by far more than the OMC's noise
    f_new, f_old = _frame_errors(outs, "fullperc", calibrated, 2.5), _frame_errors(outs, "fullperc", bridge, 2.5)
    c_new, c_old = _frame_errors(outs, "cbkf", calibrated, 2.5), _frame_errors(outs, "cbkf", bridge, 2.5)
    assert f_new < 0.4 * f_old and c_old < 0.4 * c_new


def test_a_re_calibration_after_a_bump_moves_the_estimate_to_the_vegas_new_place():
    """The Vega is bumped 3 mm at 3 s and loses the tool at 4.5 s; the link monitor re-calibrates (2 s): fullperc's
    OMC-only outputs afterwards are back on the truth, CBKF's stay off by the bump (its bias was learnt against the
    bumped Vega's samples, mapped through the old link)."""
    pipe = _pipe(monitor=MonitorParams(window_s=0.5, recalibrate=True))
    outs = run(pipe, stream(9.0, tool_seen_until=4.5, bump_at=3.0))
    assert pipe.counts["recalibrations"] == 1 and pipe.counts["frame_moves"] == 2   # bridge -> calibrated -> new
    err = {name: np.median([np.linalg.norm(o.p - truth((o.t_ns - T0) / S)[:3, 3]) * 1e3 for o in outs
                            if o.filter == name and o.t_ns > T0 + round(7.5 * S)]) for name in ("fullperc", "cbkf")}
    assert err["fullperc"] < 0.25 * err["cbkf"] and err["cbkf"] > 2.0, err   # what is left: the new link's noise


def test_no_move_before_a_local_sample_was_fused():
    """A link change before the Vega ever saw the tool: the estimate is not tied to a frame yet, nothing moves."""
    pipe = _pipe()
    run(pipe, stream(3.0, tool_seen_until=0.0))
    assert "robust mean over 2 s" in pipe.chain.links.sources["T_base_ots"] and pipe.counts["frame_moves"] == 0


def test_arrival_processing_moves_the_estimate_as_ordered_processing_does():
    """Final estimates of processing on arrival equal ordered processing of the same input exactly, the move with
    the frame included, with samples up to 30 ms out of order (rewinds and replays across the link change)."""
    ev = stream(3.0, tool_seen_until=1.2)
    rng = np.random.default_rng(5)
    recv = [e[2] + int(rng.uniform(0, 30_000_000)) for e in ev]
    shuffled = [e for _, e in sorted(zip(recv, ev, strict=True), key=lambda x: x[0])]
    ordered_pipe = _pipe()
    ordered = {o.t_ns: o for o in run(ordered_pipe, shuffled) if o.filter == "fullperc"}
    pipe = _pipe(ArrivalPipeline)
    final = []
    for dev, body, t, T in shuffled:
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, t, T)
        pipe.poll()
        final += pipe.take_final()
    pipe.flush()
    final = {o.t_ns: o for o in final + pipe.take_final() if o.filter == "fullperc"}
    assert pipe.counts["frame_moves"] == ordered_pipe.counts["frame_moves"] == 1 and pipe.counts["rewinds"] > 0
    assert final.keys() == ordered.keys() and len(final) > 300
    for t, o in ordered.items():
        assert np.array_equal(final[t].p, o.p) and np.array_equal(final[t].cov, o.cov), t
