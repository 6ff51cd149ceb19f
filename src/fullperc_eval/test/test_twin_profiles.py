"""Twin profiles (``config/profile_*.yaml``): raw-sensor statistics within their targets; the accuracy summary.

The profiles are calibrated on raw-sensor figures only (``make twin-report``); this pins them on the seeds the report
uses by default (0-1; both profiles, six tasks each: ~1 min). The accuracy helpers are checked on hand-made rows.
"""

from __future__ import annotations

import pytest

from fullperc_eval.evaluation.accuracy import holds, summarize
from fullperc_eval.evaluation.twin_report import DEFAULT_SEEDS, check_targets, parse_seeds, report
from fullperc_eval.sim.scene import PROFILES, SceneError, load_profile, load_scene_config, merge_overrides
from fullperc_eval.sim.tasks import TASKS


def test_parse_seeds():
    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("0,4, 7") == [0, 4, 7]
    assert parse_seeds("5") == [5]
    with pytest.raises(ValueError):
        parse_seeds("")


def test_profiles_override_the_scene_and_record_their_name():
    base = load_scene_config()
    assert base["_profile"] == "base"
    for p in PROFILES:
        cfg = load_scene_config(profile=p)
        assert cfg["_profile"] == p and cfg["_plans_file"] == "task_plans_site.yaml"
        assert cfg["bodies"]["base"]["pose_in_omc"] != base["bodies"]["base"]["pose_in_omc"]
        assert cfg["bodies"]["tool"] == base["bodies"]["tool"]          # untouched parts stay
        assert load_profile(p)["targets"]
    with pytest.raises(SceneError, match="unknown twin profile"):
        load_scene_config(profile="nope")
    assert merge_overrides({"a": {"b": 1, "c": [1]}}, {"a": {"c": [2]}}) == {"a": {"b": 1, "c": [2]}}


def test_check_targets_ranges():
    rows = [{"task": "G-B-P", "omc_mae_mm": 3.2, "omc_b_to_p_median_mm": 9.0},
            {"task": "P-G-B", "omc_mae_mm": 2.0}]
    c = {(x["target"], x["of"]): x["ok"] for x in check_targets(rows, {"omc_mae_mm": [2.5, 4.5],
                                                                      "b_to_p_median_mm": [4.5, 7.0]})}
    assert c == {("omc_mae_mm", "G-B-P"): True, ("omc_mae_mm", "P-G-B"): False,
                 ("b_to_p_median_mm", "G-B-P"): False}


def test_accuracy_summary_orderings_and_ratios():
    def row(task, seed, omc, kf, bkf, ckf, cbkf):
        return {"task": task, "seed": seed, "mae_mm": dict(omc=omc, kf=kf, bkf=bkf, ckf=ckf, cbkf=cbkf),
                "b_to_p": None}
    rows = [row("G-B-P", 0, 4, 2, 2, 1.5, 1.5), row("G-B-P", 1, 4, 2, 2, 2.5, 2.0), row("P-G-B", 0, 2, 3, 3, 3, 3)]
    assert holds(rows[0]["mae_mm"]) and not holds(rows[1]["mae_mm"])
    s = summarize(rows)
    assert s["share_full_order"] == pytest.approx(1 / 3)
    assert s["share_cbkf_kf_omc"] == pytest.approx(2 / 3)
    assert s["cbkf_over_omc"]["max"] == pytest.approx(1.5)
    assert s["table1_mae_mm"]["G-B-P"]["cbkf"][0] == pytest.approx(1.75)


REPORT_SEEDS = parse_seeds(DEFAULT_SEEDS)   # what `make twin-report` uses by default


@pytest.mark.parametrize("profile", PROFILES)
def test_committed_profile_is_within_its_raw_sensor_targets(profile):
    """Every target is met on seeds 0-1 except the profile's declared ``known_misses`` (each measured and explained
    in the profile file; none today); a known miss that is met now must be removed from the list (it would hide a
    regression)."""
    known = set(load_profile(profile).get("known_misses") or ())
    assert known <= set(load_profile(profile)["targets"])
    rep = report(profile, REPORT_SEEDS)
    assert {c["of"] for c in rep["checks"] if c["target"] == "omc_mae_mm"} == set(TASKS)   # every task checked
    bad = [c for c in rep["checks"] if not c["ok"] and c["target"] not in known]
    assert not bad, f"profile {profile}, seeds {REPORT_SEEDS}: raw-sensor figures outside the targets: {bad}"
    met = {c["target"] for c in rep["checks"]} - {c["target"] for c in rep["checks"] if not c["ok"]}
    assert not (known & met), f"profile {profile}: known misses now met, drop them: {known & met}"
