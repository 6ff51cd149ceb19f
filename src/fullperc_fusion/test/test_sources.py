"""Sources by configuration (sources.py): parsing and its errors, three synchronizer streams, a chain and a noise
per local source, arrival == ordered with two local sources, accuracy from the second local source."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.params import ParameterError
from fullperc_common.testing import load_by_path
from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion import fusion_config as fc
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.sources import SourceSet, SourceSpec
from fullperc_fusion.pipeline.synchronizer import ApproxSync, Sample

MS = 1_000_000
_tp = load_by_path(Path(__file__).with_name("test_pipeline.py"), "_pipeline_streams")
T0, S, truth, T_OMC_BASE, T_OMC_OTS = _tp.T0, _tp.S, _tp.truth, _tp.T_OMC_BASE, _tp.T_OMC_OTS
OMC_OFFSET = _tp.OMC_OFFSET
ALL = ("cbkf", "ckf", "bkf", "kf", "omc")
T_OMC_ATR = make_T([-1.0, 2.0, 1.2], Rot.from_euler("zyx", [-60, 10, 5], degrees=True).as_quat())
T_OMC_ATR_RIG = T_OMC_ATR @ inv_T(make_T([0.02, 0.03, -0.05], Rot.from_euler("y", 7, degrees=True).as_quat()))
TWO_LOCAL = {"sources": ["omc", "ots", "atracsys"], "omc": {"role": "global"}, "ots": {"role": "local"},
             "atracsys": {"role": "local", "topic_prefix": "/atracsys", "base_tool": "ref", "noise_std": 2.0e-4},
             "tool": {"atracsys": "probe7"}}


def _write(tmp_path, params: dict):
    p = tmp_path / "f.yaml"
    p.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": params}}))
    return p


# ---------------------------------------------------------------------------------------------- configuration
def test_no_sources_is_the_built_in_pair_and_reads_nothing_more():
    seen = []
    cfg = fc.target_config(lambda n, d: seen.append(n), "tool")
    assert [s.name for s in (cfg.sources.glob, *cfg.sources.locals)] == ["omc", "ots"]
    assert cfg.sources.stream_names == ("global", "local") and not any("." in n and n.startswith(("omc.", "ots."))
                                                                       for n in seen)


def test_two_local_sources_are_mapped(tmp_path):
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, "local_chain": "direct"}), filters=("cbkf",))
    s = cfg.sources
    assert s.glob.name == "omc" and [x.name for x in s.locals] == ["ots", "atracsys"]
    assert s.stream_names == ("global", "local", "atracsys")
    assert cfg.chain.local_chain == "direct" and cfg.chain.ots_target == "tool"   # the first local: legacy values
    a = s.extras[0]
    assert a.topic("probe7") == "/atracsys/probe7/pose" and a.noise_std == 2.0e-4 and a.noise_model == "std"
    assert (a.chain.ots_target, a.chain.ots_base, a.chain.local_chain, a.chain.omc_rig) == \
        ("probe7", "ref", "static", "atracsys_rig")
    # the first local source's block overrides the legacy parameters
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, "ots": {"role": "local", "chain": "tracked",
                                                                          "base_tool": "b2"}}), filters=("cbkf",))
    assert (cfg.chain.local_chain, cfg.chain.ots_base) == ("tracked", "b2")


@pytest.mark.parametrize("change, match", [
    ({"atracsys": {"role": "remote"}}, "'atracsys.role'"),
    ({"ots": {"role": "global"}}, "exactly one source needs role global"),
    ({"sources": ["omc"]}, "at least one source needs role local"),
    ({"sources": ["omc", "ots", "ots"]}, "listed twice"),
    ({"sources": ["omc", "ots", "tool"], "tool": {"role": "local"}}, "clashes"),
    ({"sources": ["omc", "ots", "noise"]}, "clashes"),
    ({"sources": ["omc", "ots", "Vega-2"]}, "lower-case identifier"),
    ({"sources": ["omc", "ots", "vega2"]}, "source 'vega2' .* has no block"),
    ({"atracsys": {"role": "local", "chain": "flying"}}, "'atracsys.chain'"),
    ({"atracsys": {"role": "local", "noise_std": -1.0}}, "'atracsys.noise_std'"),
    ({"atracsys": {"role": "local", "noise_model": "omc"}}, "'atracsys.noise_model'"),
    ({"atracsys": {"role": "local", "topic_prefix": "/"}}, "'atracsys.topic_prefix'"),   # relative is fine (issue 39)
    ({"ots": {"role": "local", "T_base": [0, 0, 0, 0, 0, 0, 1]}, "T_base_ots": [0, 0, 0, 0, 0, 0, 1]}, "give it once"),
    ({"sources": ["atracsys", "omc", "ots"]}, "omc and ots are kept"),
])
def test_bad_source_configurations_are_refused_naming_the_parameter(tmp_path, change, match):
    with pytest.raises(ParameterError, match=match):
        fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, **change}), filters=("cbkf",))


def test_shipped_two_local_example_loads():
    path = Path(__file__).resolve().parents[1] / "config" / "fusion_two_local.yaml"
    cfg, _ = fc.load_fusion_config(path, filters=("cbkf",))
    assert len(cfg.sources.locals) == 2 and cfg.sources.extras[0].topic_prefix == "atracsys"   # relative (issue 39)


def test_a_source_blocks_keys_are_rows_with_their_rule(tmp_path):
    """--help / docs and the check read the same row: a source key's row carries its unit, description and rule,
    a device name's row refuses ''."""
    from fullperc_fusion.pipeline.param_table import POSITIVE

    row = fc.spec("atracsys.noise_std")
    assert (row.name, row.kind, row.unit, row.check) == ("atracsys.noise_std", "float", "m", POSITIVE.check)
    assert row.doc.startswith("source 'atracsys': ")
    with pytest.raises(ParameterError, match="'tool.atracsys'"):
        fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, "tool": {"atracsys": ""}}), filters=("cbkf",))


def test_global_and_local_are_one_role_in_three_encodings():
    """filters.api.Role is the one definition: the synchronizer's stream index, the bit of Measurement.source and
    of FusionStatus on the wire (values unchanged), and the text of a source's role, the stream names and the
    health keys."""
    from fullperc_fusion import fusion_health
    from fullperc_fusion.filters import api
    from fullperc_fusion.pipeline import sources, synchronizer
    from fullperc_msgs.msg import FusionStatus

    R = api.Role
    assert (int(R.GLOBAL), int(R.LOCAL)) == (synchronizer.GLOBAL, synchronizer.LOCAL) == (0, 1)
    assert (api.SOURCE_GLOBAL, api.SOURCE_LOCAL) == (R.GLOBAL.bit, R.LOCAL.bit) == \
        (FusionStatus.SOURCE_GLOBAL, FusionStatus.SOURCE_LOCAL) == (1, 2)
    assert type(api.SOURCE_GLOBAL) is int and type(synchronizer.GLOBAL) is int   # plain ints on the hot paths
    assert api.ROLE_LABELS == sources.ROLES == ApproxSync().names == SourceSet().stream_names == ("global", "local")
    assert (fusion_health.GLOBAL, fusion_health.LOCAL) == (R.GLOBAL.label, R.LOCAL.label)
    assert fusion_health._BITS == {"global": 1, "local": 2}


# ---------------------------------------------------------------------------------------------- synchronizer
def _samples(ts):
    return [Sample(int(t), None) for t in ts]


def test_a_third_stream_never_pairs_and_leaves_the_pairing_unchanged():
    rng = np.random.default_rng(3)
    g = np.unique(np.round(np.cumsum(rng.uniform(3, 6, 300)) * MS))
    lo = np.unique(np.round(np.cumsum(rng.uniform(2, 5, 400)) * MS + 0.7 * MS))
    x = np.unique(np.round(np.cumsum(rng.uniform(1, 4, 500)) * MS + 0.3 * MS))
    two = ApproxSync.pair(_samples(g), _samples(lo), 4 * MS)
    three = ApproxSync.pair(_samples(g), _samples(lo), 4 * MS, [_samples(x)])
    paired = [i for i in three if i.source == 0]
    assert [(i.glob and i.glob.t_ns, i.local and i.local.t_ns) for i in paired] == \
        [(i.glob and i.glob.t_ns, i.local and i.local.t_ns) for i in two]
    extra = [i for i in three if i.source == 1]
    assert [i.local.t_ns for i in extra] == list(x) and all(i.glob is None for i in extra)
    firsts = [min(s.t_ns for s in (i.glob, i.local) if s is not None) for i in three]
    assert firsts == sorted(firsts)   # the order of the first stamps
    # the incremental (polled) synchronizer gives the same items as the complete set
    s = ApproxSync(4 * MS, 20 * MS, names=("global", "local", "atracsys"))
    out = []
    ev = sorted([(t, 0) for t in g] + [(t, 1) for t in lo] + [(t, 2) for t in x])
    for t, k in ev:
        assert s.push(k, int(t)) == "ok"
        out += s.poll()
    out += s.flush()
    assert [(i.t_ns, i.source, i.glob and i.glob.t_ns) for i in out] == \
        [(i.t_ns, i.source, i.glob and i.glob.t_ns) for i in three]
    assert s.counts["atracsys_alone"] == len(x) and s.counts["atracsys_in"] == len(x)


# ---------------------------------------------------------------------------------------------- pipelines
def stream3(duration=3.0, ots=(0.5, 1.5), atr=(0.5, 3.0), seed=1):
    """('omc'|'ots'|'atracsys', body, t_ns, T) in arrival order: the OMC tool biased by OMC_OFFSET, the OTS and the
    Atracsys (its own pose, 300 Hz, 5 ms late) seeing the tool in their windows and the base marker always."""
    rng = np.random.default_rng(seed)
    ev = []
    for k in range(int(duration * 240)):
        t = k / 240
        ns = T0 + round(t * S)
        Tm = T_OMC_BASE @ truth(t)
        Tm[:3, 3] += OMC_OFFSET + rng.normal(0, 3e-4, 3)
        ev += [(ns + 2 * MS, "omc", "tool", ns, Tm), (ns + 2 * MS, "omc", "base", ns, T_OMC_BASE),
               (ns + 2 * MS, "omc", "ots_rig", ns, _tp.T_OMC_RIG), (ns + 2 * MS, "omc", "atracsys_rig", ns,
                                                                    T_OMC_ATR_RIG)]
    for dev, T_omc_dev, hz, off, late, win in (("ots", T_OMC_OTS, 400, 0.003, 15, ots),
                                               ("atracsys", T_OMC_ATR, 300, 0.0017, 5, atr)):
        for k in range(int(duration * hz)):
            t = off + k / hz
            ns = T0 + round(t * S)
            ev.append((ns + late * MS, dev, "base", ns, inv_T(T_omc_dev) @ T_OMC_BASE))
            if win[0] <= t < win[1]:
                Tl = inv_T(T_omc_dev) @ T_OMC_BASE @ truth(t)
                Tl[:3, 3] += rng.normal(0, 1e-4, 3)
                ev.append((ns + late * MS, dev, "tool", ns, Tl))
    ev.sort(key=lambda e: e[0])
    return [e[1:] for e in ev]


def _cfg(filters=ALL, atr_chain="static", noise_std=None, **kw):
    extra = SourceSpec("atracsys", "local", "/atracsys", noise_std, "std",
                       ChainConfig(local_chain=atr_chain, omc_rig="atracsys_rig", static_links="average"))
    return TargetConfig(filters=filters, chain=ChainConfig(static_links="average", **kw),
                        sources=SourceSet(locals=(SourceSet().locals[0], extra)))


def _push(pipe, ev):
    dev, body, ns, T = ev
    if dev == "omc":
        return pipe.push_omc(body, ns, T)
    return pipe.push_local(0 if dev == "ots" else 1, body, ns, T)


def _run(pipe, events):
    outs = []
    for ev in events:
        _push(pipe, ev)
        outs += pipe.poll()
    return outs + pipe.flush()


@pytest.fixture(scope="module")
def events3():
    """:func:`stream3` with the same arguments, made once per module (several tests and every parametrisation of the
    arrival test run the same stream). Poses read-only: no pipeline may change its input in place."""
    made: dict[tuple, list] = {}

    def get(**kw):
        key = tuple(sorted(kw.items()))
        if key not in made:
            made[key] = stream3(**kw)
            for ev in made[key]:
                ev[3].flags.writeable = False
        return made[key]
    return get


@pytest.fixture(scope="module")
def ordered3(events3):
    """(pipeline, outputs) of the ordered TargetPipeline with :func:`_cfg` over ``stream3()``: one run read by the
    accuracy test and by the arrival test's ``[0-static]`` case (its ordered reference: the same config and events)."""
    pipe = TargetPipeline(_cfg())
    return pipe, _run(pipe, events3())


def _err_mm(outs, name, t0, t1):
    e = [np.linalg.norm(o.p - truth((o.t_ns - T0) / S)[:3, 3]) for o in outs
         if o.filter == name and t0 <= (o.t_ns - T0) / S < t1]
    assert e
    return 1e3 * float(np.mean(e))


def test_each_local_source_has_its_own_chain_and_the_second_keeps_the_accuracy(events3, ordered3):
    """The Atracsys sits elsewhere (its own T_base_atracsys, estimated from its view of the base marker): its
    samples land on the truth in base; after the OTS goes silent (1.5 s) CBKF stays at local accuracy through the
    Atracsys while the biased OMC is off by its offset; both local sources were fused."""
    pipe, outs = ordered3
    assert pipe.counts["ots_fused"] > 100 and pipe.counts["atracsys_fused"] > 100
    off_mm = 1e3 * np.linalg.norm(OMC_OFFSET)
    assert _err_mm(outs, "omc", 2.0, 3.0) > 0.8 * off_mm
    assert _err_mm(outs, "cbkf", 2.0, 3.0) < 0.3
    local_only = [o for o in outs if o.filter == "kf" and o.t_global is None and o.t_local is not None
                  and (o.t_ns - T0) / S > 2.0]
    assert local_only, "Atracsys samples are their own local-only items"
    np.testing.assert_allclose(pipe.extra_chains[0].links.T_base_ots, inv_T(T_OMC_BASE) @ T_OMC_ATR, atol=1e-9)
    # without the Atracsys the OMC-only phase is global only
    alone = TargetPipeline(TargetConfig(filters=ALL, chain=ChainConfig(static_links="average")))
    outs1 = _run(alone, [e for e in events3() if e[0] != "atracsys"])
    assert not [o for o in outs1 if o.filter == "kf" and o.t_local is not None and (o.t_ns - T0) / S > 2.0]


def test_noise_std_is_the_sources_own_noise(events3):
    """Only Atracsys samples after the links: the paper's KF weighs them with the source's noise_std (a larger
    std -> a larger posterior position variance), and the covariance's position block is noise_std^2."""
    ev = [e for e in events3(ots=(0, 0)) if not (e[0] == "omc" and e[1] == "tool")]
    var = {}
    for std in (1e-4, 1e-2):
        pipe = TargetPipeline(_cfg(filters=("kf",), noise_std=std))
        outs = _run(pipe, ev)
        assert pipe._fixed_local[1][0, 0] == std**2
        var[std] = float(np.mean([o.cov[0, 0] for o in outs[-50:]]))
    assert var[1e-2] > 100 * var[1e-4]


@pytest.mark.parametrize("atr_chain", ["static", "tracked", "direct"])
@pytest.mark.parametrize("reorder_ms", [0, 30])
def test_arrival_final_estimates_equal_ordered_processing_with_two_local_sources(atr_chain, reorder_ms, events3,
                                                                                 ordered3):
    """test_arrival.py's equality check with a second local source: every filter, every output, exactly."""
    events = events3()
    if reorder_ms:
        rng = np.random.default_rng(reorder_ms)
        recv = [ev[2] + int(rng.uniform(0, reorder_ms * MS)) for ev in events]
        events = [ev for _, ev in sorted(zip(recv, events, strict=True), key=lambda x: x[0])]
    cfg = _cfg(atr_chain=atr_chain)
    if (atr_chain, reorder_ms) == ("static", 0):
        opipe, ordered = ordered3    # this config over these events: the run the accuracy test made
    else:
        opipe = TargetPipeline(cfg)
        ordered = _run(opipe, events)
    apipe = ArrivalPipeline(cfg)
    final = []
    for ev in events:
        _push(apipe, ev)
        apipe.poll()
        final += apipe.take_final()
    apipe.flush()
    final += apipe.take_final()
    do = {(o.filter, o.t_ns, o.t_local): o for o in ordered}
    da = {(o.filter, o.t_ns, o.t_local): o for o in final}
    assert len(do) == len(ordered) and len(da) == len(final)
    assert len(do) > 3000 and do.keys() == da.keys()
    for k, o in do.items():
        a = da[k]
        assert np.array_equal(o.p, a.p) and np.array_equal(o.cov, a.cov) and np.array_equal(o.bias, a.bias), k
        assert (o.sources, o.t_global, o.t_local) == (a.sources, a.t_global, a.t_local), k
    assert apipe.counts["items"] == opipe.counts["items"]
    assert apipe.counts["atracsys_fused"] == opipe.counts["atracsys_fused"] > 100
    assert apipe.counts["late"] == opipe.counts["late"] == 0
    if reorder_ms:
        assert apipe.counts["rewinds"] > 0


def _est(T):
    from fullperc_common.transforms import T_to_pq
    from fullperc_fusion.calibration.se3_stats import LinkEstimate

    p, q = T_to_pq(T)
    return LinkEstimate(p, q, np.eye(6) * 1e-10, 100, 100, 0.1, 0.2, 0.1, 0.2, "test")


def test_a_calibration_file_gives_the_further_sources_link_by_its_name(tmp_path):
    """T_base_atracsys in the calibration file is the Atracsys chain's static link from the first sample on (and not
    the OTS's); the OTS's T_base_ots stays the OTS's; an unknown link name is still refused."""
    from fullperc_fusion.calibration.io import save_calibration
    from fullperc_fusion.calibration.se3_stats import Calibration

    T_ba, T_bo = inv_T(T_OMC_BASE) @ T_OMC_ATR, inv_T(T_OMC_BASE) @ T_OMC_OTS
    cal = tmp_path / "cal.yaml"
    save_calibration(cal, Calibration({"T_omc_base": _est(T_OMC_BASE), "T_base_ots": _est(T_bo),
                                       "T_base_atracsys": _est(T_ba)}, T0, 10.0, "test"))
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, "calibration_file": str(cal)}), filters=("kf",))
    pipe = TargetPipeline(cfg)
    atr = pipe.extra_chains[0].links
    assert atr.local_ready and atr.global_ready and "calibration file" in atr.sources["T_base_ots"]
    np.testing.assert_allclose(atr.T_base_ots, T_ba, atol=1e-12)
    np.testing.assert_allclose(pipe.chain.links.T_base_ots, T_bo, atol=1e-12)
    assert not hasattr(pipe.chain.links, "T_base_atracsys")
    Tl = inv_T(T_OMC_ATR) @ T_OMC_BASE @ truth(0.0)
    assert pipe.push_local(1, "probe7", T0, Tl)
    (o,) = pipe.flush()
    np.testing.assert_allclose(o.p, truth(0.0)[:3, 3], atol=1e-9)
    with pytest.raises(ParameterError, match="T_base_atracsys"):
        fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, "calibration_file": str(cal),
                                                "atracsys": {"role": "local", "T_base": [0, 0, 0, 0, 0, 0, 1]}}))
    text = cal.read_text().replace("T_base_atracsys", "T_bogus")
    cal.write_text(text)
    with pytest.raises(ParameterError, match="unknown link"):
        fc.load_fusion_config(_write(tmp_path, {**TWO_LOCAL, "calibration_file": str(cal)}))


def test_model_covariance_per_source_for_filters_that_use_models(events3):
    """fullperc (declares models): an Atracsys with noise_model vega gets the Vega distance model through its own chain,
    one with noise_std its diagonal -- a 1 cm std makes the fused position variance far larger than the model's."""
    from fullperc_fusion.filters.fullperc_params import FullpercParams

    ev = [e for e in events3(ots=(0, 0)) if not (e[0] == "omc" and e[1] == "tool")]
    var = {}
    for model, std in (("vega", None), ("std", 1e-2)):
        extra = SourceSpec("atracsys", "local", "/atracsys", std, model,
                           ChainConfig(omc_rig="atracsys_rig", static_links="average"))
        cfg = TargetConfig(filters=("fullperc",), params=FullpercParams(), chain=ChainConfig(static_links="average"),
                           sources=SourceSet(locals=(SourceSet().locals[0], extra)))
        pipe = TargetPipeline(cfg)
        outs = _run(pipe, ev)
        assert pipe.counts["atracsys_fused"] > 100
        var[model] = float(np.mean([o.cov[0, 0] for o in outs[-50:]]))
    assert var["std"] > 100 * var["vega"], var
