"""TargetPipeline with the fullperc filter (issue 18): model covariances for it only, the paper's four unchanged,
its fused orientation and 6x6 covariance in the output, bad covariances rejected and counted."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.so3 import quat_to_R, so3_log
from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.measurement_models import omc_covariance
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

S = 1_000_000_000
T0 = 1_700_000_000 * S
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_OTS = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
PAPER = ("cbkf", "ckf", "bkf", "kf", "omc")


def stream(seconds=3.0, seed=0):
    """(device, body, t_ns, T, T_true_base) in stamp order: OMC 120 Hz, OTS 60 Hz (3 ms later), a turning tool."""
    rng = np.random.default_rng(seed)
    ev = []
    for k in range(int(seconds * 120)):
        t = k / 120
        ns = T0 + round(t * S)
        q = Rot.from_euler("z", 10 * t, degrees=True).as_quat()
        T_bt = make_T([0.5 + 0.1 * np.cos(t), 0.1 * np.sin(t), 0.3], q)
        Tm = T_OMC_BASE @ T_bt
        Tm[:3, 3] += rng.normal(0, 3e-4, 3)
        Tm[:3, :3] = Rot.from_rotvec(rng.normal(0, 3e-3, 3)).as_matrix() @ Tm[:3, :3]
        ev += [("omc", "base", ns, T_OMC_BASE, None), ("omc", "tool", ns, Tm, T_bt)]
        if k % 2 == 0:
            Tl = inv_T(T_OMC_OTS) @ T_OMC_BASE @ T_bt
            Tl[:3, 3] += rng.normal(0, 1e-4, 3)
            ev += [("ots", "base", ns + 3_000_000, inv_T(T_OMC_OTS) @ T_OMC_BASE, None),
                   ("ots", "tool", ns + 3_000_000, Tl, T_bt)]
    return ev


def run(pipe, ev, quality=None, cov=None):
    outs = []
    for k, (dev, body, t, T, _) in enumerate(ev):
        if dev == "omc":
            pipe.push_omc(body, t, T, None if cov is None else cov(k), quality=None if quality is None else quality(k))
        else:
            pipe.push_ots(body, t, T)
        outs.extend(pipe.poll())
    return outs + pipe.flush()


def _by_filter(outs, name):
    return [o for o in outs if o.filter == name]


def test_the_paper_filters_get_the_same_results_with_fullperc_beside_them():
    ev = stream()
    a = run(TargetPipeline(TargetConfig(filters=PAPER)), ev)
    b = run(TargetPipeline(TargetConfig(filters=(*PAPER, "fullperc"))), ev, quality=lambda k: {"fit_error": 2e-3})
    for name in PAPER:
        oa, ob = _by_filter(a, name), _by_filter(b, name)
        assert len(oa) == len(ob) > 300
        for x, y in zip(oa, ob, strict=True):
            assert x.t_ns == y.t_ns
            np.testing.assert_array_equal(x.p, y.p)
            np.testing.assert_array_equal(x.q, y.q)
            np.testing.assert_array_equal(x.cov, y.cov)
    assert len(_by_filter(b, "fullperc")) == len(_by_filter(b, "cbkf"))


def test_fullperc_outputs_its_fused_orientation_and_pose_covariance():
    ev = stream(seconds=4.0)
    outs = _by_filter(run(TargetPipeline(TargetConfig(filters=("fullperc", "cbkf"))), ev), "fullperc")
    truth = {t: T for dev, body, t, _, T in ev if T is not None}
    errs, errs_omc = [], []
    omc_q = {t: T for dev, body, t, T, _ in ev if dev == "omc" and body == "tool"}
    for o in outs[240:]:
        assert o.orientation_source == SOURCE_GLOBAL | SOURCE_LOCAL
        assert o.cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(o.cov) > 0)
        T = truth[o.t_ns]
        errs.append(np.linalg.norm(so3_log(quat_to_R(o.q) @ T[:3, :3].T)))
        if o.t_ns in omc_q:
            Rm = inv_T(T_OMC_BASE)[:3, :3] @ omc_q[o.t_ns][:3, :3]
            errs_omc.append(np.linalg.norm(so3_log(Rm @ T[:3, :3].T)))
    # the fused orientation is better than the raw OMC's (3 mrad per axis) it partly comes from
    assert np.mean(errs) < 0.7 * np.mean(errs_omc)
    # the cbkf beside it still copies a source's orientation
    cb = _by_filter(run(TargetPipeline(TargetConfig(filters=("cbkf",))), ev), "cbkf")
    assert {o.orientation_source for o in cb} <= {SOURCE_GLOBAL, SOURCE_LOCAL}


def test_quality_reaches_fullperc_as_its_model_covariance_and_only_fullperc():
    seen: dict[str, list] = {"fullperc": []}
    ev = stream(seconds=1.0)
    pipe = TargetPipeline(TargetConfig(filters=("fullperc", "cbkf")))
    f = pipe.filters["fullperc"]
    assert isinstance(f, FullpercFilter)
    orig = f.update

    def spy(*ms):
        seen["fullperc"].extend(ms)
        return orig(*ms)

    f.update = spy
    cb_orig = pipe.filters["cbkf"].update
    cb_seen = []

    def cb_spy(*ms):
        cb_seen.extend(ms)
        return cb_orig(*ms)

    pipe.filters["cbkf"].update = cb_spy
    run(pipe, ev, quality=lambda k: {"fit_error": 1e-3, "markers_used": 4} if k % 4 == 1 else None)
    g = [m for m in seen["fullperc"] if m.source == SOURCE_GLOBAL]
    loc = [m for m in seen["fullperc"] if m.source == SOURCE_LOCAL]
    assert g and loc and all(m.cov is not None for m in g + loc)
    with_q = [m for m in g if m.extras.get("fit_error") == 1e-3]
    assert with_q and len(with_q) < len(g)
    np.testing.assert_allclose(with_q[0].cov, omc_covariance(1e-3, None), rtol=1e-9, atol=1e-18)  # rotated
    without = next(m for m in g if "fit_error" not in m.extras)
    assert without.cov[0, 0] < with_q[0].cov[0, 0]
    assert all(m.cov is None for m in cb_seen)   # the paper's filters: fixed noise, as before


def test_a_bad_covariance_is_rejected_counted_and_never_fused():
    ev = stream(seconds=1.0)
    bad = {k for k, e in enumerate(ev) if e[0] == "omc" and e[1] == "tool"}
    bad = set(sorted(bad)[50:53])

    def cov(k):
        if k not in bad:
            return None
        return np.full((6, 6), np.nan) if k % 2 else -np.eye(6)

    pipe = TargetPipeline(TargetConfig(filters=("fullperc",)))
    outs = run(pipe, ev, cov=cov)
    assert pipe.counts["rejected_cov"] == 3
    bad_t = {ev[k][2] for k in bad}
    assert not any(o.t_global in bad_t for o in outs)
    assert all(np.all(np.isfinite(o.p)) and np.all(np.isfinite(o.cov)) for o in outs)


def test_malformed_quality_means_the_defaults():
    pipe = TargetPipeline(TargetConfig(filters=("fullperc",)))
    pipe.push_omc_quality("tool", T0, {"fit_error": "much"})
    pipe.push_omc_quality("base", T0, {"fit_error": 1e-3})      # not the target body: ignored
    assert len(pipe.omc_quality) == 0
    outs = run(pipe, stream(seconds=0.5), quality=lambda k: {"fit_error": float("nan")})
    assert outs and all(np.all(np.isfinite(o.cov)) for o in outs)
    assert any(o.sources & SOURCE_LOCAL for o in outs)
