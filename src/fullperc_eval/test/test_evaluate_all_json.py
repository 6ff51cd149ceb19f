"""``make eval``'s JSON (evaluation/evaluate_all.py) names the config files it used the same way on every machine.

The committed ``bags/<profile>/eval.json`` must not hold the absolute path of the machine that wrote it
(test/test_code_rules.py checks every tracked file): a file in an installed package's share directory is
recorded as ``package://<pkg>/<file>``, a file below the current directory relative to it.
"""

from __future__ import annotations

import json
import os

from fullperc_eval.evaluation import evaluate_all
from fullperc_eval.sim.dataset import synthetic_content, write_bag


def test_json_records_config_files_without_machine_paths(tmp_path, monkeypatch):
    content, _ = synthetic_content(3.0)
    write_bag(tmp_path / "bags" / "synthetic", content)
    monkeypatch.chdir(tmp_path)
    assert evaluate_all.main(["--bags", "bags", "--json", "eval.json", "--quiet"]) == 0
    config = json.loads((tmp_path / "eval.json").read_text())["config"]
    # the defaults: fusion_node's params file and the camera layout, both installed by fullperc_fusion
    assert config["fusion_config"] == "package://fullperc_fusion/config/fusion.yaml", config
    assert config["layout"] == "package://fullperc_fusion/config/or_layout.yaml", config


def test_portable_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    share = os.path.join(str(tmp_path), "install", "pkg_a", "share", "pkg_a", "config", "x.yaml")
    assert evaluate_all.portable_path(share) == "package://pkg_a/config/x.yaml"
    assert evaluate_all.portable_path(str(tmp_path / "src" / "y.yaml")) == os.path.join("src", "y.yaml")
    assert evaluate_all.portable_path("rel/z.yaml") == "rel/z.yaml"
    outside = os.path.join(os.path.dirname(str(tmp_path)), "elsewhere.yaml")  # not below the current directory
    assert evaluate_all.portable_path(outside) == outside
