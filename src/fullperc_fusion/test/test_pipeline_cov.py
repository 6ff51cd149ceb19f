"""TargetPipeline with per-sample covariances (issue 18): validated at the input, mapped into base, fused; and a
filter added by one registry entry runs in the pipeline."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion.filters import registry as filter_registry
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Filter, Step
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.fusion_health import ERROR, GLOBAL, HealthParams, TargetHealth
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

S = 1_000_000_000
T0 = 1_700_000_000 * S
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_OTS = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
ALL = ("cbkf", "ckf", "bkf", "kf", "omc")


def cov6(pos, rot=1e-6):
    C = np.zeros((6, 6))
    C[0:3, 0:3] = np.diag(np.broadcast_to(pos, 3))
    C[3:6, 3:6] = rot * np.eye(3)
    return C


def stream(seconds=3.0, seed=0):
    """(device, body, t_ns, T) in stamp order: OMC 120 Hz, OTS 60 Hz (3 ms later), the tool on an arc."""
    rng = np.random.default_rng(seed)
    ev = []
    for k in range(int(seconds * 120)):
        t = k / 120
        ns = T0 + round(t * S)
        q = Rot.from_euler("z", 10 * t, degrees=True).as_quat()
        T_bt = make_T([0.5 + 0.1 * np.cos(t), 0.1 * np.sin(t), 0.3], q)
        Tm = T_OMC_BASE @ T_bt
        Tm[:3, 3] += rng.normal(0, 3e-4, 3)
        ev += [("omc", "base", ns, T_OMC_BASE), ("omc", "tool", ns, Tm)]
        if k % 2 == 0:
            Tl = inv_T(T_OMC_OTS) @ T_OMC_BASE @ T_bt
            Tl[:3, 3] += rng.normal(0, 1e-4, 3)
            ev += [("ots", "base", ns + 3_000_000, inv_T(T_OMC_OTS) @ T_OMC_BASE), ("ots", "tool", ns + 3_000_000, Tl)]
    return ev


def run(pipe, ev, cov=None, health=None):
    """Push every event (``cov(dev, body, k)`` -> covariance or None) as fusion_node does; all outputs."""
    outs = []
    for k, (dev, body, t, T) in enumerate(ev):
        C = cov(dev, body, k) if cov else None
        ok = (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, t, T, C)
        if health is not None and dev == "omc" and body == "tool":
            now = (t - T0) / S
            health.accepted(GLOBAL, now) if ok else health.rejected(GLOBAL, now, pipe.last_problem)
        outs.extend(pipe.poll())
    return outs + pipe.flush()


def test_no_covariance_and_the_fixed_noise_as_covariance_agree():
    prm = FilterParams()
    fixed = {"omc": cov6(prm.global_std**2), "ots": cov6(prm.local_std**2)}
    a = run(TargetPipeline(TargetConfig(filters=ALL)), stream())
    b = run(TargetPipeline(TargetConfig(filters=ALL)), stream(), cov=lambda dev, body, k: fixed[dev])
    assert len(a) == len(b) > 0
    for oa, ob in zip(a, b, strict=True):
        # R_A sigma^2 I R_A^T = sigma^2 I up to rounding of the rotation: equal to ~1e-15 relative
        assert oa.filter == ob.filter and oa.t_ns == ob.t_ns
        assert np.allclose(oa.p, ob.p, rtol=0, atol=1e-12) and np.allclose(oa.cov[:3, :3], ob.cov[:3, :3], rtol=1e-9)


def test_device_covariance_is_rotated_into_base():
    Sig = cov6([1e-6, 4e-6, 9e-6], rot=0.0)
    Sig[3:6, 3:6] = np.diag([1e-4, 2e-4, 3e-4])
    outs = run(TargetPipeline(TargetConfig(filters=("omc", "cbkf"))), stream(1.0), cov=lambda dev, body, k: Sig)
    R = T_OMC_BASE[:3, :3].T                    # T_base_tool = inv(T_omc_base) T_omc_tool
    omc = [o for o in outs if o.filter == "omc"]
    assert omc and np.allclose(omc[-1].cov[:3, :3], R @ Sig[:3, :3] @ R.T, rtol=1e-12, atol=0)
    assert np.allclose(omc[-1].cov[3:6, 3:6], R @ Sig[3:6, 3:6] @ R.T, rtol=1e-12, atol=0)
    # the output's orientation covariance is that of the orientation source (OTS: R_A = R_base_ots)
    Rl = (inv_T(T_OMC_BASE) @ T_OMC_OTS)[:3, :3]
    loc = [o for o in outs if o.filter == "cbkf" and o.orientation_source == SOURCE_LOCAL]
    assert loc and np.allclose(loc[-1].cov[3:6, 3:6], Rl @ Sig[3:6, 3:6] @ Rl.T, rtol=1e-9, atol=0)


def test_a_larger_local_covariance_moves_the_estimate_towards_the_global_source():
    prm = FilterParams()
    base = run(TargetPipeline(TargetConfig(filters=("kf",))), stream())
    loose = run(TargetPipeline(TargetConfig(filters=("kf",))), stream(),
                cov=lambda dev, body, k: cov6(prm.global_std**2 if dev == "omc" else 1e-4))
    assert any(not np.allclose(a.p, b.p, atol=1e-9) for a, b in zip(base, loose, strict=True))


@pytest.fixture(scope="module")
def without_bad():
    """(events, indices of the samples given a bad covariance, the outputs of a run in which those samples were
    never sent): the same for every bad covariance below, so the reference run is made once per module. Poses
    read-only: no pipeline may change its input in place (a reference shared by four runs must stay as made)."""
    ev = stream()
    for e in ev:
        e[3].flags.writeable = False
    bad_k = {k for k, (dev, body, *_) in enumerate(ev) if dev == "omc" and body == "tool" and k % 5 == 1}
    ref = run(TargetPipeline(TargetConfig(filters=ALL)), [e for k, e in enumerate(ev) if k not in bad_k])
    return ev, bad_k, ref


@pytest.mark.parametrize("bad, why", [
    (cov6(np.nan), "non-finite"),
    (cov6(1e-8) + np.triu(np.full((6, 6), 1e-9), 1), "not symmetric"),
    (cov6([1e-8, -1e-8, 1e-8]), "not positive definite"),
    (cov6(1e-8, rot=0.0), "not positive definite"),
])
def test_bad_covariance_is_rejected_counted_and_never_fused(bad, why, without_bad):
    ev, bad_k, ref = without_bad
    n_tool = sum(1 for dev, body, *_ in ev if dev == "omc" and body == "tool")
    pipe = TargetPipeline(TargetConfig(filters=ALL))
    outs = run(pipe, ev, cov=lambda dev, body, k: bad if k in bad_k else None)
    assert 0 < len(bad_k) < n_tool
    assert pipe.counts["rejected_cov"] == len(bad_k)
    assert why in pipe.problems["rejected_cov"] and "OMC body 'tool'" in pipe.problems["rejected_cov"]
    # never fused: identical to a run in which those samples were never sent (the module's one reference run)
    assert len(outs) == len(ref)
    for a, b in zip(outs, ref, strict=True):
        assert a.filter == b.filter and a.t_ns == b.t_ns and np.array_equal(a.p, b.p)


def test_every_sample_with_a_bad_covariance_raises_the_all_rejected_alarm():
    prm = HealthParams()
    h = TargetHealth("tool", {GLOBAL: "OMC body 'tool'"}, prm)
    pipe = TargetPipeline(TargetConfig(filters=("cbkf",)))
    run(pipe, stream(), cov=lambda dev, body, k: cov6(-1.0) if dev == "omc" and body == "tool" else None, health=h)
    assert pipe.counts["rejected_cov"] == 360
    alarms = [a for a in h.alarms(3.0) if a.rule == "rejected" and a.source == GLOBAL]
    assert alarms and alarms[0].level == ERROR and "not positive definite" in alarms[0].message
    assert prm.reject_timeout_s < 3.0


class _Hold:
    """A filter in a dozen lines: the newest local position, held (the shape CONTRIBUTING describes)."""

    kind = "hold"

    def __init__(self, params: FilterParams | None = None) -> None:
        self.params = params or FilterParams()
        self.reset()

    def reset(self) -> None:
        self.last = None

    def predict(self, t_ns: int) -> None:
        pass

    def update(self, *measurements) -> Step | None:
        self.last = next((m for m in measurements if m.source == SOURCE_LOCAL), self.last)
        if self.last is None:
            return None
        return Step(max(m.t_ns for m in measurements), self.last.p.copy(), np.zeros(3), np.zeros(3),
                    np.eye(6) * 1e-8, SOURCE_LOCAL)

    def snapshot(self) -> object:
        return self.last

    def restore(self, snap: object) -> None:
        self.last = snap


def test_one_registry_entry_adds_a_filter_to_the_pipeline(monkeypatch):
    assert isinstance(_Hold(), Filter)
    monkeypatch.setitem(filter_registry.FILTERS, "hold", filter_registry.FilterSpec(_Hold))
    outs = run(TargetPipeline(TargetConfig(filters=("cbkf", "hold"))), stream(1.0))
    held = [o for o in outs if o.filter == "hold"]
    assert held and all(o.sources == SOURCE_LOCAL for o in held)
    monkeypatch.delitem(filter_registry.FILTERS, "hold")
    with pytest.raises(ValueError, match="not one of"):
        TargetConfig(filters=("hold",))
    assert SOURCE_GLOBAL not in {o.sources for o in held}


class _Seen(_Hold):
    """_Hold that records what it is given and answers with a fused orientation; ``uses_models`` and ``express_in``
    as attributes (the old way of guessing): only its registry entry's declaration may count."""

    uses_models = True

    def reset(self) -> None:
        super().reset()
        self.got: list = []
        self.frames = 0

    def express_in(self, T_frame, local=True):
        self.frames += 1

    def update(self, *measurements) -> Step | None:
        self.got.extend(measurements)
        st = super().update(*measurements)
        if st is not None:
            st.q, st.pose_cov = np.array([0.0, 0.0, 0.0, 1.0]), np.eye(6) * 1e-6
        return st


def test_the_pipeline_acts_on_declared_capabilities_not_on_attributes(monkeypatch):
    """``models`` (model covariances, the local chain's frame) and ``orientation`` (the Step's fused orientation is
    output) come from the registry entry: the same filter class under two declarations behaves as declared."""
    caps = filter_registry.Capabilities
    monkeypatch.setitem(filter_registry.FILTERS, "plain", filter_registry.FilterSpec(_Seen))
    monkeypatch.setitem(filter_registry.FILTERS, "modelled",
                        filter_registry.FilterSpec(_Seen, caps=caps(models=True, orientation=True)))
    pipe = TargetPipeline(TargetConfig(filters=("plain", "modelled")))
    outs = run(pipe, stream(1.0))
    plain, modelled = pipe.filters["plain"], pipe.filters["modelled"]
    assert plain.got and all(m.cov is None for m in plain.got), "no model covariances without the declaration"
    assert modelled.got and all(m.cov is not None for m in modelled.got)
    assert plain.frames == 0 and modelled.frames > 0
    by = {name: [o for o in outs if o.filter == name] for name in ("plain", "modelled")}
    assert by["plain"] and {o.orientation_source for o in by["plain"]} <= {SOURCE_GLOBAL, SOURCE_LOCAL}   # a source's
    assert by["modelled"] and {o.orientation_source for o in by["modelled"]} == {SOURCE_GLOBAL | SOURCE_LOCAL}


def test_rotation_stds_are_the_parameters_own_when_they_model_orientation():
    """The orientation part of a source's fixed covariance (noise_std / noise_model std): FullpercParams' rot_*_std,
    else the outputs' orientation_std_* (declared by the parameter type, not looked up by attribute name)."""
    from fullperc_fusion.filters.fullperc_params import FullpercParams
    from fullperc_fusion.pipeline.target import rotation_stds

    fp = FullpercParams(rot_global_std=4e-3, rot_local_std=3e-3)
    assert rotation_stds(TargetConfig(filters=("fullperc",), params=fp)) == (4e-3, 3e-3)
    cfg = TargetConfig(orientation_std_global=0.02, orientation_std_local=0.003)
    assert rotation_stds(cfg) == (0.02, 0.003)
