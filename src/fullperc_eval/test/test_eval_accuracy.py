"""``make accuracy``'s summary with the issue-18 additions (evaluation/accuracy.py, accuracy_goals.py).

Hand-made task-seed rows; every expected value is recomputed here from those rows by the goal's definition.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from fullperc_eval.evaluation.accuracy import format_summary, json_lines, pooled_nees, summarize
from fullperc_eval.evaluation.accuracy_goals import format_goals, goal_checks
from fullperc_eval.evaluation.evaluate_all import TASK_ORDER

PAPER = ("omc", "kf", "bkf", "ckf", "cbkf")


def _rows(with_new: bool, seeds=(0, 1, 2)) -> list[dict]:
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        for k, t in enumerate(TASK_ORDER):
            mae = dict(zip(PAPER, sorted(rng.uniform(1.0, 4.0, 5), reverse=True), strict=True))
            r = {"task": t, "seed": seed, "profile": "x", "mae_mm": mae, "mae_by_region_mm": {}, "b_to_p": None}
            if t == "G-B-P":
                r["b_to_p"] = {"max_mm": dict(mae), "median_mm": {m: v / 2 for m, v in mae.items()}}
            if with_new:
                mae["fullperc"] = mae["cbkf"] * (0.7 + 0.05 * k) if k != 3 else mae["omc"] * 1.08
                if t == "G-B-P":
                    r["b_to_p"]["max_mm"]["fullperc"] = r["b_to_p"]["median_mm"]["fullperc"] = 1.0
                r["orientation_mae_deg"] = {**{m: 1.0 + 0.1 * k for m in PAPER}, "fullperc": 0.2 + 0.01 * seed,
                                            "local": 0.25 if k != 2 else 0.1}
                r["orientation_by_region_deg"] = {g: dict(r["orientation_mae_deg"]) for g in ("BVV", "GVV", "PVV")}
                r["orientation_by_local_deg"] = {
                    **{m: {"seen": 1.0 + 0.1 * k, "unseen": 0.8} for m in PAPER},
                    "fullperc": {"seen": 0.15 + 0.01 * seed, "unseen": 0.7 + (0.2 if k == 4 else 0.0)},
                    "local": {"seen": 0.2 if k != 1 else 0.17, "unseen": None}}
                n = 100 * (k + 1)
                r["nees"] = {m: {"position": {"n": n, "share_95": 0.5 + 0.05 * k, "mean": 3.0 + k},
                                 "pose": {"n": 0, "share_95": None, "mean": None}} for m in (*PAPER, "fullperc")}
                r["nees"]["fullperc"]["pose"] = {"n": n, "share_95": 0.93, "mean": 6.1}
            rows.append(r)
    return rows


def _seed_mean(rows, task, m, key="mae_mm"):
    return float(np.mean([r[key][m] for r in rows if r["task"] == task]))


def test_goals_are_computed_by_their_definitions():
    rows = _rows(True)
    s = summarize(rows)
    g = {x["goal"]: x for x in goal_checks("paper", s)}
    f = np.mean([_seed_mean(rows, t, "fullperc") for t in TASK_ORDER])
    c = np.mean([_seed_mean(rows, t, "cbkf") for t in TASK_ORDER])
    assert g["position_vs_cbkf"]["value"] == pytest.approx(1 - f / c)
    assert g["position_vs_cbkf"]["ok"] is bool(1 - f / c >= 0.20)
    assert "position_vs_omc" not in g                        # the spec-profile goal
    ratios = {t: _seed_mean(rows, t, "fullperc", "orientation_mae_deg")
              / min(_seed_mean(rows, t, "omc", "orientation_mae_deg"), _seed_mean(rows, t, "local",
                                                                                  "orientation_mae_deg"))
              for t in TASK_ORDER}
    worst = max(ratios, key=ratios.get)
    assert worst == TASK_ORDER[2]                            # where the raw local chain is best (0.1 deg)
    assert g["orientation_vs_single_sources"]["value"] == pytest.approx(ratios[worst])
    assert g["orientation_vs_single_sources"]["ok"] is False and "LOCAL" in g["orientation_vs_single_sources"]["detail"]
    n = np.array([100 * (k + 1) for k in range(6)] * 3)
    share = np.array([0.5 + 0.05 * k for k in range(6)] * 3)
    assert g["nees_position_share95"]["value"] == pytest.approx(float((n * share).sum() / n.sum()))
    assert g["nees_pose_share95"]["ok"] is True
    sp = {x["goal"]: x for x in goal_checks("spec", s)}
    omc = {t: _seed_mean(rows, t, "fullperc") / _seed_mean(rows, t, "omc") for t in TASK_ORDER}
    assert sp["position_vs_omc"]["value"] == pytest.approx(max(omc.values()))
    assert sp["position_vs_omc"]["ok"] is False and TASK_ORDER[3] in sp["position_vs_omc"]["detail"]
    assert "position_vs_cbkf" not in sp
    text = "\n".join(format_goals(goal_checks("paper", s)))
    assert "MISSED orientation_vs_single_sources" in text


def test_same_samples_orientation_goal_by_its_definition():
    """Where the Vega sees the tool: the method against the better of the OMC and the local chain on those
    outputs; elsewhere against the OMC. The worst per-task ratio of seed means is the value."""
    rows = _rows(True)
    s = summarize(rows)

    def sm(t, m, part):
        return float(np.mean([r["orientation_by_local_deg"][m][part] for r in rows if r["task"] == t]))

    ratios = {}
    for t in TASK_ORDER:
        ratios[(t, "seen")] = sm(t, "fullperc", "seen") / min(sm(t, "omc", "seen"), sm(t, "local", "seen"))
        ratios[(t, "unseen")] = sm(t, "fullperc", "unseen") / sm(t, "omc", "unseen")
    worst = max(ratios, key=ratios.get)
    assert worst == (TASK_ORDER[4], "unseen")               # 0.9 vs the OMC's 0.8
    for profile in ("paper", "spec"):
        g = {x["goal"]: x for x in goal_checks(profile, s)}["orientation_vs_single_sources_same_samples"]
        assert g["value"] == pytest.approx(ratios[worst]) and g["ok"] is False
        assert TASK_ORDER[4] in g["detail"] and "OMC" in g["detail"] and "does not" in g["detail"]
    # better everywhere: met; the old task-wide goal is still reported beside it, unchanged
    for r in rows:
        r["orientation_by_local_deg"]["fullperc"]["unseen"] = 0.7
    g = {x["goal"]: x for x in goal_checks("paper", summarize(rows))}
    assert g["orientation_vs_single_sources_same_samples"]["ok"] is True
    assert g["orientation_vs_single_sources_same_samples"]["value"] == pytest.approx(
        max(max(sm(t, "fullperc", "seen") / min(sm(t, "omc", "seen"), sm(t, "local", "seen")), 0.7 / 0.8)
            for t in TASK_ORDER))
    assert g["orientation_vs_single_sources"]["ok"] is False


def test_goals_without_the_method_are_not_met_but_not_available():
    s = summarize(_rows(False))
    g = goal_checks("paper", s) + goal_checks("spec", s)
    assert g and all(x["ok"] is None and x["value"] is None for x in g)


def test_json_lines_of_the_papers_five_are_unchanged_by_a_new_method():
    """The lines of the paper's five methods come first, identical whether a further filter is evaluated or not;
    the new method's lines, orientation, NEES and goals only follow them."""
    before = json_lines("paper", summarize(_rows(False)))
    rows = _rows(True)
    s = summarize(rows)
    after = json_lines("paper", s, goal_checks("paper", s))
    assert after[:len(before)] == before
    names = [x["name"] for x in after[len(before):]]
    assert "mae_fullperc_G-B-P" in names and "orientation_mae_local_P-G-B" in names
    assert "nees_pose_share95_fullperc" in names and "goal_position_vs_cbkf_fullperc" in names
    assert not any(n.startswith(f"mae_{m}_") for n in names for m in PAPER)
    json.dumps(after, allow_nan=False)


def test_pooled_nees_weights_by_outputs_and_summary_prints_the_new_tables():
    rows = _rows(True, seeds=(0,))
    p = pooled_nees(rows)
    n = np.array([100 * (k + 1) for k in range(6)])
    assert p["kf"]["position"]["mean"] == pytest.approx(float((n * (3.0 + np.arange(6))).sum() / n.sum()))
    assert p["kf"]["pose"] == {"n": 0, "share_95": None, "mean": None}
    s = summarize(rows)
    text = format_summary("paper", s, goal_checks("paper", s))
    assert "Orientation MAE [deg]" in text and "LOCAL" in text and "FULLPERC" in text
    assert "NEES pooled" in text and "Issue 18 goals for FULLPERC" in text
    seen = text.split("while the Vega sees the tool")[1].split("while it does not")[0]
    assert "LOCAL" in seen and "0.170 ± 0.000" in seen            # the LOCAL cell of task 1 (seen only)
    unseen = text.split("while it does not")[1].split("NEES pooled")[0]
    assert "LOCAL" not in unseen and "0.900 ± 0.000" in unseen    # FULLPERC unseen in task 4 (0.7 + 0.2)
    assert s["table1_orientation_deg"]["G-B-P"]["fullperc"][0] == pytest.approx(0.2)


def _fake_seeds(monkeypatch, used: dict | None = None):
    """accuracy with hand-made per-seed results instead of simulation (``used``: (profile, seed) -> the fusion
    config each seed was evaluated with), threads instead of processes, a fixed twin hash."""
    from concurrent.futures import ThreadPoolExecutor

    from fullperc_eval.evaluation import accuracy as acc

    def fake_run_seed(profile, seed, cache, fusion_config, key, presets=True):
        if used is not None:
            used[(profile, seed)] = fusion_config
        rows = [dict(r, profile=profile) for r in _rows(True, seeds=(seed,))]
        return {"profile": profile, "seed": seed, "rows": rows, "generated": 0, "sim_s": 0.0, "eval_s": 0.0}

    monkeypatch.setattr(acc, "run_seed", fake_run_seed)
    monkeypatch.setattr(acc, "ProcessPoolExecutor", ThreadPoolExecutor)
    monkeypatch.setattr(acc, "twin_hash", lambda p: f"hash-{p}")
    return acc


def test_main_keeps_every_former_key_and_adds_the_goals(tmp_path, monkeypatch, capsys):
    """The whole ``make accuracy`` path on hand-made per-seed results (no simulation): accuracy.json keeps the
    keys others read and gains ``goals``; the goal lines are printed."""
    acc = _fake_seeds(monkeypatch)
    monkeypatch.setattr(acc, "as_completed", lambda fs: list(fs)[::-1])   # seeds finishing in the other order
    out = tmp_path / "accuracy.json"
    assert acc.main(["--seeds", "0-1", "--profile", "both", "--json", str(out), "--cache", str(tmp_path),
                     "--noise-model", "builtin"]) == 0
    d = json.loads(out.read_text())
    order = [(r["profile"], r["seed"]) for r in d["task_seeds"]]
    assert order == sorted(order, key=lambda x: (("paper", "spec").index(x[0]), x[1]))   # file order fixed
    assert d["noise_model"] == {"mode": "builtin", "paper": None, "spec": None}
    assert {"profiles", "seeds", "fusion_config", "twin_hash", "summary", "task_seeds"} <= set(d)
    for p in d["profiles"]:
        s = d["summary"][p]
        assert {"n_task_seeds", "seeds", "table1_mae_mm", "share_full_order", "share_cbkf_kf_omc",
                "share_cbkf_le_omc", "cbkf_over_omc", "table2_gbp_b_to_p_mm", "table2_n"} <= set(s)
        assert {g["goal"] for g in d["goals"][p]} >= {"orientation_vs_single_sources", "nees_position_share95"}
    assert {g["goal"] for g in d["goals"]["paper"]} >= {"position_vs_cbkf"}
    assert {g["goal"] for g in d["goals"]["spec"]} >= {"position_vs_omc"}
    text = capsys.readouterr().out
    assert '"name": "goal_position_vs_cbkf_fullperc"' in text and "Issue 18 goals for FULLPERC" in text


def test_main_evaluates_each_profile_with_its_calibrated_noise_model(tmp_path, monkeypatch):
    """``--noise-model calibrated``: each profile's seeds run with the fusion config that reads the
    noise model fitted on that profile's calibration seeds, and accuracy.json records the model."""
    used, fitted_on = {}, {}
    acc = _fake_seeds(monkeypatch, used)

    def fake_cal(profile, key, cache, fusion_config, seeds):
        fitted_on[profile] = seeds
        return {"fusion_config": f"cfg-{profile}.yaml", "noise_model_file": f"nm-{profile}.yaml",
                "noise_model": {"omc": {"margin_std": 1e-3 if profile == "paper" else 5e-4}}}

    monkeypatch.setattr(acc, "calibrated_fusion_config", fake_cal)
    out = tmp_path / "accuracy.json"
    assert acc.main(["--seeds", "0-1", "--profile", "both", "--json", str(out), "--cache", str(tmp_path),
                     "--noise-model", "calibrated"]) == 0
    assert fitted_on == {"paper": [100, 101, 102], "spec": [100, 101, 102]}
    assert used == {(p, s): f"cfg-{p}.yaml" for p in ("paper", "spec") for s in (0, 1)}
    d = json.loads(out.read_text())
    assert d["noise_model"]["mode"] == "calibrated" and d["noise_model"]["calibration_seeds"] == [100, 101, 102]
    assert d["noise_model"]["paper"]["omc"]["margin_std"] == 1e-3


def test_calibration_seeds_that_are_also_evaluated_are_refused(tmp_path, capsys):
    from fullperc_eval.evaluation import accuracy as acc

    assert acc.main(["--seeds", "0-9", "--profile", "spec", "--noise-model", "calibrated",
                     "--calibration-seeds", "9-10", "--json", "",
                     "--cache", str(tmp_path)]) == 2
    assert "calibration seeds [9] are also evaluated" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())   # refused before any bag was generated


def test_a_given_noise_model_file_is_used_for_every_profile(tmp_path):
    from fullperc_eval.evaluation.accuracy import noise_model_configs
    from fullperc_fusion.filters.noise_model_file import noise_model_yaml
    from fullperc_fusion.fusion_config import load_fusion_config

    nm = tmp_path / "noise.yaml"
    nm.write_text(noise_model_yaml({"margin_std": 2e-3}, {"sys_time": 7.0}, "test"))
    out = noise_model_configs(str(nm), ("paper", "spec"), {"paper": "a", "spec": "b"}, str(tmp_path), None,
                              [100], [0])
    for p in ("paper", "spec"):
        cfg, _ = load_fusion_config(out[p]["fusion_config"])
        assert cfg.omc_model.margin_std == 2e-3 and cfg.params.sys_time == 7.0
    assert noise_model_configs("builtin", ("spec",), {"spec": "b"}, str(tmp_path), None, [0], [0]) == {
        "spec": {"fusion_config": None, "noise_model_file": "", "noise_model": None}}
    with pytest.raises(ValueError, match="missing.yaml"):
        noise_model_configs(str(tmp_path / "missing.yaml"), ("spec",), {"spec": "b"}, str(tmp_path), None, [0], [1])


def test_calibrated_noise_model_of_the_committed_spec_bags_is_the_built_in_one(tmp_path, monkeypatch, cached_bag_rows):
    """The real path, no simulation: the committed spec bags stand in for calibration seed 100 (links to them
    in the cache). The config written reads the file, and the file's model is the built-in one (which is the
    spec bags' statistics, test/test_model_constants.py): what fusion_node runs by default is what the
    calibration gives for the installation it was fitted on. Each bag's raw rows are sensor_stats.bag_rows' of its
    content, computed once per test session (root conftest; test_model_constants reads the same)."""
    import dataclasses
    from pathlib import Path

    from fullperc_eval.evaluation import sensor_stats
    from fullperc_eval.evaluation.accuracy import calibrated_fusion_config
    from fullperc_fusion.filters.measurement_models import OmcModelParams
    from fullperc_fusion.fusion_config import load_fusion_config
    from fullperc_fusion.margin.layout import default_layout_path, load_layout

    bags = Path(__file__).resolve().parents[3] / "bags" / "spec"
    monkeypatch.setattr(sensor_stats, "bag_rows", cached_bag_rows)
    cached_bag_rows.prefetch([bags / t for t in TASK_ORDER], load_layout(default_layout_path()))
    d = tmp_path / "spec-k" / "seed100"
    d.mkdir(parents=True)
    for t in TASK_ORDER:
        (d / t).symlink_to(bags / t)
    r = calibrated_fusion_config("spec", "k", str(tmp_path), None, [100])
    cfg, vals = load_fusion_config(r["fusion_config"])
    assert vals["fullperc.noise_model_file"] == r["noise_model_file"]
    assert Path(r["noise_model_file"]).parent == tmp_path / "spec-k"
    builtin = dataclasses.asdict(OmcModelParams())
    for k, v in dataclasses.asdict(cfg.omc_model).items():
        assert v == pytest.approx(builtin[k], rel=0.02), k
    assert r["noise_model"]["omc"]["margin_std"] == cfg.omc_model.margin_std
    # the position error field from the raw (OMC - local chain) differences too, as fit_noise_model --write fits it:
    # the spec bags' fit is the built-in one (FullpercParams), and it reaches the filter
    bias = r["noise_model"]["omc_bias"]
    assert bias["bias_field_std"] == pytest.approx(0.341e-3, rel=0.02)
    assert bias["bias_field_length"] == pytest.approx(0.296, rel=0.02) == cfg.params.bias_field_length


def test_mae_split_at_the_first_local_sample_and_the_ceiling_it_gives():
    """metrics.first_local_split on hand-made errors (contributions add up to the MAE; invalid outputs left out;
    no local sample -> None); the summary's means and best-before, and position_vs_cbkf's ceiling from it."""
    from fullperc_eval.evaluation.metrics import first_local_split

    t = np.arange(10, dtype=np.int64) * 100
    outs = {"omc": {"t_ns": t}, "cbkf": {"t_ns": t}}
    errs = {"omc": np.arange(10.0), "cbkf": np.full(10, 2.0)}
    ok = {"omc": np.ones(10, bool), "cbkf": np.r_[np.zeros(1, bool), np.ones(9, bool)]}
    sp = first_local_split(outs, errs, ok, np.array([450, 300, 900]), 0)
    assert sp["t_s"] == pytest.approx(300e-9)
    assert sp["share"] == {"omc": 0.3, "cbkf": pytest.approx(2 / 9)}
    c = sp["contribution_mm"]["omc"]
    assert c["before"] == pytest.approx((0 + 1 + 2) / 10) and c["after"] == pytest.approx(sum(range(3, 10)) / 10)
    assert c["before"] + c["after"] == pytest.approx(errs["omc"].mean())
    assert sp["mae_mm"]["cbkf"] == {"before": 2.0, "after": 2.0}
    assert first_local_split(outs, errs, ok, None, 0) is None
    assert first_local_split(outs, errs, ok, np.zeros(0, np.int64), 0) is None

    rows = _rows(True)
    for k, r in enumerate(rows):
        r["before_first_local"] = {"share": {m: 0.3 for m in r["mae_mm"]},
                                   "contribution_mm": {m: {"before": 0.5 + 0.1 * (m == "omc") + 0.01 * k,
                                                           "after": v - 0.5} for m, v in r["mae_mm"].items()}}
    s = summarize(rows)
    best = np.mean([0.5 + 0.01 * k for k in range(len(rows))])
    assert s["before_first_local"]["best_before_mm"][0] == pytest.approx(best)
    assert s["before_first_local"]["contribution_mm"]["omc"]["before"][0] == pytest.approx(best + 0.1)
    g = {x["goal"]: x for x in goal_checks("paper", s)}["position_vs_cbkf"]
    c = np.mean([_seed_mean(rows, tk, "cbkf") for tk in TASK_ORDER])
    assert g["ceiling"] == pytest.approx(1 - best / c) and "first Vega sample" in g["detail"]
    lines = {x["name"]: x for x in json_lines("paper", s, [g])}
    assert lines["mae_before_first_local_best"]["value"] == pytest.approx(best, abs=1e-4)
    assert lines["goal_position_vs_cbkf_fullperc"]["ceiling"] == pytest.approx(1 - best / c, abs=1e-4)
    assert "split at the first Vega sample" in format_summary("paper", s)
    assert "before_first_local" not in summarize(_rows(True))      # rows without the split: no table
