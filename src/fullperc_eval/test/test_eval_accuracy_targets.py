"""``make accuracy`` for every target of the bags (evaluation/accuracy_targets.py and accuracy.py's use of it).

Hand-made task-seed rows of the tool and of a hand-held ``instrument``; expected figures are recomputed here from the
rows. The whole ``accuracy.main`` runs on hand-made per-seed results (no simulation), and the target list and the
row of one real evaluation come from the committed seed-0 bags.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fullperc_eval.evaluation.accuracy import json_lines, summarize
from fullperc_eval.evaluation.accuracy_goals import goal_checks
from fullperc_eval.evaluation.accuracy_targets import (
    format_target,
    split_targets,
    target_json_lines,
    target_summary,
    task_row,
    task_targets,
)
from fullperc_eval.evaluation.evaluate_all import TASK_ORDER
from fullperc_eval.evaluation.target_goals import target_goal_checks

ROOT = Path(__file__).resolve().parents[3]
METHODS = ("omc", "kf", "bkf", "ckf", "cbkf", "fullperc")


def _row(task: str, seed: int, target: str, scale: float) -> dict:
    rng = np.random.default_rng([seed, TASK_ORDER.index(task), len(target)])
    mae = dict(zip(METHODS, scale * np.sort(rng.uniform(1.0, 4.0, 6))[::-1], strict=True))
    reg = {g: {m: v * f for m, v in mae.items()} for g, f in (("BVV", 0.3), ("GVV", 1.2), ("PVV", 1.5))}
    if task == "P-B-G":
        reg["PVV"] = {}                                  # a task that never enters PVV
    nees = {m: {"position": {"n": 100 + seed, "share_95": 0.9 + 0.01 * i, "mean": 3.0},
                "pose": {"n": 0, "share_95": None, "mean": None}} for i, m in enumerate(METHODS)}
    r = {"task": task, "seed": seed, "profile": "x", "mae_mm": mae, "mae_by_region_mm": reg,
         "b_to_p": {"max_mm": dict(mae), "median_mm": dict(mae)} if task == "G-B-P" and target == "tool" else None,
         "orientation_mae_deg": None, "orientation_by_region_deg": None, "orientation_by_local_deg": None,
         "before_first_local": None, "nees": nees,
         "motion_presets_mae_mm": {"arm": 1.02 * mae["fullperc"], "hand": 1.1 * mae["fullperc"], "static": 3.0}}
    return {**r, "target": target} if target != "legacy" else r


def _seed_rows(seed: int, targets=("tool", "instrument")) -> list[dict]:
    return [_row(t, seed, g, 1.0 if g == "tool" else 2.0) for t in TASK_ORDER for g in targets]


def test_target_summary_by_its_definitions():
    rows = [r for s in (0, 1, 2) for r in _seed_rows(s) if r["target"] == "instrument"]
    ts = target_summary(rows)
    assert ts["n_task_seeds"] == 18 and ts["seeds"] == [0, 1, 2] and list(ts["table1_mae_mm"]) == list(TASK_ORDER)
    v = [r["mae_mm"]["cbkf"] for r in rows if r["task"] == "P-G-B"]
    assert ts["table1_mae_mm"]["P-G-B"]["cbkf"] == pytest.approx((np.mean(v), np.std(v, ddof=1)))
    pvv = [r["mae_by_region_mm"]["PVV"] for r in rows if r["mae_by_region_mm"]["PVV"]]
    assert ts["region_n"] == {"BVV": 18, "GVV": 18, "PVV": 15}
    assert ts["mae_by_region_mm"]["PVV"]["kf"][0] == pytest.approx(np.mean([p["kf"] for p in pvv]))
    assert ts["region_over_omc"]["PVV"]["fullperc"] == pytest.approx(
        np.mean([p["fullperc"] for p in pvv]) / np.mean([p["omc"] for p in pvv]))
    assert ts["region_over_omc"]["GVV"]["omc"] == pytest.approx(1.0)
    n = np.array([100 + r["seed"] for r in rows])
    assert ts["nees"]["ckf"]["position"]["n"] == n.sum()
    assert ts["nees"]["ckf"]["position"]["share_95"] == pytest.approx(0.93)
    text = format_target("spec", "instrument", ts, target_goal_checks("spec", "instrument", rows, ts["nees"]))
    assert "/sim/truth/instrument" in text and "Table 1" in text and "NEES pooled" in text
    assert "PVV (15)" in text and "acceptance checks" in text and "mae_vs_omc_GVV" in text


def test_split_targets_and_the_target_lines():
    rows = _seed_rows(0, ("instrument", "tool", "legacy"))   # a row without a target is the tool's (older runs)
    split = split_targets(rows)
    assert list(split) == ["tool", "instrument"] and len(split["tool"]) == 12 and len(split["instrument"]) == 6
    ts = {t: target_summary(rs) for t, rs in split.items()}
    inst = {x["name"]: x for x in target_json_lines("paper", "instrument", ts["instrument"])}
    assert inst["instrument_mae_fullperc_G-B-P"]["value"] == pytest.approx(
        split["instrument"][0]["mae_mm"]["fullperc"], abs=1e-4)
    assert inst["instrument_region_mae_fullperc_GVV"]["over_omc"] == pytest.approx(
        ts["instrument"]["region_over_omc"]["GVV"]["fullperc"], abs=1e-4)
    assert "instrument_nees_position_share95_kf" in inst
    assert all(x["target"] == "instrument" and x["profile"] == "paper" for x in inst.values())
    tool = [x["name"] for x in target_json_lines("paper", "tool", ts["tool"])]   # the tool's Table 1 and NEES exist
    assert tool and all(n.startswith("tool_region_mae_") for n in tool)


def _fake(monkeypatch, targets):
    from concurrent.futures import ThreadPoolExecutor

    from fullperc_eval.evaluation import accuracy as acc

    def fake_run_seed(profile, seed, cache, fusion_config, key, presets=True):
        rows = [dict(r, profile=profile) for r in _seed_rows(seed, targets)]
        return {"profile": profile, "seed": seed, "rows": rows, "generated": 0, "sim_s": 0.0, "eval_s": 0.0}

    monkeypatch.setattr(acc, "run_seed", fake_run_seed)
    monkeypatch.setattr(acc, "ProcessPoolExecutor", ThreadPoolExecutor)
    monkeypatch.setattr(acc, "as_completed", lambda fs: list(fs)[::-1])
    monkeypatch.setattr(acc, "twin_hash", lambda p: f"hash-{p}")
    return acc


def test_main_reports_every_target_and_keeps_the_tools_output(tmp_path, monkeypatch, capsys):
    acc = _fake(monkeypatch, ("tool", "instrument"))
    out = tmp_path / "accuracy.json"
    assert acc.main(["--seeds", "0-2", "--profile", "both", "--json", str(out), "--cache", str(tmp_path)]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.startswith("{")]
    d = json.loads(out.read_text())
    tool_rows = {p: [r for s in (0, 1, 2) for r in _seed_rows(s) if r["target"] == "tool"] for p in d["profiles"]}
    former = []
    for p in d["profiles"]:   # the tool's summary, goals and lines are those of its rows alone
        s = summarize([dict(r, profile=p) for r in tool_rows[p]])
        g = goal_checks(p, s)
        assert {k: v for k, v in d["summary"][p].items() if k != "targets"} == json.loads(json.dumps(s))
        assert d["goals"][p] == json.loads(json.dumps(g))
        former += json_lines(p, s, g)
    assert lines[:len(former)] == json.loads(json.dumps(former))       # printed first, unchanged
    rest = lines[len(former):]
    assert rest and all("target" in x and (x["name"].startswith(f"{x['target']}_") or x["name"].startswith("goal41_"))
                        for x in rest)
    assert d["targets"] == {"paper": ["tool", "instrument"], "spec": ["tool", "instrument"]}
    for p in d["profiles"]:
        assert set(d["summary"][p]["targets"]) == {"tool", "instrument"}
        inst = [r for r in d["task_seeds"] if r["profile"] == p and r["target"] == "instrument"]
        assert len(inst) == 18
        want = target_goal_checks(p, "instrument", inst, d["summary"][p]["targets"]["instrument"]["nees"])
        assert [c for c in d["target_goals"][p] if c["target"] == "instrument"] == json.loads(json.dumps(want))
        assert {c["target"] for c in d["target_goals"][p]} == {"tool", "instrument"}
    cbkf = {c["profile"]: c for c in d["target_goals"].values() for c in c if c["goal"] == "mae_vs_cbkf"
            and c["target"] == "tool"}
    assert cbkf["paper"]["bound"] == ">= 0.10" and cbkf["spec"]["bound"] == ">= 0.00"
    order = [(r["profile"], r["seed"]) for r in d["task_seeds"]]
    assert order == sorted(order, key=lambda x: (("paper", "spec").index(x[0]), x[1]))


def _committed_bags_as_cache(tmp_path: Path) -> None:
    """The committed seed-0 ``paper`` bags linked where ``run_seed("paper", 0, tmp_path, ..., key="k")`` looks."""
    d = tmp_path / "paper-k" / "seed0"
    d.mkdir(parents=True)
    for t in TASK_ORDER:
        (d / t).symlink_to(ROOT / "bags" / "paper" / t)


def test_run_seed_evaluates_every_target_of_the_committed_bags(tmp_path, monkeypatch):
    """The real path up to the evaluation: the committed seed-0 bags stand in for the cache (links, nothing
    generated); the targets come from the bags' truth topics; each evaluation is asked for its target."""
    from fullperc_eval.evaluation import accuracy, metrics

    _committed_bags_as_cache(tmp_path)
    asked = []

    class Fake:
        def __init__(self, bag, target):
            self.result = {"mae_mm": {"omc": 2.0, "fullperc": 1.0 if target == "tool" else 3.0},
                           "mae_by_region_mm": {}, "b_to_p": None, "nees": {}}

    def fake_evaluate_bag(bag, *, fusion_config=None, target="tool", progress=True):
        asked.append((Path(bag).name, target, fusion_config))
        return Fake(bag, target)

    monkeypatch.setattr(metrics, "evaluate_bag", fake_evaluate_bag)
    monkeypatch.setattr(accuracy, "generate", lambda *a, **k: pytest.fail("a committed bag was regenerated"))
    r = accuracy.run_seed("paper", 0, str(tmp_path), "cfg.yaml", "k", presets=False)
    targets = ("tool", "instrument", "reference")   # the arm-held tool, then the twin's targets by name
    assert asked == [(t, g, "cfg.yaml") for t in TASK_ORDER for g in targets]
    assert [(x["task"], x["target"]) for x in r["rows"]] == [(t, g) for t in TASK_ORDER for g in targets]
    assert {x["mae_mm"]["fullperc"] for x in r["rows"] if x["target"] != "tool"} == {3.0}
    assert r["generated"] == 0


def test_run_seed_evaluates_fullperc_with_each_motion_preset_for_the_auto_check(tmp_path, monkeypatch):
    """With presets (the default), each bag-target is evaluated once more per motion preset: fullperc (and the OMC)
    only, the target's motion set to the preset's fields and "fixed", everything else as configured; the row keeps
    fullperc's MAE per preset."""
    from fullperc_eval.evaluation import accuracy, metrics
    from fullperc_fusion.filters.motion import PRESETS

    _committed_bags_as_cache(tmp_path)
    seen = []

    class Fake:
        def __init__(self, value):
            self.result = {"mae_mm": {"omc": 2.0, "fullperc": value}, "mae_by_region_mm": {}, "b_to_p": None,
                           "nees": {}}

    def fake_evaluate_bag(bag, *, fusion_config=None, target="tool", progress=True, config=None):
        if config is None:
            return Fake(1.0)
        seen.append((Path(bag).name, target, config.filters, config.params))
        preset = next(p for p, f in PRESETS.items() if all(getattr(config.params, k) == v for k, v in f.items()))
        return Fake({"arm": 1.5, "hand": 2.5, "static": 3.5}[preset])

    monkeypatch.setattr(metrics, "evaluate_bag", fake_evaluate_bag)
    r = accuracy.run_seed("paper", 0, str(tmp_path), None, "k")
    assert len(seen) == len(TASK_ORDER) * 3 * len(PRESETS)
    assert all(f == ("omc", "fullperc") and p.motion == "fixed" for _, _, f, p in seen)
    assert {x["target"]: x["motion_presets_mae_mm"] for x in r["rows"]}["instrument"] == {
        "arm": 1.5, "hand": 2.5, "static": 3.5}


def test_the_row_of_a_real_instrument_evaluation_feeds_the_checks(cached_evaluate_bag):
    """One committed bag, its instrument evaluated with fusion.yaml: the row keeps the figures the checks read and
    the checks give what the evaluation's own figures give."""
    bag = ROOT / "bags" / "paper" / "P-G-B"
    assert task_targets(bag) == ["tool", "instrument", "reference"]
    res = cached_evaluate_bag(bag, "instrument").result
    row = task_row("P-G-B", 0, "paper", "instrument", res)
    assert row["target"] == "instrument" and row["mae_mm"] == res["mae_mm"]
    ts = target_summary([row])
    checks = {c["goal"]: c for c in target_goal_checks("paper", "instrument", [row], ts["nees"])}
    mae = res["mae_mm"]
    assert checks["mae_vs_omc_every_task_seed"]["value"] == pytest.approx(mae["fullperc"] / mae["omc"])
    for reg in ("GVV", "PVV"):
        per = res["mae_by_region_mm"].get(reg) or {}
        if per.get("omc"):
            assert checks[f"mae_vs_omc_{reg}"]["value"] == pytest.approx(per["fullperc"] / per["omc"])
    assert checks["mae_vs_cbkf"]["value"] == pytest.approx(1 - mae["fullperc"] / mae["cbkf"])
    assert checks["mae_vs_cbkf"]["bound"] == ">= 0.00"
    assert ts["nees"]["fullperc"]["position"]["n"] == res["nees"]["fullperc"]["position"]["n"] > 0
    assert {m for m in checks["nees_share95_filters"]["meet"] + checks["nees_share95_filters"]["miss"]} == \
        {m for m in res["nees"] if m != "omc"}


def test_the_results_page_renders_every_target(tmp_path, monkeypatch, capsys, load_script):
    """scripts/results_page.py on an accuracy.json with targets (written by main from hand-made rows): the
    instrument's Table 1, NEES and regions, each target's region table and the checks with their signed margins;
    an accuracy.json without targets renders none of it (the committed page stays as it is until a new run)."""
    import shutil

    acc = _fake(monkeypatch, ("tool", "instrument"))
    for rel in ("README.md", "bags/paper/eval.json", "bags/spec/eval.json"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, tmp_path / rel)
    assert acc.main(["--seeds", "0-1", "--profile", "both", "--json", str(tmp_path / "bags/accuracy.json"),
                     "--cache", str(tmp_path)]) == 0
    capsys.readouterr()
    page = load_script("results_page").render_page(tmp_path)
    d = json.loads((tmp_path / "bags/accuracy.json").read_text())
    spec = page.split("### Twin profile `spec`")[1].split("## The committed sample bags")[0]
    assert "`instrument` (truth `/sim/truth/instrument`): position MAE [mm]" in spec
    assert "`tool`: position MAE [mm] by region" in spec and "`instrument`: position MAE [mm] by region" in spec
    ts = d["summary"]["spec"]["targets"]["instrument"]
    gvv = ts["mae_by_region_mm"]["GVV"]["fullperc"]
    assert f"{gvv[0]:.2f} ± {gvv[1]:.2f} ({ts['region_over_omc']['GVV']['fullperc']:.2f})" in spec
    checks = d["target_goals"]["spec"]
    for c in checks:
        line = next(x for x in spec.splitlines() if x.startswith(f"| `{c['target']}` | `{c['goal']}` |")
                    and (c["method"] == "all" or f"| {c['method'].upper()} |" in x or f"`{c['method']}`" in x))
        assert f"{c['margin']:+.3f}" in line and {True: "met", False: "**missed**"}[c["ok"]] in line
    assert not [x for x in spec.splitlines() if "`instrument`" in x and len(x) > 200]
    for p in d["profiles"]:
        del d["summary"][p]["targets"]
    del d["target_goals"]
    (tmp_path / "bags/accuracy.json").write_text(json.dumps(d))
    assert "by region" not in load_script("results_page").render_page(tmp_path).split("## The committed")[0]
