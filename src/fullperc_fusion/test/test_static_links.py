"""Static links of the frame chain: ``static_links: calibrate`` (the default: robust calibration over a duration,
bridged by the average of the first ``init_samples`` sightings until it completes) against ``average``, a calibration
file, :meth:`StaticLinks.apply`, refusals and re-collection.

Synthetic sightings with a fixed seed and made-up stamps (no wall clock): OMC at 120 Hz with ~1 mm / 2 mrad per
frame, Vega at 60 Hz with ~0.1-0.3 mm / 3 mrad (as in test_calibration), optionally with gross outliers.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import inv_T, make_T, mean_T
from fullperc_fusion.calibration.collector import Collector
from fullperc_fusion.calibration.se3_stats import COV_FLOOR, Calibration, se3_residuals, se3_retract
from fullperc_fusion.pipeline.frame_chain import ChainConfig, FrameChain, links_needed

S = 1_000_000_000
T0 = 1_700_000_000 * S
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_RIG = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
T_RIG_OTS = make_T([0.05, 0.0, -0.1], Rot.from_euler("x", 5, degrees=True).as_quat())
T_OMC_OTS = T_OMC_RIG @ T_RIG_OTS
T_OTS_BASE = inv_T(T_OMC_OTS) @ T_OMC_BASE
T_BASE_OTS = inv_T(T_OTS_BASE)
SIG_OMC = np.array([1e-3, 1e-3, 1e-3, 2e-3, 2e-3, 2e-3])
SIG_VEGA = np.array([0.1e-3, 0.1e-3, 0.3e-3, 3e-3, 3e-3, 3e-3])


def events(seconds, rng, outliers=0.0, start=0.0, ots=True, move=None):
    """Sightings in stamp order: (device, body, t_ns, T). ``move`` = (body, at_s, dx): a step of that OMC/OTS
    base body along x from at_s on. ``outliers``: fraction of gross outliers (2 cm / 50 mrad) in every stream.

    Each sighting is ``se3_retract(T_true, d)`` with ``d`` drawn in stamp order; the retractions are done in one
    batch at the end (one ``Rotation.from_rotvec`` for the stack instead of one per sighting: the same formula and
    the same draws from ``rng``, at a fraction of the cost)."""
    ev, poses, deltas = [], [], []

    def sample(T, sig, body, t):
        d = rng.normal(size=6) * sig
        if outliers and rng.random() < outliers:
            d = d + np.array([0.02, 0, 0, 0, 0.05, 0]) * rng.choice([-1, 1])
        if move is not None and body == move[0] and t >= move[1]:
            d = d + np.array([move[2], 0, 0, 0, 0, 0])
        poses.append(T)
        deltas.append(d)

    for k in range(int(seconds * 120)):
        t = start + k / 120
        ns = T0 + round(t * S)
        ev.append(("omc", "base", ns))
        sample(T_OMC_BASE, SIG_OMC, "omc:base", t)
        ev.append(("omc", "ots_rig", ns))
        sample(T_OMC_RIG, SIG_OMC, "omc:ots_rig", t)
        if ots and k % 2 == 0:
            ev.append(("ots", "base", ns + 3_000_000))
            sample(T_OTS_BASE, SIG_VEGA, "ots:base", t)
    if not ev:
        return []
    P, D = np.stack(poses), np.stack(deltas)
    Ts = np.zeros_like(P)
    Ts[:, :3, :3] = Rot.from_rotvec(D[:, 3:]).as_matrix() @ P[:, :3, :3]
    Ts[:, :3, 3] = P[:, :3, 3] + D[:, :3]
    Ts[:, 3, 3] = 1.0
    Ts.flags.writeable = False   # a list may be fed to more than one chain: none may change a sighting in place
    return [(*e, T) for e, T in zip(ev, Ts, strict=True)]


def feed(ch, ev):
    for dev, body, t, T in ev:
        (ch.observe_omc if dev == "omc" else ch.observe_ots)(body, t, T)


def err(T, T_true):
    d = se3_residuals(T_true, T[None])[0]
    return float(np.linalg.norm(d[:3])), float(np.linalg.norm(d[3:]))


def test_calibrate_mode_reaches_the_truth_better_than_the_30_sample_average():
    """The decision this mode is for: over 10 s the robust calibration beats the average of the first 30 sightings
    (``average`` mode, and the bridge of calibrate mode until the calibration completes: the same links) on both
    links, with and without gross outliers, for every seed."""
    ratios = []
    for seed in range(6):
        for outliers in (0.0, 0.03):
            chains, bridge = {}, {}
            ev = events(10.2, np.random.default_rng(seed), outliers)   # both modes see the same sightings
            for mode in ("average", "calibrate"):
                ch = FrameChain(ChainConfig(static_links=mode, calibration_duration_s=10.0))
                feed(ch, [e for e in ev if e[2] < T0 + 5 * S])
                bridge[mode] = {k: getattr(ch.links, k).copy() for k in ("T_omc_base", "T_base_ots")}
                feed(ch, [e for e in ev if e[2] >= T0 + 5 * S])
                assert ch.links.global_ready and ch.links.local_ready and not ch.links.collecting, mode
                chains[mode] = ch
            for link, truth in (("T_omc_base", T_OMC_BASE), ("T_base_ots", T_BASE_OTS)):
                assert np.array_equal(bridge["calibrate"][link], bridge["average"][link])   # the bridge: the average
                assert np.array_equal(bridge["average"][link], getattr(chains["average"].links, link))
                a = err(getattr(chains["average"].links, link), truth)
                c = err(getattr(chains["calibrate"].links, link), truth)
                # T_base_ots: its translation carries the Vega's rotation noise times the 2 m lever
                assert c[0] < a[0] and c[1] < a[1], (seed, outliers, link, a, c)
                ratios.append(c[0] / a[0])
                if link == "T_omc_base":   # absolute: the robust mean of 1200 sightings is within 0.2 mm
                    assert c[0] < 0.2e-3, (seed, outliers, c)
    assert np.median(ratios) < 0.35     # ~sqrt(30/600) = 0.22 without outliers, far less with them


def test_calibrate_is_the_default():
    assert ChainConfig().static_links == "calibrate" and FrameChain(ChainConfig()).links.mode == "calibrate"


def test_calibrate_mode_serves_the_average_from_init_samples_on():
    """Output starts as early as in average mode: after init_samples sightings of each body, with the average's
    links (exactly), named as the bridge in ``sources``; the collection goes on meanwhile."""
    ev = events(1.5, np.random.default_rng(17))
    ch = FrameChain(ChainConfig(static_links="calibrate", calibration_duration_s=2.0, init_samples=30))
    base = [T for d, b, _, T in ev if (d, b) == ("omc", "base")]
    ots = [T for d, b, _, T in ev if (d, b) == ("ots", "base")]
    t29 = [t for d, b, t, _ in ev if (d, b) == ("omc", "base")][29]
    feed(ch, [e for e in ev if e[2] < t29])
    L = ch.links
    assert not L.global_ready and ch.global_T(T_OMC_BASE) is None      # 29 sightings: nothing yet
    feed(ch, [e for e in ev if e[2] >= t29])
    assert L.global_ready and L.local_ready and L.collecting
    assert ch.global_T(T_OMC_BASE) is not None and ch.local_T(T0, T_OTS_BASE)[0] is not None
    assert np.array_equal(L.T_omc_base, mean_T(base[:30]))
    assert np.array_equal(L.T_base_ots, mean_T([inv_T(T) for T in ots[:30]]))
    for name, samples in (("T_omc_base", base[:30]), ("T_base_ots", [inv_T(T) for T in ots[:30]])):
        assert L.sources[name].startswith("average of 30 samples") and "until the robust mean over 2 s" in \
            L.sources[name]
        # the bridge carries the covariance of its mean (what the frame covariance and the local model use)
        est = L.estimates[name]
        r = se3_residuals(getattr(L, name), np.array(samples))
        expected = np.cov(r, rowvar=False, ddof=1) / 30 + np.diag(np.repeat(np.square(COV_FLOOR), 3))
        assert est.n_samples == est.n_inliers == 30 and np.allclose(est.cov, expected, rtol=1e-12, atol=0)
        assert np.allclose(est.T, getattr(L, name), atol=1e-12)
    assert "meanwhile the average of the first 30 samples" in L.describe()


def test_calibrate_mode_switches_every_link_to_the_calibrated_one_after_the_duration():
    ch = FrameChain(ChainConfig(static_links="calibrate", calibration_duration_s=2.0))
    ev = events(3.0, np.random.default_rng(1))
    feed(ch, [e for e in ev if e[2] < T0 + round(1.9 * S)])
    avg = {k: getattr(ch.links, k).copy() for k in ("T_omc_base", "T_base_ots")}
    gen = ch.links.generation
    assert ch.links.global_ready and ch.links.local_ready and ch.links.collecting   # the bridge
    assert "calibrating the static links over 2 s" in ch.links.describe()
    assert {k: e.n_samples for k, e in ch.links.estimates.items()} == {"T_omc_base": 30, "T_base_ots": 30}
    feed(ch, [e for e in ev if e[2] >= T0 + round(1.9 * S)])
    L = ch.links
    assert L.global_ready and L.local_ready and not L.collecting and L.describe() == ""
    assert L.generation == gen + 2                        # global and local link, each once
    for k, T in avg.items():
        assert not np.array_equal(getattr(L, k), T) and np.array_equal(getattr(L, k), L.estimates[k].T)
    assert set(L.estimates) == {"T_omc_base", "T_base_ots"}
    assert L.estimates["T_omc_base"].n_samples == 241    # 2 s at 120 Hz, both ends included
    assert "robust mean over 2 s" in L.sources["T_omc_base"] and "eq. 2" in L.sources["T_base_ots"]
    assert np.allclose(ch.global_T(T_OMC_BASE), np.eye(4), atol=5e-3)


def test_a_moving_body_is_refused_and_collected_again():
    ch = FrameChain(ChainConfig(static_links="calibrate", calibration_duration_s=2.0))
    rng = np.random.default_rng(2)
    ev = events(2.5, rng, move=("omc:base", 1.0, 5e-3))     # the base marker is moved 5 mm after 1 s
    feed(ch, ev)
    L = ch.links
    assert L.refusals == 1 and "OMC body 'base' moved during the collection" in L.last_refusal
    assert L.collecting and L.estimates["T_omc_base"].n_samples == 30   # no calibrated link from a moving body ...
    avg = mean_T([T for d, b, _, T in ev if (d, b) == ("omc", "base")][:30])
    assert L.global_ready and np.array_equal(L.T_omc_base, avg)   # ... the average (before the move) stays
    assert L.sources["T_omc_base"].startswith("average of 30 samples")
    assert L.local_ready and "robust mean" in L.sources["T_base_ots"]   # the OTS's view did not move: calibrated
    assert "refused" in L.describe()
    moved = T_OMC_BASE @ make_T([0, 0, 0])
    moved[:3, 3] += [5e-3, 0, 0]
    feed(ch, [(d, b, t, T if b != "base" or d != "omc" else se3_retract(moved, np.zeros(6)))
              for d, b, t, T in events(2.5, rng, start=2.6)])
    assert L.global_ready and not L.collecting and L.refusals == 1
    assert err(L.T_omc_base, moved)[0] < 0.3e-3


def test_tracked_chain_calibrates_T_rig_ots_against_the_T_omc_base_in_use():
    ch = FrameChain(ChainConfig(local_chain="tracked", static_links="calibrate", calibration_duration_s=3.0))
    feed(ch, events(3.2, np.random.default_rng(3)))
    L = ch.links
    assert L.local_ready and not L.collecting
    assert err(L.T_rig_ots, T_RIG_OTS)[0] < 1e-3 and err(L.T_rig_ots, T_RIG_OTS)[1] < 1e-3
    assert L.estimates["T_rig_ots"].n_inliers >= 150


def test_tracked_T_rig_ots_is_consistent_with_the_T_omc_base_the_chain_uses():
    """T_rig_ots is computed with the T_omc_base in use (here a file's, 10 mm off), so eq. 1 still maps the OTS's
    view of the base marker onto the base: the error of T_omc_base cancels."""
    est = _calibration(np.random.default_rng(15)).links["T_omc_base"]
    est.position = est.position + np.array([0.01, 0.0, 0.0])
    ch = FrameChain(ChainConfig(local_chain="tracked", static_links="calibrate", calibration_duration_s=2.0,
                                calibration=Calibration({"T_omc_base": est}, 0, 2.0, "test")))
    feed(ch, events(2.2, np.random.default_rng(16)))
    L = ch.links
    assert np.array_equal(L.T_omc_base, est.T) and L.local_ready
    T = inv_T(L.T_omc_base) @ T_OMC_RIG @ L.T_rig_ots @ T_OTS_BASE
    assert err(T, np.eye(4))[0] < 1.5e-3          # noise of the 2 s estimate; the 10 mm are gone


def test_eq1_with_a_given_hand_eye_calibration_when_the_ots_never_sees_the_base():
    ch = FrameChain(ChainConfig(static_links="calibrate", calibration_duration_s=2.0, T_rig_ots=T_RIG_OTS))
    feed(ch, events(2.2, np.random.default_rng(4), ots=False))
    assert ch.links.local_ready and "eq. 1" in ch.links.sources["T_base_ots"]
    assert err(ch.links.T_base_ots, T_BASE_OTS)[0] < 2e-3


def _calibration(rng, seconds=2.0) -> Calibration:
    col = Collector(("T_omc_base", "T_base_ots", "T_rig_ots"), duration_s=seconds)
    for dev, body, t, T in events(seconds + 0.1, rng):
        col.add(dev, body, t, T)
    return col.finish(source="test")


def test_a_calibration_file_gives_the_links_from_the_first_sample():
    cal = _calibration(np.random.default_rng(5))
    ch = FrameChain(ChainConfig(calibration=cal, calibration_file="cal.yaml", init_samples=30,
                                static_links="average"))
    L = ch.links
    assert L.global_ready and L.local_ready and not L.collecting
    assert np.array_equal(L.T_omc_base, cal.T("T_omc_base")) and np.array_equal(L.T_base_ots, cal.T("T_base_ots"))
    assert L.sources["T_omc_base"] == "calibration file cal.yaml"
    gen = L.generation
    feed(ch, events(1.0, np.random.default_rng(6)))
    assert L.generation == gen                       # nothing re-estimated
    ch.reinitialize()                                # ~/initialize: every link again, in the configured mode
    assert L.collecting and np.array_equal(L.T_omc_base, cal.T("T_omc_base"))
    feed(ch, events(1.0, np.random.default_rng(7), start=2.0))
    assert not L.collecting and "average of 30" in L.sources["T_omc_base"]
    assert L.estimates["T_omc_base"].n_samples == 30   # the average's covariance, no longer the file's


def test_a_partial_file_leaves_the_rest_to_the_mode():
    full = _calibration(np.random.default_rng(8))
    part = Calibration({"T_omc_base": full.links["T_omc_base"]}, full.stamp_ns, full.duration_s, "test")
    ch = FrameChain(ChainConfig(calibration=part, init_samples=5))
    assert ch.links.global_ready and not ch.links.local_ready and ch.links.collecting
    feed(ch, events(0.2, np.random.default_rng(9)))
    assert ch.links.local_ready and np.array_equal(ch.links.T_omc_base, full.T("T_omc_base"))


def test_a_link_given_twice_is_refused():
    cal = _calibration(np.random.default_rng(10))
    with pytest.raises(ValueError, match="T_base_ots is given both as a parameter and in the calibration file"):
        ChainConfig(T_base_ots=T_BASE_OTS, calibration=cal, calibration_file="c.yaml")
    with pytest.raises(ValueError, match="static_links"):
        ChainConfig(static_links="median")
    with pytest.raises(ValueError, match="duration"):
        ChainConfig(calibration_duration_s=0.0)


def test_apply_swaps_every_link_at_once_and_ends_a_running_collection():
    ch = FrameChain(ChainConfig(static_links="calibrate", calibration_duration_s=5.0))
    feed(ch, events(1.0, np.random.default_rng(11)))
    assert ch.links.collecting
    cal = _calibration(np.random.default_rng(12))
    gen = ch.links.generation
    ch.links.apply(cal, "~/calibrate")
    L = ch.links
    assert not L.collecting and L.generation == gen + 1
    for name in ("T_omc_base", "T_base_ots", "T_rig_ots"):
        assert np.array_equal(getattr(L, name), cal.T(name)) and L.sources[name] == "~/calibrate"
    feed(ch, events(6.0, np.random.default_rng(13), start=1.0))
    assert L.generation == gen + 1                   # the interrupted collection does not come back


def test_links_needed():
    assert links_needed(ChainConfig()) == ("T_omc_base", "T_base_ots")
    assert links_needed(ChainConfig(local_chain="direct")) == ("T_omc_base", "T_base_ots")
    assert links_needed(ChainConfig(local_chain="tracked")) == ("T_omc_base", "T_rig_ots")
    assert links_needed(ChainConfig(local_chain="tracked", T_rig_ots=T_RIG_OTS)) == ("T_omc_base",)
    assert links_needed(ChainConfig(T_base_ots=T_BASE_OTS)) == ("T_omc_base",)


def test_the_average_mode_is_unchanged():
    """The chordal mean of the first init_samples sightings, exactly (as calibrate mode's bridge serves it)."""
    from fullperc_common.transforms import mean_T

    ev = events(1.0, np.random.default_rng(14))
    ch = FrameChain(ChainConfig(init_samples=30, static_links="average"))
    feed(ch, ev)
    base = [T for d, b, _, T in ev if (d, b) == ("omc", "base")][:30]
    ots = [inv_T(T) for d, b, _, T in ev if (d, b) == ("ots", "base")][:30]
    assert np.array_equal(ch.links.T_omc_base, mean_T(base))
    assert np.array_equal(ch.links.T_base_ots, mean_T(ots))
    assert ch.links.mode == "average"
    assert {k: e.n_samples for k, e in ch.links.estimates.items()} == {"T_omc_base": 30, "T_base_ots": 30}


def test_a_calibration_file_with_calibrate_mode_keeps_its_links_on_reinitialize_until_calibrated():
    """No bridge on a re-estimation: the previous links stay in use until the calibration completes."""
    cal = _calibration(np.random.default_rng(18))
    ch = FrameChain(ChainConfig(calibration=cal, calibration_duration_s=1.0))
    ch.reinitialize()
    L = ch.links
    feed(ch, events(0.9, np.random.default_rng(19)))
    assert L.collecting and np.array_equal(L.T_omc_base, cal.T("T_omc_base"))
    assert np.array_equal(L.T_base_ots, cal.T("T_base_ots"))
    feed(ch, events(0.5, np.random.default_rng(20), start=0.95))
    assert not L.collecting and "robust mean over 1 s" in L.sources["T_omc_base"]


def test_tracked_chain_bridge_then_calibrated_T_rig_ots():
    ch = FrameChain(ChainConfig(local_chain="tracked", calibration_duration_s=2.0))
    ev = events(2.2, np.random.default_rng(21))
    feed(ch, [e for e in ev if e[2] < T0 + S])
    L = ch.links
    assert L.local_ready and L.sources["T_rig_ots"].startswith("average of 30 samples (eq. 1)")
    feed(ch, [e for e in ev if e[2] >= T0 + S])
    assert not L.collecting and L.sources["T_rig_ots"] == "robust mean over 2 s (eq. 1)"
    assert err(L.T_rig_ots, T_RIG_OTS)[0] < 1e-3
