"""``make demo PROFILE=… CALIBRATION=…``: the demo's twin profile and static-link calibration reach the processes.

What the graph starts is checked by loading the installed graph with the demo's values (the live run is
test/test_demo_graph.py): the profile goes to the simulator, the calibration file to fusion_node (quoted, so an
empty value stays a string), and the offline evaluation gets a fusion params file naming the same calibration.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from fullperc_eval.graph.cli import main as supervisor_main
from fullperc_eval.graph.demo import DEMO_REORDER_S, DEMO_TARGET_PARAMS, fusion_params_with, graph_path, sim_diana_base
from fullperc_eval.graph.supervisor import load_graph
from fullperc_fusion.fusion_config import default_fusion_config_path, node_key, read_params_file

ROOT = Path(__file__).resolve().parents[3]
VALUES = {"task": "B-G-P", "out": "demo-out", "omc_port": "1", "diana_port": "2", "vega_port": "3",
          "diana_base": "[0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0]"}


def _cmds(values: dict[str, str]) -> dict[str, list[str]]:
    return {p.name: p.cmd for p in load_graph(graph_path(ROOT), {**VALUES, **values}).processes}


def test_profile_and_calibration_reach_the_simulator_and_fusion_node():
    cmds = _cmds({"profile": "spec", "calibration_file": "/cal/or1.yaml", "vega_bump": "12:0.004:0.3"})
    sim = cmds["sim"]
    assert sim[sim.index("--profile") + 1] == "spec"
    assert sim[sim.index("--vega-bump") + 1] == "12:0.004:0.3"
    assert "calibration_file:='/cal/or1.yaml'" in cmds["fusion"]
    # defaults: the paper twin, fusion_node calibrating itself (an empty string parameter), no bump
    cmds = _cmds({})
    assert cmds["sim"][cmds["sim"].index("--profile") + 1] == "paper"
    assert "calibration_file:=''" in cmds["fusion"]
    assert cmds["sim"][cmds["sim"].index("--vega-bump") + 1] == ""
    assert "tf.diana_base:=[0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0]" in cmds["fusion"]


def test_the_arm_base_given_to_fusion_node_is_the_simulators():
    """run_demo fills ``diana_base`` from :func:`sim_diana_base`: the simulator's T_base_diana_base of the task plan
    (the same transform ``sim --calibration-out`` writes; the live demo test compares it with that file)."""
    from fullperc_common.transforms import inv_T, make_T
    from fullperc_eval.sim.dataset import sim_calibration
    from fullperc_eval.sim.run import simulate
    from fullperc_eval.sim.scene import build_scene
    from fullperc_eval.sim.tasks import plan_task

    v = sim_diana_base("P-G-B", 2, "spec")
    scene = build_scene(2, profile="spec")
    plan = plan_task("P-G-B", scene)
    run = simulate(scene.with_diana_base(plan.T_omc_diana_base), plan.arc, task="P-G-B")
    want = sim_calibration(run).T_base_diana_base
    assert np.allclose(make_T(v[:3], v[3:]), want, atol=1e-12)
    assert not np.allclose(want, inv_T(scene.T_omc_base), atol=1e-3)   # not the identity of the arm in omc


def test_offline_evaluation_uses_the_same_calibration(tmp_path):
    cal = tmp_path / "or1.yaml"
    path = fusion_params_with(cal, tmp_path)
    got, default = read_params_file(path), read_params_file(default_fusion_config_path())
    assert got["calibration_file"] == str(cal)
    demo_own = ("calibration_file", "reorder_delay", *DEMO_TARGET_PARAMS)
    assert {k: v for k, v in got.items() if k not in demo_own} == \
        {k: v for k, v in default.items() if k not in demo_own}
    assert got["reorder_delay"] == DEMO_REORDER_S
    assert {k: got[k] for k in DEMO_TARGET_PARAMS} == DEMO_TARGET_PARAMS   # the instrument's preset, as the node gets
    assert (d := yaml.safe_load(path.read_text()))[node_key(d)]["ros__parameters"]["calibration_file"] == str(cal)


def test_a_missing_calibration_file_is_refused_before_anything_starts(tmp_path, capsys):
    rc = supervisor_main(["demo", "--out", str(tmp_path), "--calibration", str(tmp_path / "nope.yaml")])
    assert rc == 2 and "nope.yaml does not exist" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())   # no run directory, no process
