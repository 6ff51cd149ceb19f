"""TargetPipeline with the static-link machinery: link monitoring (a bumped Vega), re-calibration, calibrate mode.

Device-level synthetic streams (OMC 120 Hz, Vega 60 Hz, made-up stamps); the Vega is bumped by moving the OTS
frame itself, so its views of the base marker and of the tool both change, as in an OR.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion.calibration.monitor import MonitorParams
from fullperc_fusion.calibration.se3_stats import se3_retract
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

S = 1_000_000_000
T0 = 1_700_000_000 * S
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_OTS = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
BUMP = make_T([3e-3, 0.0, 0.0])        # the Vega is pushed 3 mm along its own x axis
SIG_VEGA = np.array([0.05e-3, 0.05e-3, 0.15e-3, 1e-3, 1e-3, 1e-3])


def truth(t):
    return make_T([0.5 + 0.1 * np.cos(0.3 * t), 0.1 * np.sin(0.3 * t), 0.3], Rot.from_euler("z", 5 * t, degrees=True)
                  .as_quat())


def stream(seconds, bump_at=None, seed=0, move_base_at=None):
    """(device, body, t_ns, T) in stamp order; the Vega bumped at ``bump_at`` s, the OMC base marker moved 5 mm at
    ``move_base_at`` s."""
    rng = np.random.default_rng(seed)
    ev = []
    for k in range(int(seconds * 120)):
        t = k / 120
        ns = T0 + round(t * S)
        base = T_OMC_BASE.copy()
        if move_base_at is not None and t >= move_base_at:
            base[:3, 3] += [5e-3, 0, 0]
        ev.append(("omc", "base", ns, se3_retract(base, rng.normal(size=6) * 2e-4)))
        ev.append(("omc", "ots_rig", ns, T_OMC_OTS))
        ev.append(("omc", "tool", ns, T_OMC_BASE @ truth(t)))
        if k % 2 == 0:
            ots = T_OMC_OTS @ BUMP if bump_at is not None and t >= bump_at else T_OMC_OTS
            nl = ns + 3_000_000
            ev.append(("ots", "base", nl, se3_retract(inv_T(ots) @ T_OMC_BASE, rng.normal(size=6) * SIG_VEGA)))
            ev.append(("ots", "tool", nl, inv_T(ots) @ T_OMC_BASE @ truth(t + 0.003)))
    return ev


def run(pipe, ev):
    outs = []
    for dev, body, t, T in ev:
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, t, T)
        outs.extend(pipe.poll())
    return outs + pipe.flush()


def local_err_mm(pipe, outs, t_from, t_to):
    """Error of the local measurement in the outputs' stamps: the kf-free check of the chain itself."""
    sel = [o for o in outs if o.filter == "kf" and t_from <= (o.t_ns - T0) / S < t_to and o.t_local is not None]
    return [1e3 * np.linalg.norm(o.p - truth((o.t_local - T0) / S)[:3, 3]) for o in sel]


def _pipe(**kw):
    mon = kw.pop("monitor", MonitorParams(window_s=0.5))
    return TargetPipeline(TargetConfig(chain=ChainConfig(**kw), filters=("cbkf", "kf"), monitor=mon))


def test_a_bumped_vega_sets_link_bumped_and_is_counted():
    pipe = _pipe(init_samples=30)
    outs = run(pipe, stream(6.0, bump_at=3.0))
    t = np.array([(o.t_ns - T0) / S for o in outs])
    flags = np.array([o.link_bumped for o in outs])
    assert not flags[t < 3.0].any()                      # the 30-sample average is no bump
    assert flags[t > 3.0 + 0.75 + 0.05].all()            # 1.5 windows of 0.5 s after the bump (+ reorder delay)
    assert pipe.counts["link_bumped_checks"] > 0 and pipe.counts["recalibrations"] == 0
    s = pipe.stats()
    assert s["link_bumped"] and abs(s["link_dtrans_mm"] - 3.0) < 0.3
    assert "T_base_ots" in pipe.monitor.message("tool")
    # without re-calibration the local measurement stays off by the bump
    assert np.median(local_err_mm(pipe, outs, 4.0, 6.0)) > 2.0


def test_recalibrate_re_estimates_the_links_and_clears_the_flag():
    pipe = _pipe(init_samples=30, calibration_duration_s=1.0,
                 monitor=MonitorParams(window_s=0.5, recalibrate=True))
    outs = run(pipe, stream(8.0, bump_at=3.0))
    assert pipe.counts["recalibrations"] == 1
    L = pipe.chain.links
    assert "robust mean over 1 s" in L.sources["T_base_ots"] and not L.collecting
    t = np.array([(o.t_ns - T0) / S for o in outs])
    flags = np.array([o.link_bumped for o in outs])
    assert flags[(t > 3.9) & (t < 4.2)].all()            # old links in use while re-calibrating
    assert not flags[t > 6.0].any()                      # the new links match the Vega's new place
    assert len([o for o in outs if 4.0 < (o.t_ns - T0) / S < 5.0]) > 0   # fusion went on meanwhile
    assert np.median(local_err_mm(pipe, outs, 6.0, 8.0)) < 0.5


def test_monitor_is_off_for_a_tracked_chain_and_when_disabled():
    pipe = _pipe(init_samples=30, local_chain="tracked")
    run(pipe, stream(5.0, bump_at=2.0))
    assert pipe.monitor.reference is None and pipe.counts["link_bumped_checks"] == 0
    pipe = _pipe(init_samples=30, monitor=MonitorParams(enabled=False))
    outs = run(pipe, stream(5.0, bump_at=2.0))
    assert not any(o.link_bumped for o in outs) and pipe.monitor.n_checks == 0


def test_calibrate_mode_fuses_from_the_average_on_and_reports_refusals():
    pipe = _pipe(static_links="calibrate", calibration_duration_s=2.0)
    sources = []
    ev = stream(5.0, move_base_at=1.0)                   # the base marker moves during the first collection
    outs = run(pipe, [e for e in ev if e[2] < T0 + round(1.5 * S)])
    sources.append(pipe.stats()["links_source"])
    outs += run(pipe, [e for e in ev if e[2] >= T0 + round(1.5 * S)])
    assert pipe.counts["calibration_refused"] >= 1
    assert "OMC body 'base' moved" in pipe.problems["calibration_refused"]
    first = min((o.t_ns - T0) / S for o in outs if o.sources & 1)
    assert first < 30 / 120 + 0.1                        # output from the average of the first 30 sightings on
    assert "T_omc_base: average of 30 samples, until the robust mean" in sources[0]
    L = pipe.chain.links                                 # the global link came from the second collection
    assert "robust mean over 2 s" in L.sources["T_omc_base"] and not L.collecting
    assert "robust mean over 2 s (eq. 2)" in L.sources["T_base_ots"]   # the OTS's view did not move: the first one
    assert pipe.stats()["static_links"] == "calibrate"


def test_default_outputs_are_unchanged_by_the_monitor():
    """Monitoring only observes: the same stream gives the same estimates with and without it."""
    a = run(_pipe(init_samples=30), stream(4.0, bump_at=2.0, seed=3))
    b = run(_pipe(init_samples=30, monitor=MonitorParams(enabled=False)), stream(4.0, bump_at=2.0, seed=3))
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.t_ns == y.t_ns and np.array_equal(x.p, y.p) and np.array_equal(x.cov, y.cov)
