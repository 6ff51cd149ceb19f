"""Issue 41's acceptance checks per target (evaluation/target_goals.py) on hand-made task-seed rows.

Every expected value is recomputed here from the rows by the check's definition; each test also moves a row across
the bound, so a check that stopped comparing (always passing, always failing) fails here.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_eval.evaluation.target_goals import (
    every_task_seed,
    format_target_goals,
    nees_checks,
    published_filters,
    region_vs_omc,
    target_goal_checks,
    target_goal_lines,
    vs_cbkf,
)

TASKS = ("G-B-P", "P-G-B", "P-B-G")


def _rows(seeds=(0, 1, 2)) -> list[dict]:
    """fullperc between CBKF and the OMC everywhere; GVV and PVV with OMC figures that differ a lot by task."""
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(100 + seed)
        for k, t in enumerate(TASKS):
            omc = float(rng.uniform(2.0, 4.0))
            mae = {"omc": omc, "cbkf": 0.8 * omc, "fullperc": 0.7 * omc}
            reg = {"BVV": {m: 0.2 * v for m, v in mae.items()},
                   "GVV": {"omc": 1.0 + k, "cbkf": 1.1 + k, "fullperc": 0.9 + k + 0.01 * seed},
                   "PVV": {"omc": 3.0, "cbkf": 3.3, "fullperc": 2.7} if k != 1 else {}}
            rows.append({"task": t, "seed": seed, "profile": "x", "mae_mm": mae, "mae_by_region_mm": reg,
                         "target": "instrument"})
    return rows


def test_every_task_seed_reports_the_worst_ratio_and_where():
    rows = _rows()
    g = every_task_seed("paper", "instrument", rows)
    assert g["value"] == pytest.approx(max(r["mae_mm"]["fullperc"] / r["mae_mm"]["omc"] for r in rows))
    assert g["ok"] is True and g["margin"] == pytest.approx(1.0 - g["value"]) and g["bound"] == "<= 1.0"
    assert "9 of 9" in g["detail"]
    bad = rows[4]
    bad["mae_mm"]["fullperc"] = 1.07 * bad["mae_mm"]["omc"]   # one task-seed worse than the OMC fails it
    g = every_task_seed("paper", "instrument", rows)
    assert g["ok"] is False and g["value"] == pytest.approx(1.07) and g["margin"] == pytest.approx(-0.07)
    assert g["where"] == {"task": bad["task"], "seed": bad["seed"]} and "8 of 9" in g["detail"]
    assert g["target"] == "instrument" and g["method"] == "fullperc" and g["profile"] == "paper"


def test_region_checks_are_ratios_of_the_means_over_task_seeds():
    rows = _rows()
    for reg in ("GVV", "PVV"):
        have = [r["mae_by_region_mm"][reg] for r in rows if r["mae_by_region_mm"][reg]]
        want = np.mean([p["fullperc"] for p in have]) / np.mean([p["omc"] for p in have])
        g = region_vs_omc("spec", "tool", rows, reg)
        assert g["goal"] == f"mae_vs_omc_{reg}" and g["value"] == pytest.approx(want) and g["ok"] is True
        assert f"over {len(have)} task-seeds" in g["detail"]
    # a ratio of means, not a mean of ratios: one task-seed far better than a tiny OMC figure, others slightly worse
    for r in rows:
        r["mae_by_region_mm"]["GVV"] = {"omc": 2.0, "fullperc": 2.1}
    rows[0]["mae_by_region_mm"]["GVV"] = {"omc": 0.1, "fullperc": 0.001}
    g = region_vs_omc("spec", "tool", rows, "GVV")
    ratios = [r["mae_by_region_mm"]["GVV"]["fullperc"] / r["mae_by_region_mm"]["GVV"]["omc"] for r in rows]
    assert np.mean(ratios) < 1.0                                     # a mean of ratios would pass ...
    assert g["value"] == pytest.approx((8 * 2.1 + 0.001) / (8 * 2.0 + 0.1)) and g["ok"] is False   # ... it fails
    assert g["margin"] == pytest.approx(1.0 - g["value"])
    for r in rows:
        r["mae_by_region_mm"].pop("PVV")
    g = region_vs_omc("spec", "tool", rows, "PVV")   # never in PVV: nothing to check (the next test)
    assert g["ok"] is True and g["value"] is None and g["margin"] is None


def test_cbkf_check_asks_ten_percent_for_the_tool_in_the_paper_profile_only():
    rows = _rows()
    for r in rows:
        r["mae_mm"]["fullperc"] = 0.95 * r["mae_mm"]["cbkf"]    # 5 % below CBKF
    red = 1 - np.mean([r["mae_mm"]["fullperc"] for r in rows]) / np.mean([r["mae_mm"]["cbkf"] for r in rows])
    tool_paper = vs_cbkf("paper", "tool", rows)
    assert tool_paper["value"] == pytest.approx(red) == pytest.approx(0.05)
    assert tool_paper["bound"] == ">= 0.10" and tool_paper["ok"] is False
    assert tool_paper["margin"] == pytest.approx(red - 0.10)
    for profile, target in (("paper", "instrument"), ("spec", "tool")):
        g = vs_cbkf(profile, target, rows)
        assert g["bound"] == ">= 0.00" and g["ok"] is True and g["margin"] == pytest.approx(red)
    rows[0]["mae_mm"]["fullperc"] = 50.0                           # one very bad run: worse than CBKF on average
    assert vs_cbkf("paper", "instrument", rows)["ok"] is False
    for r in rows:
        del r["mae_mm"]["fullperc"]
    assert vs_cbkf("paper", "tool", rows)["ok"] is None


def _nees(share: dict[str, tuple[float, float | None]]) -> dict:
    return {m: {"position": {"n": 500, "share_95": p, "mean": 3.0},
                "pose": {"n": 500 if q is not None else 0, "share_95": q, "mean": 6.0 if q is not None else None}}
            for m, (p, q) in share.items()}


def test_nees_per_published_filter_and_which_meet_it():
    nees = _nees({"omc": (0.0, None), "kf": (0.95, None), "cbkf": (0.89, None), "fullperc": (0.93, 0.91)})
    assert published_filters(nees) == ["kf", "cbkf", "fullperc"]          # the raw OMC pass-through is no filter
    out = nees_checks("paper", "instrument", nees)
    per = {(c["method"], c["goal"]): c for c in out}
    assert ("omc", "nees_position_share95") not in per and ("kf", "nees_pose_share95") not in per
    assert per[("kf", "nees_position_share95")]["ok"] is True
    assert per[("cbkf", "nees_position_share95")]["ok"] is False
    assert per[("cbkf", "nees_position_share95")]["margin"] == pytest.approx(-0.01)
    assert per[("fullperc", "nees_pose_share95")]["value"] == pytest.approx(0.91)
    summary = per[("all", "nees_share95_filters")]
    assert summary["meet"] == ["kf", "fullperc"] and summary["miss"] == ["cbkf"]
    assert summary["value"] == pytest.approx(2 / 3) and summary["ok"] is False
    # a filter meeting the position bound but not the pose one misses
    nees = _nees({"kf": (0.95, None), "fullperc": (0.93, 0.80)})
    summary = nees_checks("spec", "tool", nees)[-1]
    assert summary["miss"] == ["fullperc"] and summary["ok"] is False
    summary = nees_checks("spec", "tool", _nees({"kf": (0.95, None), "fullperc": (0.93, 0.92)}))[-1]
    assert summary["ok"] is True and summary["value"] == 1.0 and summary["miss"] == []
    assert nees_checks("spec", "tool", {})[-1]["ok"] is None


def test_a_region_the_target_never_enters_is_met_with_nothing_to_check():
    rows = _rows()
    for r in rows:
        r["mae_by_region_mm"] = {"BVV": r["mae_by_region_mm"]["BVV"]}
    c = region_vs_omc("paper", "reference", rows, "GVV")
    assert c["ok"] is True and c["value"] is None and "never in GVV" in c["detail"]
    for r in rows:   # the evaluator writes a region it never saw with null figures
        r["mae_by_region_mm"]["GVV"] = {"omc": None, "fullperc": None}
    assert region_vs_omc("paper", "reference", rows, "GVV")["ok"] is True
    rows[0]["mae_by_region_mm"]["GVV"] = {"omc": 1.0}   # entered, but without the method's figure: not met
    assert region_vs_omc("paper", "reference", rows, "GVV")["ok"] is None


def test_auto_against_the_best_motion_preset_on_the_same_task_seeds():
    from fullperc_eval.evaluation.target_goals import auto_vs_presets

    rows = _rows()
    assert auto_vs_presets("paper", "tool", rows)["ok"] is None      # no preset figures: not met by default
    for r, (arm, hand) in zip(rows, [(1.0, 2.0), (1.2, 1.8), (0.8, 2.2)], strict=False):
        r["motion_presets_mae_mm"] = {"arm": arm, "hand": hand}
    auto = np.mean([r["mae_mm"]["fullperc"] for r in rows[:3]])
    c = auto_vs_presets("paper", "tool", rows[:3])
    assert c["value"] == pytest.approx(auto / 1.0) and "best: arm" in c["detail"] and c["bound"] == "<= 1.05"
    assert c["ok"] is False and c["margin"] == pytest.approx(1.05 - auto)
    for r in rows[:3]:
        r["motion_presets_mae_mm"] = {"arm": auto + 1.0, "hand": auto - 0.01}
    c = auto_vs_presets("paper", "tool", rows[:3])
    assert c["ok"] is True and "best: hand" in c["detail"] and c["value"] == pytest.approx(auto / (auto - 0.01))
    rows[1]["motion_presets_mae_mm"] = {"arm": 1.2}   # a row without every preset is left out
    assert "over 2 task-seeds" in auto_vs_presets("paper", "tool", rows[:3])["detail"]


def test_all_checks_of_a_target_their_lines_and_table():
    rows = _rows()
    nees = _nees({"omc": (0.0, None), "cbkf": (0.97, None), "fullperc": (0.85, 0.95)})
    checks = target_goal_checks("paper", "instrument", rows, nees)
    names = [c["goal"] for c in checks]
    assert names == ["mae_vs_omc_every_task_seed", "mae_vs_omc_GVV", "mae_vs_omc_PVV", "mae_vs_cbkf",
                     "motion_auto_vs_best_preset", "nees_position_share95", "nees_position_share95",
                     "nees_pose_share95", "nees_share95_filters"]
    assert all(c["target"] == "instrument" and c["profile"] == "paper" for c in checks)
    lines = target_goal_lines(checks)
    assert [x["name"] for x in lines][:2] == ["goal41_mae_vs_omc_every_task_seed_fullperc_instrument",
                                              "goal41_mae_vs_omc_GVV_fullperc_instrument"]
    by = {x["name"]: x for x in lines}
    fp = by["goal41_nees_position_share95_fullperc_instrument"]
    assert fp["ok"] is False and fp["margin"] == pytest.approx(-0.05) and fp["unit"] == "fraction"
    assert by["goal41_nees_share95_filters_all_instrument"]["miss"] == ["fullperc"]
    assert lines[0]["where"] == checks[0]["where"]
    text = "\n".join(format_target_goals(checks))
    assert "profile paper" in text
    row = next(t for t in text.splitlines() if "nees_position_share95" in t and "FULLPERC" in t)
    assert "FAIL" in row and "-0.050" in row and ">= 0.90" in row
    row = next(t for t in text.splitlines() if "mae_vs_cbkf" in t)
    assert "PASS" in row and f"+{checks[3]['margin']:.3f}" in row
