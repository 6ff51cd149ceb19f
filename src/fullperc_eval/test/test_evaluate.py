"""Offline evaluator core: ground truth, calibration, segments, metrics on bags with *known* injected errors.

Expected values here come from the construction of the synthetic recordings (an injected OMC offset, exact
joint motion), or from hand-written label sequences -- never from running the evaluator and copying its output.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import yaml

from fullperc_common.runs import runs
from fullperc_common.transforms import make_T
from fullperc_drivers.diana_kinematics import DianaKinematics
from fullperc_eval.bag.calibration import Calibration, CalibrationError, load_calibration, save_calibration
from fullperc_eval.evaluation.config import METHODS, PAPER_METHODS, EvaluationError, replay_config
from fullperc_eval.evaluation.ground_truth import GroundTruth
from fullperc_eval.evaluation.metrics import evaluate_bag, transition_segments
from fullperc_eval.evaluation.report import write_report
from fullperc_eval.evaluation.tables import to_json
from fullperc_eval.sim.dataset import synthetic_content, write_bag
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import FILTER_NAMES, TargetConfig

OFFSET = (0.003, 0.001, -0.002)   # injected OMC error [m]; |OFFSET| = sqrt(14) mm


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    content, truth = synthetic_content(8.0, omc_offset=OFFSET, ots_window_s=(0.0, 4.0))
    path = write_bag(tmp_path_factory.mktemp("synth") / "synth", content)
    return path, content, truth


@pytest.fixture(scope="module")
def synth_eval(synth):
    return evaluate_bag(synth[0], progress=False)


@pytest.fixture(scope="module")
def synth_replay(synth):
    """A function giving a fresh copy of the replay of the synthetic bag with the default configuration: one replay
    for the tests that inject an error into a method's outputs (each changes its own copy)."""
    import copy

    from fullperc_eval.evaluation.replay import replay

    cfg, _ = replay_config()
    rep = replay(synth[0], cfg, progress=False)
    return lambda: copy.deepcopy(rep)


# ------------------------------------------------------------------------------------------- ground truth
def _cal():
    return Calibration(make_T([0.1, -0.2, 0.3], [0, 0, 0.3826834323650898, 0.9238795325112867]),
                       make_T([0, 0, -0.06], [1, 0, 0, 0]))


def test_ground_truth_interpolates_linear_joint_motion_exactly():
    kin = DianaKinematics()
    cal = _cal()
    t = np.arange(0, 1_000_000_001, 10_000_000, dtype=np.int64)          # 100 Hz, 1 s
    q0 = np.array([0.2, 0.4, -0.1, 1.2, 0.3, 0.5, -0.2])
    rate = np.array([0.3, -0.2, 0.1, 0.25, 0.0, -0.3, 0.4])                 # rad/s on every joint
    Q = q0 + np.outer(t * 1e-9, rate)
    gt = GroundTruth(t, Q, cal, kin)
    tq = np.array([5_000_000, 123_456_789, 990_000_000, 1_000_000_000])    # between and on samples
    P, ok = gt.position_base(tq)
    assert ok.all()
    want = cal.T_base_diana_base @ kin.fk_many(q0 + np.outer(tq * 1e-9, rate)) @ cal.T_flange_tool
    np.testing.assert_allclose(P, want[:, :3, 3], atol=1e-12)


def test_ground_truth_refuses_extrapolation_and_gaps():
    t = np.array([0, 10, 20, 200, 210], dtype=np.int64) * 1_000_000       # a 180 ms gap
    Q = np.zeros((5, 7))
    Q[:, 3] = 1.0
    gt = GroundTruth(t, Q, _cal(), max_gap_ns=50_000_000)
    _, ok = gt.position_base(np.array([-1, 0, 15, 100, 205, 210, 211]) * 1_000_000)
    assert ok.tolist() == [False, True, True, False, True, True, False]


def test_ground_truth_rejects_bad_joint_arrays():
    with pytest.raises(ValueError, match="N, 7"):
        GroundTruth([0, 1], np.zeros((2, 6)), _cal())
    with pytest.raises(ValueError, match="at least 2"):
        GroundTruth([0], np.zeros((1, 7)), _cal())
    with pytest.raises(ValueError, match="NaN"):
        GroundTruth([0, 1], np.full((2, 7), np.nan), _cal())


def test_calibration_roundtrip_and_clear_errors(tmp_path):
    cal = _cal()
    cal.T_omc_base = make_T([1, 2, 3], [0, 0, 0, 1])
    cal.source = "unit test"
    save_calibration(tmp_path, cal)
    back = load_calibration(tmp_path)
    np.testing.assert_allclose(back.T_base_diana_base, cal.T_base_diana_base, atol=1e-12)
    np.testing.assert_allclose(back.T_flange_tool, cal.T_flange_tool, atol=1e-12)
    np.testing.assert_allclose(back.T_omc_base, cal.T_omc_base, atol=1e-12)
    assert back.source == "unit test"
    f = tmp_path / "calibration.yaml"
    f.write_text(yaml.safe_dump({"T_flange_tool": [0, 0, 0, 0, 0, 0, 1]}))
    with pytest.raises(CalibrationError, match="missing T_base_diana_base"):
        load_calibration(tmp_path)
    f.write_text(yaml.safe_dump({"T_flange_tool": [0, 0, 0, 0, 0, 0, 1], "T_base_diana_base": [0, 0, 0, 0, 0, 0, 2]}))
    with pytest.raises(CalibrationError, match="norm"):
        load_calibration(tmp_path)
    f.write_text("T_flange_tool: [0, 0\n")
    with pytest.raises(CalibrationError, match="YAML"):
        load_calibration(tmp_path)
    with pytest.raises(CalibrationError, match="no calibration file"):
        load_calibration(tmp_path / "nowhere")


# ---------------------------------------------------------------------------------------------- segments
def test_methods_are_the_pipeline_filters_in_the_papers_column_order():
    assert sorted(METHODS) == sorted(FILTER_NAMES) and len(METHODS) == len(FILTER_NAMES)
    assert METHODS[:5] == ("omc", "kf", "bkf", "ckf", "cbkf")  # Table 1: OMC first, CBKF last of the paper's


def test_runs_and_transition_segments_follow_the_documented_definition():
    t = np.arange(10) * 10
    #          0  1  2  3  4  5  6  7  8  9
    labels = [2, 2, 1, 1, 1, 3, 3, 3, 2, 2]
    assert runs(labels) == [(2, 0, 1), (1, 2, 4), (3, 5, 7), (2, 8, 9)]
    segs = transition_segments(t, np.array(labels))
    assert [(s["from"], s["to"], s["t0_ns"], s["t1_ns"]) for s in segs] == [
        ("G", "B", 10, 40),   # last G sample .. last B sample
        ("B", "P", 40, 70),   # last B sample .. end of the following P run
        ("P", "G", 70, 90)]
    assert transition_segments(t[:3], np.array([1, 1, 1])) == []


# ---------------------------------------------------------------------------------------------- metrics
def test_omc_mae_is_the_injected_offset(synth_eval):
    r = synth_eval.result
    want = float(np.linalg.norm(OFFSET) * 1e3)
    assert r["mae_mm"]["omc"] == pytest.approx(want, abs=1e-6)
    assert r["max_mm"]["omc"] == pytest.approx(want, abs=1e-6)
    assert r["outputs"]["omc"] > 0.9 * 8.0 * 120 - 60   # every OMC frame after the 30-sample base init


def test_compensated_filters_keep_the_bias_after_the_ots_leaves(synth_eval, synth):
    """Physics of the setup, not a number: with the OTS gone after 4 s and a constant OMC offset, a filter
    without a bias state converges to the biased OMC, the compensated ones keep the learned offset."""
    r = synth_eval.result
    s = synth_eval.series
    late = {m: s["errors"][m][(s["outputs"][m]["t_ns"] - synth[2]["t_omc_ns"][0]) * 1e-9 > 6.0] for m in METHODS}
    off = np.linalg.norm(OFFSET) * 1e3
    assert np.median(late["kf"]) == pytest.approx(off, rel=0.02)
    assert np.median(late["cbkf"]) < 0.05 * off
    assert np.median(late["ckf"]) < 0.05 * off
    assert r["mae_mm"]["cbkf"] < r["mae_mm"]["kf"] < r["mae_mm"]["omc"]


def test_errors_use_the_truth_at_each_output_stamp(synth_eval, synth):
    """The pass-through outputs exactly the recorded OMC samples: error = injected offset expressed in base."""
    _, _, truth = synth
    o = synth_eval.series["outputs"]["omc"]
    idx = np.searchsorted(truth["t_omc_ns"], o["t_ns"])
    assert np.array_equal(truth["t_omc_ns"][idx], o["t_ns"])
    np.testing.assert_allclose(o["p"] - truth["p_base_true"][idx], truth["offset_base"][idx], atol=1e-9)


def test_common_stamp_mae_and_region_split_are_consistent(synth_eval):
    r = synth_eval.result
    assert r["common_stamps"] > 0
    assert r["mae_common_mm"]["omc"] == pytest.approx(np.linalg.norm(OFFSET) * 1e3, abs=1e-6)
    fr = r["regions"]["fraction"]
    assert sum(fr.values()) == pytest.approx(1.0)
    # the region means, weighted by their output counts, give back the overall MAE
    s = synth_eval.series
    for m in METHODS:
        ok = s["valid"][m]
        assert np.nanmean(s["errors"][m][ok]) == pytest.approx(r["mae_mm"][m])


def test_evaluation_is_deterministic(synth, synth_eval):
    again = evaluate_bag(synth[0], progress=False).result
    assert json.dumps(to_json(again), sort_keys=True) == json.dumps(to_json(synth_eval.result), sort_keys=True)


def test_result_has_the_eval_json_schema(synth_eval):
    r = to_json(synth_eval.result)
    json.dumps(r, allow_nan=False)
    assert set(r["mae_mm"]) == set(FILTER_NAMES)
    assert r["task"] == "synthetic" and r["b_to_p"] is None    # this path never enters BVV then PVV


# ------------------------------------------------------------------------------------------ configuration
def test_fusion_yaml_maps_to_the_node_defaults():
    """fusion.yaml says every value equals the node's built-in default: loading it must give the dataclass
    defaults (a drift between the file and the code would make live and offline disagree); the target's ``motion``
    is the node's per-target default ``auto`` (the filters' dataclass says "fixed" for a direct caller)."""
    cfg, flat = replay_config()
    want = TargetConfig(name="tool", chain=ChainConfig(), filters=METHODS, params=FilterParams())
    # the params may be a FilterParams subclass carrying a further filter's fields too (fullperc): the paper's
    # fields must be FilterParams' defaults, and every field the defaults of the class the config built
    assert isinstance(cfg.params, FilterParams)
    assert {f.name: getattr(cfg.params, f.name) for f in dataclasses.fields(FilterParams)} == vars(want.params)
    assert cfg.params == dataclasses.replace(type(cfg.params)(), motion="auto")
    assert (cfg.slop_ns, cfg.delay_ns) == (want.slop_ns, want.delay_ns)
    for f in dataclasses.fields(ChainConfig):
        a, b = getattr(cfg.chain, f.name), getattr(want.chain, f.name)
        assert (a is None and b is None) or np.array_equal(a, b), f.name
    assert flat["idle_flush"] == 0.5


def test_fusion_config_values_are_mapped_and_checked(synth, tmp_path):
    p = tmp_path / "f.yaml"
    p.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {
        "noise": {"accel": 0.2, "global_std": 0.001}, "hop_to_bias": False, "slop": 0.002, "reorder_delay": 0.1,
        "local_chain": "direct", "init_samples": 5, "tool": {"omc_body": "t1"},
        "T_base_ots": [1, 2, 3, 0, 0, 0, 1]}}}))
    cfg, _ = replay_config(p)
    assert cfg.filters == METHODS
    assert cfg.params.accel_noise == 0.2 and cfg.params.global_std == 0.001 and cfg.params.hop_to_bias is False
    assert (cfg.slop_ns, cfg.delay_ns) == (2_000_000, 100_000_000)
    assert cfg.chain.local_chain == "direct" and cfg.chain.init_samples == 5 and cfg.chain.omc_target == "t1"
    np.testing.assert_allclose(cfg.chain.T_base_ots[:3, 3], [1, 2, 3])
    p.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {"T_rig_ots": [1, 2, 3]}}}))
    with pytest.raises(EvaluationError, match="T_rig_ots"):
        replay_config(p)
    p.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {"noise": {"global_std": -1.0}}}}))
    with pytest.raises(EvaluationError, match="global_std"):
        evaluate_bag(synth[0], progress=False, fusion_config=p)


def test_a_changed_filter_changes_the_numbers(synth, synth_eval):
    cfg, _ = replay_config()
    cfg.params = dataclasses.replace(cfg.params, hop_to_bias=False, bias_walk=1e-5)
    other = evaluate_bag(synth[0], progress=False, config=cfg).result
    assert other["mae_mm"]["omc"] == synth_eval.result["mae_mm"]["omc"]
    assert other["mae_mm"]["cbkf"] != synth_eval.result["mae_mm"]["cbkf"]


# ------------------------------------------------------------------------------------------------ report
def test_report_writes_plots_and_html(synth_eval, tmp_path):
    index = write_report(synth_eval, tmp_path)
    text = index.read_text()
    for name in ("trajectory.png", "errors.png"):
        assert (tmp_path / name).stat().st_size > 10_000
        assert name in text
    assert f"{synth_eval.result['mae_mm']['omc']:.2f}" in text
    assert not (tmp_path / "box_b_to_p.png").exists()     # no B->P segment on this path


# ------------------------------------------------------------------------- orientation, NEES, single sources
def test_orientation_error_of_exact_data_is_zero_for_every_method_and_source(synth_eval):
    """The synthetic devices report the true orientation: any frame mix-up in the ground truth's rotation (FK,
    calibration, the chain into base) would show here as degrees. (The paper's filters copy a source's
    orientation; a filter that estimates it may lag behind the turning tool and is not checked here.)"""
    ori = synth_eval.result["orientation_mae_deg"]
    assert set(ori) == set(METHODS) | {"local"}
    exact = {m: ori[m] for m in (*PAPER_METHODS, "local")}
    assert all(v is not None and v < 1e-9 for v in exact.values()), exact


def test_injected_orientation_error_is_measured_and_split_by_region(synth, synth_eval, synth_replay):
    from scipy.spatial.transform import Rotation

    from fullperc_eval.evaluation.metrics import evaluate_replay
    from fullperc_fusion.margin.layout import default_layout_path, load_layout

    rep = synth_replay()
    angle = 1.7   # deg, about an arbitrary axis in base
    d = Rotation.from_rotvec(np.radians(angle) * np.array([0.48, -0.6, 0.64]))
    o = rep.outputs["kf"]
    o["q"] = (d * Rotation.from_quat(o["q"])).as_quat()
    r = evaluate_replay(rep, load_calibration(synth[0]), load_layout(default_layout_path())).result
    assert r["orientation_mae_deg"]["kf"] == pytest.approx(angle, abs=1e-9)
    assert r["orientation_mae_deg"]["cbkf"] < 1e-9                    # the others untouched
    gvv = r["orientation_by_region_deg"]["GVV"]["kf"]
    assert gvv == pytest.approx(angle, abs=1e-9) and r["orientation_by_region_deg"]["PVV"]["kf"] is None
    assert r["mae_mm"] == synth_eval.result["mae_mm"]                 # position figures unchanged


def test_omc_position_nees_is_the_injected_offset_over_its_reported_variance(synth_eval):
    """The pass-through reports global_std^2 I; its error is the constant injected offset."""
    n = synth_eval.result["nees"]["omc"]["position"]
    want = float(np.sum(np.square(OFFSET))) / FilterParams().global_std ** 2
    assert n["mean"] == pytest.approx(want, rel=1e-6) and n["dof"] == 3
    assert n["share_95"] == (1.0 if want <= n["bound"] else 0.0)
    assert n["n"] == synth_eval.result["outputs"]["omc"]
    assert synth_eval.result["nees"]["cbkf"]["pose"]["n"] == 0        # a copied orientation is not checked


def test_raw_local_chain_is_a_single_source_and_the_tap_sees_the_omc_as_the_pass_through(synth, synth_eval):
    s = synth_eval.series
    loc = synth_eval.result["single_sources"]["local"]
    assert loc["mae_mm"] < 1e-6                                     # exact Vega, exact static link
    t_loc = s["single_sources"]["local"]["t_ns"] - synth[2]["t_omc_ns"][0]
    assert loc["n"] == len(t_loc) > 0 and t_loc.max() * 1e-9 < 4.0   # only inside the OTS window
    g, o = s["single_sources"]["global"], s["outputs"]["omc"]
    np.testing.assert_array_equal(g["t_ns"], o["t_ns"])
    np.testing.assert_allclose(g["p"], o["p"], atol=0)


def test_regions_carry_the_layouts_threshold_and_the_time_spent(synth_eval):
    from fullperc_fusion.margin.layout import default_layout_path, load_layout

    reg = synth_eval.result["regions"]
    assert reg["threshold_deg"] == load_layout(default_layout_path()).threshold_deg
    assert sum(reg["seconds"].values()) == pytest.approx(synth_eval.result["duration_s"], abs=1e-9)
    for k, f in reg["fraction"].items():
        assert reg["seconds"][k] == pytest.approx(f * synth_eval.result["duration_s"], abs=0.02)


def test_an_injected_omc_hop_is_reported_with_its_time_and_size(tmp_path):
    before, after, t_hop = (0.003, 0.0, 0.0), (-0.002, 0.003, 0.0), 5.0
    content, _ = synthetic_content(8.0, omc_offset=before, omc_offset_after=after, t_offset_change_s=t_hop,
                                   ots_window_s=(0.0, 8.0), omc_noise_m=1e-4)
    r = evaluate_bag(write_bag(tmp_path / "hop", content), progress=False).result
    assert len(r["omc_hops"]) == 1, r["omc_hops"]
    h = r["omc_hops"][0]
    assert h["t_s"] == pytest.approx(t_hop, abs=0.05)
    assert h["jump_mm"] == pytest.approx(np.linalg.norm(np.subtract(after, before)) * 1e3, abs=0.2)


def test_local_seen_mask_spans_and_stamp_tolerance():
    from fullperc_eval.evaluation.metrics import LOCAL_SPAN_GAP_NS, LOCAL_STAMP_TOL_NS, local_seen_mask

    ms = 1_000_000
    local = np.array([100, 116, 132, 400], dtype=np.int64) * ms     # a span 100-132 ms, one lone sample at 400
    t = np.array([90, 99, 100, 108, 132, 136, 138, 250, 396, 404, 406], dtype=np.int64) * ms
    want = [False, True, True, True, True, True, False, False, True, True, False]
    assert LOCAL_STAMP_TOL_NS == 5 * ms and LOCAL_SPAN_GAP_NS == 100 * ms
    assert local_seen_mask(t, local).tolist() == want
    assert local_seen_mask(t, local[::-1]).tolist() == want                  # order of the local stamps
    assert not local_seen_mask(t, np.zeros(0, dtype=np.int64)).any()
    # a gap longer than the span gap splits the span: 132 -> 400 ms is not one span
    assert not local_seen_mask(np.array([250 * ms]), local).any()
    assert local_seen_mask(np.array([250 * ms]), local, gap_ns=300 * ms).all()


def test_orientation_split_by_the_local_sources_sightings(synth, synth_replay):
    """An orientation error injected into one method only where the Vega sees the tool shows in its ``seen``
    figure alone; the raw local chain has only a ``seen`` figure."""
    from scipy.spatial.transform import Rotation

    from fullperc_eval.evaluation.metrics import evaluate_replay, local_seen_mask
    from fullperc_fusion.margin.layout import default_layout_path, load_layout

    rep = synth_replay()
    o = rep.outputs["kf"]
    seen = local_seen_mask(o["t_ns"], rep.single_sources["local"]["t_ns"])
    assert 0 < seen.sum() < len(seen)
    angle = 2.3
    d = Rotation.from_rotvec(np.radians(angle) * np.array([0.0, 0.6, 0.8]))
    q = o["q"].copy()
    q[seen] = (d * Rotation.from_quat(q[seen])).as_quat()
    o["q"] = q
    r = evaluate_replay(rep, load_calibration(synth[0]), load_layout(default_layout_path())).result
    split = r["orientation_by_local_deg"]
    assert split["kf"]["seen"] == pytest.approx(angle, abs=1e-9) and split["kf"]["unseen"] < 1e-9
    assert split["cbkf"]["seen"] < 1e-9 and split["cbkf"]["unseen"] < 1e-9
    assert split["local"]["seen"] < 1e-9 and split["local"]["unseen"] is None
