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
