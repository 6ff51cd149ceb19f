"""The batched replay (evaluation/batch.py) equals the per-sample replay, and falls back to it where it must.

Equality is exact: every output array (positions, biases, covariances, quaternions, stamps, flags), the
single-source tap, the pipeline statistics (key order included), the warnings and the whole evaluation result,
on a committed sample bag and on synthetic recordings with an idle gap longer than max_gap (idle flush and
re-initialisation), a hop of the OMC, an OTS occlusion and OTS samples arriving after later OMC ones.
Where the batched path cannot reproduce the per-sample result (late samples, an invalid sample, an unsupported
configuration) the replay runs the per-sample path by itself: ``path``/``fallback`` say so and the result is
the per-sample one.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.transforms import T_to_pq
from fullperc_eval.evaluation import metrics
from fullperc_eval.evaluation.batch import _matrices, _to_pq, unsupported_reason
from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_eval.evaluation.replay import replay
from fullperc_eval.sim.dataset import synthetic_content, write_bag
from fullperc_fusion.pipeline.frame_chain import ChainConfig, pose_to_T
from fullperc_fusion.pipeline.ordered import TargetConfig

ROOT = Path(__file__).resolve().parents[3]
SAMPLE = ROOT / "bags" / "paper" / "G-B-P"
FIVE = ("omc", "kf", "bkf", "ckf", "cbkf")


def _assert_same(a, b) -> None:
    assert list(a.outputs) == list(b.outputs)
    for f in b.outputs:
        assert list(a.outputs[f]) == list(b.outputs[f])
        for k, y in b.outputs[f].items():
            x = a.outputs[f][k]
            assert x.dtype == y.dtype and x.shape == y.shape, (f, k)
            assert np.array_equal(x, y, equal_nan=True), (f, k, np.nanmax(np.abs(x - y)))
    for role, d in b.single_sources.items():
        for k, y in d.items():
            assert np.array_equal(a.single_sources[role][k], y, equal_nan=True), (role, k)
    assert list(a.pipeline_stats.items()) == list(b.pipeline_stats.items())
    assert a.warnings == b.warnings
    assert list(a.counts.items()) == list(b.counts.items())
    assert (a.messages, a.task, a.start_ns) == (b.messages, b.task, b.start_ns)
    assert np.array_equal(a.joint_t_ns, b.joint_t_ns) and np.array_equal(a.joint_q, b.joint_q)
    assert len(a.omc_base_poses) == len(b.omc_base_poses)
    assert all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1])
               for x, y in zip(a.omc_base_poses, b.omc_base_poses, strict=True))


def _synthetic(path: Path, *, ots_latency_ms: float = 30.0, bad_quat: bool = False, base_drift_m: float = 0.0,
               ots_bump_m: float = 0.0) -> Path:
    c, _ = synthetic_content(14.0, omc_offset=(0.003, 0.0, 0.0), omc_offset_after=(0.006, 0.002, 0.0),
                             t_offset_change_s=11.0, ots_window_s=(2.0, 9.0), omc_noise_m=2e-4, ots_noise_m=1e-4,
                             seed=3)
    tool = c.omc.bodies["tool"]
    t = (c.omc.t_ns - c.omc.t_ns[0]) * 1e-9
    gap = (t >= 12.0) & (t < 12.8)    # no target sample for 0.8 s: idle flush, every filter re-initialises
    occl = (t >= 4.0) & (t < 4.5)     # OMC occluded while the OTS sees the tool: local-only items
    vis = tool.visible & ~gap & ~occl
    c.omc.bodies["tool"] = dataclasses.replace(tool, visible=vis)
    ots_tool = c.ots.bodies["tool"]
    to = (c.ots.t_ns - c.ots.t_ns[0]) * 1e-9
    c.ots.bodies["tool"] = dataclasses.replace(ots_tool, visible=ots_tool.visible & ~((to >= 12.0) & (to < 12.8)))
    c.ots = dataclasses.replace(c.ots, latency_ns=int(ots_latency_ms * 1e6))
    if bad_quat:
        q = c.omc.bodies["tool"].quat_xyzw.copy()
        q[600] = (0.0, 0.0, 0.0, 1.5)   # finite but far from unit norm: the pipeline rejects it
        c.omc.bodies["tool"] = dataclasses.replace(c.omc.bodies["tool"], quat_xyzw=q)
    if base_drift_m:   # the OMC base marker creeps during the link calibration: the collection is refused
        b = c.omc.bodies["base"]
        c.omc.bodies["base"] = dataclasses.replace(b, position=b.position + np.outer(np.clip(t / 10.0, 0, 1),
                                                                                      (base_drift_m, 0.0, 0.0)))
    if ots_bump_m:     # the Vega is bumped after the calibration: the link monitor reports it
        b = c.ots.bodies["base"]
        bump = np.outer(to >= 11.0, (0.0, ots_bump_m, 0.0))
        c.ots.bodies["base"] = dataclasses.replace(b, position=b.position + bump)
    return write_bag(path, c)


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    return _synthetic(tmp_path_factory.mktemp("batch") / "synthetic")


def test_synthetic_batched_equals_per_sample(synth):
    cfg = TargetConfig(filters=FIVE)
    a = replay(synth, cfg, progress=False)
    b = replay(synth, cfg, progress=False, per_sample=True)
    assert a.path == "batched" and a.fallback == ""
    assert b.path == "per-sample"
    _assert_same(a, b)
    # the stream exercised what it is meant to: hops, local-only items, re-initialisation after the gap
    o = a.outputs["cbkf"]
    assert o["hop"].any()
    assert ((o["sources"] & 1) == 0).any() and ((o["sources"] & 2) == 0).any() and (o["sources"] == 3).any()
    assert (np.diff(o["t_ns"]) > 500_000_000).any()


def test_sample_bag_evaluation_identical(monkeypatch):
    if not (SAMPLE / "metadata.yaml").is_file():
        pytest.skip("sample bag not present")
    cfg = TargetConfig(filters=FIVE)
    replays = []   # the replay each evaluation ran (the evaluation only reads it): compared below as well

    def recorded(*args, **kw):
        replays.append(replay(*args, **kw))
        return replays[-1]
    monkeypatch.setattr(metrics, "replay", recorded)
    a = evaluate_bag(SAMPLE, progress=False, config=cfg)
    b = evaluate_bag(SAMPLE, progress=False, config=cfg, per_sample=True)
    assert json.dumps(a.result) == json.dumps(b.result)   # every figure, in the same order
    assert [r.path for r in replays] == ["batched", "per-sample"]
    _assert_same(*replays)


def test_late_samples_fall_back_with_the_per_sample_result(tmp_path):
    bag = _synthetic(tmp_path / "late", ots_latency_ms=90.0)   # OTS arrives after 2 slop + delay: late samples
    cfg = TargetConfig(filters=FIVE)
    a = replay(bag, cfg, progress=False)
    b = replay(bag, cfg, progress=False, per_sample=True)
    assert a.path == "per-sample" and "late" in a.fallback
    assert b.pipeline_stats.get("late", 0) > 0
    _assert_same(a, b)


@pytest.mark.parametrize(("kw", "why", "key"), [({"base_drift_m": 0.004}, "refused", "calibration_refused"),
                                                ({"ots_bump_m": 0.006}, "bump", "link_bumped_checks")],
                         ids=["refused-calibration", "bumped-link"])
def test_link_events_fall_back(tmp_path, kw, why, key):
    bag = _synthetic(tmp_path / "links", **kw)
    cfg = TargetConfig(filters=FIVE)
    a = replay(bag, cfg, progress=False)
    assert a.path == "per-sample" and why in a.fallback
    assert a.pipeline_stats.get(key, 0) > 0
    _assert_same(a, replay(bag, cfg, progress=False, per_sample=True))


def test_matrices_equal_pose_to_T():
    rng = np.random.default_rng(7)
    q = rng.standard_normal((2000, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    q *= 1.0 + rng.uniform(-5e-3, 5e-3, (2000, 1))   # off unit norm within pose_to_T's tolerance: renormalised
    p = rng.uniform(-2, 2, (2000, 3))
    T = _matrices(p, q)
    assert all(np.array_equal(T[i], pose_to_T((p[i], q[i]))) for i in range(len(p)))
    P, Q = _to_pq(T @ T[::-1])
    for i in range(len(p)):
        pr, qr = T_to_pq(T[i] @ T[len(p) - 1 - i])
        assert np.array_equal(P[i], pr) and np.array_equal(Q[i], qr)


def test_invalid_sample_falls_back(tmp_path):
    bag = _synthetic(tmp_path / "bad", bad_quat=True)
    cfg = TargetConfig(filters=FIVE)
    a = replay(bag, cfg, progress=False)
    assert a.path == "per-sample" and "quaternion" in a.fallback
    assert a.pipeline_stats.get("rejected_nonunit") == 1
    _assert_same(a, replay(bag, cfg, progress=False, per_sample=True))


def test_filters_without_batched_form_run_per_sample_beside_the_batched_ones(synth):
    cfg = TargetConfig(filters=("omc", "cbkf", "fullperc", "kf"))
    a = replay(synth, cfg, progress=False)
    assert a.path == "batched+per-sample" and "fullperc" in a.fallback
    _assert_same(a, replay(synth, cfg, progress=False, per_sample=True))


def test_unsupported_configuration_falls_back(synth):
    cfg = TargetConfig(filters=FIVE, chain=ChainConfig(local_chain="direct"))
    assert unsupported_reason(cfg)
    a = replay(synth, cfg, progress=False)
    assert a.path == "per-sample" and a.fallback == unsupported_reason(cfg)
    _assert_same(a, replay(synth, cfg, progress=False, per_sample=True))


def test_supported_configurations():
    assert unsupported_reason(TargetConfig(filters=FIVE)) == ""
    assert unsupported_reason(TargetConfig(filters=("cbkf",))) == ""
    assert unsupported_reason(TargetConfig(filters=FIVE, chain=ChainConfig(local_chain="tracked")))
    from fullperc_fusion.pipeline.sources import SourceSet, SourceSpec

    d = SourceSet()
    extra = SourceSpec("atracsys", "local", "/atracsys", None, "std", ChainConfig())
    assert "further" in unsupported_reason(TargetConfig(filters=FIVE, sources=SourceSet(d.glob, (*d.locals, extra))))
    noisy = dataclasses.replace(d.locals[0], noise_std=2e-4)
    assert "noise_std" in unsupported_reason(TargetConfig(filters=FIVE, sources=SourceSet(d.glob, (noisy,))))


def test_cli_per_sample_option_gives_the_same_json(synth, tmp_path):
    """``evaluate`` (every method: the five batched, fullperc per sample) and ``evaluate --per-sample``."""
    from fullperc_eval.evaluation.cli import main

    a, b = tmp_path / "batched.json", tmp_path / "per_sample.json"
    assert main([str(synth), "--quiet", "--json", str(a)]) == 0
    assert main([str(synth), "--quiet", "--json", str(b), "--per-sample"]) == 0
    assert a.read_text() == b.read_text()
    assert "fullperc" in json.loads(a.read_text())["mae_mm"]


@pytest.mark.parametrize("chain", [ChainConfig(ots_target="absent"), ChainConfig(omc_base="absent"),
                                   ChainConfig(static_links="average")],
                         ids=["no-ots-target", "no-omc-base-link", "average-links"])
def test_sample_bag_other_chains_batched_and_equal(chain):
    """No OTS target (global-only items), no OMC base (the global link never comes: local-only outputs), the
    average link mode: still batched, still equal."""
    if not (SAMPLE / "metadata.yaml").is_file():
        pytest.skip("sample bag not present")
    cfg = TargetConfig(filters=FIVE, chain=chain)
    a = replay(SAMPLE, cfg, progress=False)
    assert a.path == "batched"
    _assert_same(a, replay(SAMPLE, cfg, progress=False, per_sample=True))


def test_the_batched_replay_drives_the_pipeline_through_its_public_api():
    """batch.py uses TargetPipeline's public stages (observe_*, enqueue, poll_items / flush_items, counts, stats):
    no private attribute of it, and its synchronizer, chain and monitor are never operated directly (only read)."""
    import ast

    from fullperc_eval.evaluation import batch

    reads = {"sync": {"pending", "counts"}, "chain": {"links"}}
    tree = ast.parse(Path(batch.__file__).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "pipe":
            assert not node.attr.startswith("_"), f"pipe.{node.attr}"
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) \
                and isinstance(node.value.value, ast.Name) and node.value.value.id == "pipe":
            assert node.attr in reads.get(node.value.attr, set()), f"pipe.{node.value.attr}.{node.attr}"
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    assert not names & {"sync", "monitor", "chain"}, "a pipeline part held beside the pipeline"
