"""Repository rules that would otherwise be checked by hand in review (CONTRIBUTING.md, "Layout and dependency
direction"):

(a) no import cycle between project modules, counting imports inside functions (a function-level import that
    closes a cycle only hides it);
(b) layering: ``fullperc_common`` imports none of the other Python packages, ``fullperc_drivers`` and
    ``fullperc_fusion`` never import ``fullperc_eval`` nor each other; inside ``fullperc_eval`` every module
    lives in a layer and imports only downward: ``graph`` -> ``evaluation`` -> ``sim`` -> {``bag``,
    ``emulators``}; ``bag`` and ``emulators`` are siblings and do not import each other;
(c) no source module (``.py`` under src/, bench/, scripts/, test/) over 600 lines;
(d) no absolute path of a particular machine (a home, a build or work directory) in a tracked file.

Every checker is a plain function with a self-test on a planted violation, so a checker that stopped finding
anything would fail here instead of passing silently. Files are those git knows (tracked, or new and not
ignored), so a violation fails before it is committed.
"""

from __future__ import annotations

import ast
import fnmatch
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 600
# fullperc_fusion, in layers since it outgrew one folder: its modules stay smaller (a module is one job)
FUSION_MAX_LINES = 500
FUSION_SRC = "src/fullperc_fusion/fullperc_fusion"
SOURCE_DIRS = ("src", "bench", "scripts", "test")


# ------------------------------------------------------------------------------------------------ files
def repo_files() -> list[Path]:
    """Tracked files plus new ones that are not ignored (those that exist); every file if git is unavailable."""
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                             capture_output=True, check=True).stdout.decode()
        names = sorted({n for n in out.split("\0") if n})
        return [ROOT / n for n in names if (ROOT / n).is_file()]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "build", "install", "log"}
        return [p for p in ROOT.rglob("*") if p.is_file() and not skip & set(p.relative_to(ROOT).parts)]


# -------------------------------------------------------------------------------------------- (a) cycles
def project_modules(src: Path = ROOT / "src") -> dict[str, Path]:
    """Module name -> file of every module of the Python packages ``src/<pkg>/<pkg>/`` (``fullperc_*``)."""
    mods: dict[str, Path] = {}
    for pkg_root in sorted(src.iterdir()):
        pkg = pkg_root / pkg_root.name
        if not pkg_root.name.startswith("fullperc_") or not (pkg / "__init__.py").is_file():
            continue
        for f in sorted(pkg.rglob("*.py")):
            parts = list(f.relative_to(pkg_root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = f
    return mods


def _known_prefix(dotted: str, known: set[str]) -> str | None:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        if ".".join(parts[:i]) in known:
            return ".".join(parts[:i])
    return None


def imports_of(name: str, source: str, is_package: bool, known: set[str]) -> set[str]:
    """Project modules that module ``name`` imports anywhere in ``source`` (module level or inside functions).

    Relative imports are resolved against the module's package; ``from pkg import sub`` counts as importing the
    module ``pkg.sub`` when that is a module, else ``pkg``; names outside ``known`` are ignored.
    """
    package = name if is_package else name.rpartition(".")[0]
    out: set[str | None] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out.update(_known_prefix(a.name, known) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                parts = parts[:len(parts) - (node.level - 1)]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for a in node.names:
                full = f"{base}.{a.name}"
                out.add(full if full in known else _known_prefix(base, known))
    out.discard(None)
    out.discard(name)
    return {m for m in out if m is not None}


def import_graph(mods: dict[str, Path] | None = None) -> dict[str, set[str]]:
    mods = project_modules() if mods is None else mods
    known = set(mods)
    return {n: imports_of(n, f.read_text(), f.name == "__init__.py", known) for n, f in mods.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every import cycle as one path ``[a, b, ..., a]`` per strongly connected component (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    comps: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                comps.append(comp)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_cycle_in(graph, c) for c in comps]


def _cycle_in(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """A shortest cycle through the first module of a strongly connected component (breadth first)."""
    start = min(comp)
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph.get(v, ()) & comp):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return [start, *reversed(path[:-1]), start] if v != start else [start, start]
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    return sorted(comp)  # not reached for a real component


def test_cycle_finder_finds_planted_cycles():
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": set(), "d": {"a"}}) == []
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"a"}}) == [["a", "a"]]
    two = find_cycles({"a": {"b"}, "b": {"a"}, "x": {"y"}, "y": {"z"}, "z": {"y"}})
    assert sorted(two) == [["a", "b", "a"], ["y", "z", "y"]]


def test_import_resolution_counts_function_level_and_relative_imports():
    known = {"pkg", "pkg.sub", "pkg.sub.a", "pkg.sub.b", "pkg.c", "other"}
    src_a = "from . import b\n"
    src_b = "def f():\n    from ..c import thing\n    import other.deep\n"
    src_c = "def g():\n    from pkg.sub import a\n"
    graph = {"pkg.sub.a": imports_of("pkg.sub.a", src_a, False, known),
             "pkg.sub.b": imports_of("pkg.sub.b", src_b, False, known),
             "pkg.c": imports_of("pkg.c", src_c, False, known)}
    assert graph == {"pkg.sub.a": {"pkg.sub.b"}, "pkg.sub.b": {"pkg.c", "other"}, "pkg.c": {"pkg.sub.a"}}
    assert find_cycles(graph) == [["pkg.c", "pkg.sub.a", "pkg.sub.b", "pkg.c"]]
    # a package's own relative imports resolve inside it
    assert imports_of("pkg.sub", "from .a import x\n", True, known) == {"pkg.sub.a"}


def test_no_import_cycles():
    graph = import_graph()
    assert len(graph) > 50 and any(graph.values())  # the scan found the project
    cycles = find_cycles(graph)
    assert not cycles, "import cycles (function-level imports count):\n  " + "\n  ".join(
        " -> ".join(c) for c in cycles)


# ------------------------------------------------------------------------------------------- (b) layers
# Python packages that a package must not import (fullperc_msgs is generated; everyone may use it).
FORBIDDEN_PACKAGES = {
    "fullperc_common": {"fullperc_drivers", "fullperc_fusion", "fullperc_eval"},
    "fullperc_drivers": {"fullperc_fusion", "fullperc_eval"},
    "fullperc_fusion": {"fullperc_drivers", "fullperc_eval"},
}
# Sub-package layers of the packages built in sub-packages, top to bottom: a module may import its own sub-package
# and lower ranks only; sub-packages of equal rank may not import each other. ``TOP`` is the rank of the modules
# directly in the package (fullperc_fusion's nodes and their cores); None: every module must be in a sub-package.
EVAL_LAYERS = {"graph": 3, "evaluation": 2, "sim": 1, "bag": 0, "emulators": 0}
FUSION_LAYERS = {"filters": 0, "calibration": 0, "margin": 0, "pipeline": 1}
LAYERS: dict[str, tuple[dict[str, int], int | None]] = {
    "fullperc_eval": (EVAL_LAYERS, None),
    "fullperc_fusion": (FUSION_LAYERS, 2),
}
TOP = "(top)"


def _layer(module: str) -> str | None:
    """The sub-package (or TOP) that ``module`` belongs to in its layered package; None for the package itself."""
    parts = module.split(".")
    if len(parts) < 2:
        return None
    layers, _ = LAYERS[parts[0]]
    if parts[1] in layers:
        return parts[1]
    return TOP if len(parts) == 2 else parts[1]


def _rank(pkg: str, layer: str) -> int | None:
    layers, top = LAYERS[pkg]
    return top if layer == TOP else layers.get(layer)


def _chain(pkg: str) -> str:
    layers, top = LAYERS[pkg]
    ranks = sorted({*layers.values(), *([top] if top is not None else [])}, reverse=True)
    return " -> ".join(" | ".join(sorted([n for n, r in layers.items() if r == k] + (["top"] if k == top else [])))
                       for k in ranks)


def layering_violations(graph: dict[str, set[str]]) -> list[str]:
    out = []
    for src, dsts in sorted(graph.items()):
        top = src.split(".")[0]
        if top in LAYERS and src != top and _rank(top, _layer(src) or "") is None:
            out.append(f"{src}: not in a layer of {top} ({', '.join(LAYERS[top][0])})")
        for dst in sorted(dsts):
            dtop = dst.split(".")[0]
            if dtop in FORBIDDEN_PACKAGES.get(top, ()):
                out.append(f"{src} -> {dst}: {top} must not import {dtop}")
            if top == dtop and top in LAYERS:
                ls, ld = _layer(src), _layer(dst)
                if ls is None or ld is None or ls == ld:
                    continue  # a package's __init__ holds only a docstring; a layer may import itself
                rs, rd = _rank(top, ls), _rank(top, ld)
                if rs is None or rd is None or rs <= rd:
                    out.append(f"{src} -> {dst}: {top}.{ls} must not import {top}.{ld} ({_chain(top)})")
    return out


def test_layering_checker_finds_planted_violations():
    planted = {
        "fullperc_fusion.margin.view_margin": {"fullperc_drivers.diana_kinematics", "fullperc_common.transforms"},
        "fullperc_common.share": {"fullperc_eval.bag.types"},
        "fullperc_eval.sim.run": {"fullperc_eval.graph.demo", "fullperc_eval.sim.scene", "fullperc_eval.bag.writer"},
        "fullperc_eval.bag.reader": {"fullperc_eval.emulators.vega_device"},
        "fullperc_eval.graph.demo": {"fullperc_eval.evaluation.metrics", "fullperc_eval.bag.reader",
                                     "fullperc_fusion.margin.layout"},
        "fullperc_eval.stray": set(),
        "fullperc_fusion.filters.paper_fast": {"fullperc_fusion.filters.api", "fullperc_fusion.margin.layout"},
        "fullperc_fusion.pipeline.ordered": {"fullperc_fusion.filters.api", "fullperc_fusion.fusion_config"},
        "fullperc_fusion.fusion_node": {"fullperc_fusion.pipeline.ordered", "fullperc_fusion.fusion_config"},
        "fullperc_fusion.odd.thing": set(),
    }
    found = layering_violations(planted)
    assert len(found) == 8, found
    assert any(v.startswith("fullperc_fusion.odd.thing: not in a layer") for v in found)
    assert any(v.startswith("fullperc_fusion.filters.paper_fast -> fullperc_fusion.margin.layout") for v in found)
    assert any(v.startswith("fullperc_fusion.pipeline.ordered -> fullperc_fusion.fusion_config: "
                            "fullperc_fusion.pipeline must not import fullperc_fusion.(top) "
                            "(top -> pipeline -> calibration | filters | margin)") for v in found)
    assert any(v.startswith("fullperc_fusion.margin.view_margin -> fullperc_drivers") for v in found)
    assert any(v.startswith("fullperc_common.share -> fullperc_eval") for v in found)
    assert any(v.startswith("fullperc_eval.sim.run -> fullperc_eval.graph.demo") for v in found)
    assert any(v.startswith("fullperc_eval.bag.reader -> fullperc_eval.emulators") for v in found)
    assert any(v.startswith("fullperc_eval.stray: not in a layer") for v in found)


def test_packages_and_layers_import_only_downward():
    violations = layering_violations(import_graph())
    assert not violations, "layering violations:\n  " + "\n  ".join(violations)


# ------------------------------------------------------------------------------------- (c) module length
def long_modules(files: list[Path], limit: int = MAX_LINES) -> list[str]:
    out = []
    for f in files:
        n = len(f.read_text(errors="replace").splitlines())
        if n > limit:
            out.append(f"{f.relative_to(ROOT) if f.is_relative_to(ROOT) else f}: {n} lines")
    return out


def test_length_checker_finds_a_planted_long_module(tmp_path):
    ok, long = tmp_path / "ok.py", tmp_path / "long.py"
    ok.write_text("x = 1\n" * MAX_LINES)
    long.write_text("x = 1\n" * (MAX_LINES + 1))
    assert long_modules([ok, long]) == [f"{long}: {MAX_LINES + 1} lines"]


def test_no_source_module_over_600_lines():
    files = [f for f in repo_files() if f.suffix == ".py" and f.relative_to(ROOT).parts[0] in SOURCE_DIRS]
    assert len(files) > 50
    too_long = long_modules(files)
    assert not too_long, f"modules over {MAX_LINES} lines (split them by job):\n  " + "\n  ".join(too_long)


def test_no_fusion_module_over_500_lines():
    files = [f for f in repo_files() if f.suffix == ".py" and f.is_relative_to(ROOT / FUSION_SRC)]
    assert len(files) > 30
    too_long = long_modules(files, FUSION_MAX_LINES)
    assert not too_long, f"fullperc_fusion modules over {FUSION_MAX_LINES} lines (split them by job):\n  " + \
        "\n  ".join(too_long)


def test_fusion_top_level_holds_the_nodes_and_their_cores_only():
    """At most 12 modules directly in fullperc_fusion (the nodes, their pure cores, the configuration); the rest
    lives in the sub-packages of FUSION_LAYERS."""
    top = sorted(f.name for f in (ROOT / FUSION_SRC).glob("*.py") if f.name != "__init__.py")
    assert 0 < len(top) <= 12, top
    assert {d.name for d in (ROOT / FUSION_SRC).iterdir() if (d / "__init__.py").is_file()} == set(FUSION_LAYERS)


# ------------------------------------------------------------------------------------ (d) machine paths
# An absolute path under a root that names a particular machine's layout: a home (/home/<user>, /Users/<user>,
# /root), a work or build directory (/work, /builds, /mnt), temporary directories (/tmp, /private), or /opt
# (vendor installs, CI tool caches). Device paths (/dev/ttyUSB0) are the same on every machine: not checked.
MACHINE_PATH = re.compile(r"(?<![\w.~$/-])(?:/(?:work|home|Users|root|builds|mnt|tmp|private|opt)/[^\s'\"`<>)\]]*"
                          r"|\b[A-Za-z]:\\Users\\[^\s'\"`]*)")
# Legitimate absolute paths: (file glob, regex the whole path must match, why it is not a machine's path).
ALLOWED: tuple[tuple[str, str, str], ...] = (
    ("*", r"/opt/ros/jazzy(/[\w./-]*)?",
     "where ROS 2 Jazzy installs on every Ubuntu machine; scripts/env.sh and setup.sh look for it"),
    ("*", r"/opt/python/[\w./*\"-]*",
     "the include path the PyPI ROS wheels were built with (manylinux container); cmake/ rewrites it"),
    ("README.md", r"/opt/nokov/lib/libnokov_sdk\.so", "an example location of NOKOV's vendor library"),
    ("*", r"/tmp/(report|f\.yaml|run\.npz)", "scratch output paths in example commands (README, sim --help)"),
    ("test/test_code_rules.py", r".*", "this file spells out the patterns it looks for"),
)


def machine_paths(path: str, text: str) -> list[str]:
    """``path:line: found`` for every machine path in ``text`` that no ALLOWED entry of ``path`` covers."""
    out = []
    for i, line in enumerate(text.splitlines(), 1):
        for m in MACHINE_PATH.finditer(line):
            found = m.group(0).rstrip(".,;:")
            if not any(fnmatch.fnmatch(path, glob) and re.fullmatch(rx, found) for glob, rx, _ in ALLOWED):
                out.append(f"{path}:{i}: {found}")
    return out


def test_machine_path_checker_finds_planted_paths():
    home, work = "/" + "home/alice/ws/src", "/" + "work/main/install/fullperc_eval"
    text = (f"see {home}/x.py\nbuilt in {work}\nmac: " + "/" + "Users/bob/x\nwin: C:" + "\\" + "Users" + "\\"
            + "bob\\x\n/opt/ros/jazzy/setup.bash /dev/ttyUSB0 --out /tmp/report src/a/b ../rel/path "
            "~/.cache/fullperc $HOME/x https://example.org/home/x\n")
    found = machine_paths("docs/x.md", text)
    assert [f.split(": ", 1)[1] for f in found] == [f"{home}/x.py", work, "/" + "Users/bob/x",
                                                    "C:" + "\\" + "Users" + "\\" + "bob\\x"], found
    # `make eval` records its config files as package://<pkg>/<file> (evaluate_all.portable_path), never absolute
    assert machine_paths("bags/paper/eval.json", f'"layout": "{work}/../share/fullperc_fusion/config/or_layout.yaml"')
    assert machine_paths("bags/paper/eval.json", '"layout": "package://fullperc_fusion/config/or_layout.yaml"') == []


def test_no_machine_paths_in_tracked_files():
    found = []
    for f in repo_files():
        data = f.read_bytes()
        if b"\0" in data[:8192]:
            continue  # binary (MCAP bags, ROMs)
        found += machine_paths(str(f.relative_to(ROOT)), data.decode("utf-8", errors="replace"))
    assert not found, "absolute paths of a machine (refer to the file relative to the repository, or allow it " \
                      "in ALLOWED with the reason):\n  " + "\n  ".join(found)
