"""launch/demo.launch.py (full ROS installs) and config/demo_graph.yaml (`make demo`) describe one graph.

`launch` is not installable from the wheels, so the launch file is checked by reading it: it must parse,
start the same executables, and record the same topics as the supervisor graph.
"""

import ast
from pathlib import Path

import yaml

PKG = Path(__file__).resolve().parent.parent


def _launch_executables(tree: ast.AST) -> set[str]:
    exes = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "Node":
            kw = {k.arg: k.value for k in node.keywords}
            exes.add(f"{kw['package'].value}/{kw['executable'].value}")
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "ExecuteProcess":
            cmd = next(k.value for k in node.keywords if k.arg == "cmd")
            words = [e.value for e in cmd.elts[:4] if isinstance(e, ast.Constant)]
            assert words[:2] == ["ros2", "run"]
            exes.add(f"{words[2]}/{words[3]}")
    return exes


def test_launch_file_and_graph_agree():
    src = (PKG / "launch" / "demo.launch.py").read_text()
    tree = ast.parse(src)
    graph = yaml.safe_load((PKG / "config" / "demo_graph.yaml").read_text())
    graph_exes = {p["cmd"][0] for p in graph["processes"]}
    assert _launch_executables(tree) == graph_exes
    topics_launch = next(n for n in ast.walk(tree) if isinstance(n, ast.Assign)
                         and getattr(n.targets[0], "id", "") == "RECORD_TOPICS")
    launch_topics = {e.value for e in topics_launch.value.elts}
    rec = next(p for p in graph["processes"] if p["name"] == "record")["cmd"]
    graph_topics = set(rec[rec.index("--topics") + 1:])
    assert launch_topics == graph_topics


def _graph_fusion_params() -> dict[str, str]:
    """The ``-p name:=value`` parameters the demo graph gives fusion_node (values unparsed)."""
    cmd = next(p for p in yaml.safe_load((PKG / "config" / "demo_graph.yaml").read_text())["processes"]
               if p["name"] == "fusion")["cmd"]
    return dict(cmd[i + 1].split(":=", 1) for i, w in enumerate(cmd) if w == "-p")


def test_the_targets_fusion_parameters_are_the_demos_in_graph_launch_file_and_offline_evaluation(tmp_path):
    """The demo's live fusion_node and its offline evaluation must fuse the hand-held instrument with the same motion
    (graph/demo.py DEMO_TARGET_PARAMS, which fusion_params_with writes for the evaluation), or live and offline differ
    for it; the shipped fusion.yaml sets no target's motion (motion auto)."""
    from fullperc_eval.graph.demo import DEMO_TARGET_PARAMS, fusion_params_with

    want = dict(DEMO_TARGET_PARAMS)
    assert want == {"instrument.motion": "hand"}
    shipped = yaml.safe_load((PKG.parent / "fullperc_fusion" / "config" / "fusion.yaml").read_text())
    params = next(v for k, v in shipped.items() if k.split("/")[-1] == "fusion_node")["ros__parameters"]
    assert "instrument" not in params and set(params["tool"]) == {"omc_body", "ots_tool"}
    offline = yaml.safe_load(fusion_params_with(None, tmp_path).read_text())
    offline = next(iter(offline.values()))["ros__parameters"]
    assert {f"instrument.{k}": v for k, v in offline["instrument"].items()} == want
    given = _graph_fusion_params()
    assert {k: yaml.safe_load(v) for k, v in given.items() if k.startswith(("instrument.", "tool."))} == want
    tree = ast.parse((PKG / "launch" / "demo.launch.py").read_text())
    fusion = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Node"
                  and any(k.arg == "executable" and k.value.value == "fusion_node" for k in n.keywords))
    params = next(k.value for k in fusion.keywords if k.arg == "parameters").elts[0]
    launch = {k.value: v.value for k, v in zip(params.keys, params.values, strict=True)
              if isinstance(k, ast.Constant) and k.value.startswith(("instrument.", "tool."))}
    assert launch == want


def test_fusion_node_gets_the_same_shutdown_grace_in_graph_and_launch_file():
    """fusion_node fuses what its input queues hold at SIGINT (seconds of samples on a busy machine): the graph's
    per-process grace and the launch file's sigterm_timeout give it the same time before SIGTERM."""
    fusion = next(p for p in yaml.safe_load((PKG / "config" / "demo_graph.yaml").read_text())["processes"]
                  if p["name"] == "fusion")
    tree = ast.parse((PKG / "launch" / "demo.launch.py").read_text())
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Node"
                and any(k.arg == "executable" and k.value.value == "fusion_node" for k in n.keywords))
    timeout = next(k.value.value for k in node.keywords if k.arg == "sigterm_timeout")
    assert float(timeout) == float(fusion["grace"]) >= 10


def test_the_demo_stops_the_sources_then_fusion_then_margin_then_the_recorder():
    """fusion_node publishes its queued backlog as it exits, margin_node labels it, the recorder records both: each
    must still run while the one before it drains (margin_node stopped first lost the task's last region)."""
    graph = yaml.safe_load((PKG / "config" / "demo_graph.yaml").read_text())
    stage = {name: i for i, names in enumerate(graph["stop_stages"]) for name in names}
    assert sorted(stage) == sorted(p["name"] for p in graph["processes"])
    assert max(stage[n] for n in ("sim", "ndi", "diana", "omc")) < stage["fusion"] < stage["margin"] < stage["record"]


def test_the_recorder_holds_a_burst_of_a_fusion_node_catching_up():
    """A fusion_node behind its inputs publishes up to its ``qos_depth`` outputs per topic in one callback; the
    recorder polls its queues every 10 ms, so its keep-last depth must hold such a burst (at 1000, a busy demo
    run lost 594 of one side-by-side topic's 2,000 messages while the node's other topics came through)."""
    from fullperc_eval.bag.record import build_parser
    from fullperc_fusion.fusion_config import spec

    assert build_parser().parse_args(["--topics", "/x"]).subscription_depth >= 2 * spec("qos_depth").default


def test_the_demos_offline_evaluation_settles_links_as_its_node_does():
    """The demo's node keeps ``history`` (LIVE_HISTORY_S) and settles an item's static links ``reorder_delay`` after
    its stamp (DEMO_REORDER_S, below the history); the offline evaluation of the recording uses the same
    ``reorder_delay``, or live and offline map the first items with different links (graph.demo says why)."""
    from fullperc_eval.graph.demo import DEMO_REORDER_S, LIVE_HISTORY_S

    params = _graph_fusion_params()
    assert float(params["history"]) == LIVE_HISTORY_S
    assert float(params["reorder_delay"]) == DEMO_REORDER_S < LIVE_HISTORY_S


# ----------------------------------------------------------------------------------------------- bring-up graph
def _graph_params(proc: dict) -> dict[str, str]:
    """A graph process's ``-p name:=value`` parameters (values unfilled: ``{placeholder}`` as written)."""
    cmd = proc["cmd"]
    return dict(cmd[i + 1].split(":=", 1) for i, w in enumerate(cmd) if w == "-p")


def _launch_nodes(tree: ast.AST) -> dict[str, ast.Call]:
    """executable -> the Node(...) call of a launch file."""
    return {kw["executable"].value: n for n in ast.walk(tree)
            if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Node"
            for kw in [{k.arg: k.value for k in n.keywords}]}


def _launch_value(v: ast.AST) -> str:
    """A launch parameter value as the graph writes it: a constant as is, ``C("x")`` as ``{x}``."""
    if isinstance(v, ast.Call) and getattr(v.func, "id", "") == "C":
        return "{" + v.args[0].value + "}"
    assert isinstance(v, ast.Constant), ast.dump(v)
    return str(v.value)


def test_bringup_launch_file_and_graph_agree():
    """launch/bringup.launch.py and config/bringup_graph.yaml: the same executables, each with the same parameters
    from the same arguments, the same parameter file for fusion_node, the same optional diana_state, and the same
    arguments with the same defaults (required in both where the graph has no default)."""
    import re

    graph = yaml.safe_load((PKG / "config" / "bringup_graph.yaml").read_text())
    tree = ast.parse((PKG / "launch" / "bringup.launch.py").read_text())
    procs = {p["cmd"][0].split("/")[1]: p for p in graph["processes"]}
    nodes = _launch_nodes(tree)
    assert set(nodes) == set(procs) == {"fusion_node", "margin_node", "omc_driver", "ndi_driver", "diana_state"}
    assert _launch_executables(tree) == {p["cmd"][0] for p in graph["processes"]}
    for exe, proc in procs.items():
        params = next(k.value for k in nodes[exe].keywords if k.arg == "parameters").elts
        files = [_launch_value(e) for e in params if not isinstance(e, ast.Dict)]
        launch = {k.value: _launch_value(v) for d in params if isinstance(d, ast.Dict)
                  for k, v in zip(d.keys, d.values, strict=True)}
        cmd = proc["cmd"]
        assert files == [cmd[i + 1] for i, w in enumerate(cmd) if w == "--params-file"], exe
        assert launch == _graph_params(proc), exe
    # diana_state is optional in both, on the same argument
    cond = next(k.value for k in nodes["diana_state"].keywords if k.arg == "condition")
    assert _launch_value(cond.args[0]) == procs["diana_state"]["when"] == "{with_diana}"
    assert all("when" not in p for n, p in procs.items() if n != "diana_state")
    # the arguments: every placeholder of the graph, with the graph's defaults
    launch_args = ast.literal_eval(next(n.value for n in ast.walk(tree) if isinstance(n, ast.Assign)
                                        and getattr(n.targets[0], "id", "") == "ARGUMENTS"))
    text = yaml.safe_dump(graph["processes"])
    placeholders = set(re.findall(r"\{(\w+)\}", text))
    assert set(launch_args) == placeholders
    defaults = {k: str(v) for k, v in graph["vars"].items()}
    only_optional = {"diana_library"}       # needed by diana_state alone: launch declares it with '' (its docstring)
    assert {k: v for k, v in launch_args.items() if v is not None and k not in only_optional} == defaults
    assert {k for k, v in launch_args.items() if v is None} == placeholders - set(defaults) - only_optional
    assert launch_args["diana_library"] == "" and "{diana_library}" in str(procs["diana_state"]["cmd"])
    fusion = next(k.value.value for k in nodes["fusion_node"].keywords if k.arg == "sigterm_timeout")
    assert float(fusion) == float(procs["fusion_node"]["grace"])


def test_the_bringup_graph_offers_no_rom_and_loads_only_with_every_device_named(tmp_path):
    """The bring-up must never upload fullperc's synthetic emulator ROMs to a real tracker: no default names a ROM,
    and without the user's arguments the graph does not load, naming each one that is missing."""
    from fullperc_eval.graph.supervisor import GraphError, load_graph

    path = PKG / "config" / "bringup_graph.yaml"
    graph = yaml.safe_load(path.read_text())
    assert not any(".rom" in str(v) or "emulator_roms" in str(v) for v in graph["vars"].values())
    assert "tool_roms" not in graph["vars"]
    try:
        load_graph(path, {})
    except GraphError as e:
        msg = str(e)
    else:
        raise AssertionError("the bring-up graph loaded without a device address")
    for name in ("ndi_address", "tools", "tool_roms", "nokov_server", "nokov_sdk", "bodies", "targets",
                 "fusion_params"):
        assert f"{{{name}}}" in msg and f"--set {name}=" in msg
    assert "diana_library" not in msg                    # diana_state is off by default
    given = {n: "x" for n in ("ndi_address", "tools", "tool_roms", "nokov_server", "nokov_sdk", "bodies",
                              "targets", "fusion_params")}
    assert [p.name for p in load_graph(path, given).processes] == ["fusion", "margin", "omc", "ndi"]
    try:
        load_graph(path, given | {"with_diana": "true"})
    except GraphError as e:
        assert "{diana_library}" in str(e)
    else:
        raise AssertionError("diana_state started without its library")


def test_fusion_node_reads_the_drivers_frames_in_graph_and_launch_file():
    """The demo's fusion_node reads /omc/bodies and /ots/bodies (``inputs: frames``) in both descriptions, and the
    graph starts the task only once the drivers see it matched on them."""
    assert _graph_fusion_params()["inputs"] == "frames"
    tree = ast.parse((PKG / "launch" / "demo.launch.py").read_text())
    fusion = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Node"
                  and any(k.arg == "executable" and k.value.value == "fusion_node" for k in n.keywords))
    params = next(k.value for k in fusion.keywords if k.arg == "parameters").elts[0]
    launch = {k.value: v for k, v in zip(params.keys, params.values, strict=True) if isinstance(k, ast.Constant)}
    assert launch["inputs"].value == "frames"
    procs = {p["name"]: p for p in yaml.safe_load((PKG / "config" / "demo_graph.yaml").read_text())["processes"]}
    assert "subscribers on /omc/bodies: [1-9]" in procs["omc"]["ready"]["log"]
    assert "subscribers on /ots/bodies: [1-9]" in procs["ndi"]["ready"]["log"]
