"""The run policy of conftest.py: in CI a skip fails unless it is on ALLOWED_SKIPS, the list is printed, figures
reported with ``record_property`` are printed, and modules run heaviest first (test/durations.json).

Each case runs pytest in a child process on a small test file outside the repository, with this repository's
conftest.py loaded as a plugin."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import pytest

def test_skips():
    pytest.skip("no reason anyone listed")

def test_reports(record_property):
    record_property("demo", "tool: node lost 0 of 10 input samples")
"""


def _pytest(tmp_path: Path, ci: bool, *args: str) -> subprocess.CompletedProcess:
    (tmp_path / "test_probe.py").write_text(textwrap.dedent(PROBE))
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    env.pop("CI", None)
    if ci:
        env["CI"] = "true"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
                           "-p", "conftest", "--rootdir", str(tmp_path), *args, str(tmp_path / "test_probe.py")],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


def test_in_ci_an_unlisted_skip_fails_and_the_list_is_printed(tmp_path):
    r = _pytest(tmp_path, ci=True)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "1 failed, 1 passed" in r.stdout and "not on conftest.ALLOWED_SKIPS" in r.stdout, r.stdout
    assert "CI: allowed skips" in r.stdout and "gcc not installed" in r.stdout, r.stdout
    assert "demo: tool: node lost 0 of 10 input samples" in r.stdout, "the figure is printed"


def test_outside_ci_a_skip_is_a_skip(tmp_path):
    r = _pytest(tmp_path, ci=False)
    assert r.returncode == 0 and "1 passed, 1 skipped" in r.stdout, r.stdout + r.stderr
    assert "CI: allowed skips" not in r.stdout


def test_the_allowed_skips_match_what_they_name():
    import conftest

    assert conftest._allowed("src/fullperc_drivers/test/test_nokov_sdk.py::test_x",
                             "gcc not installed: cannot build the C test double") is not None
    assert conftest._allowed("src/fullperc_drivers/test/test_nokov_sdk.py::test_x", "some other reason") is None
    assert conftest._allowed("test/test_demo_graph.py::test_x", "gcc not installed") is None


def test_the_heaviest_modules_run_first(tmp_path):
    """``--write-durations`` records each module's seconds, and the collection puts modules in descending order of
    the recorded figures (so the two xdist workers do not end on one long module)."""
    import conftest

    class Item:
        def __init__(self, nodeid):
            self.nodeid = nodeid

    items = [Item(n) for n in ("a.py::t1", "b.py::t1", "a.py::t2", "c.py::t1", "b.py::t2")]
    old = conftest.DURATIONS_FILE
    try:
        conftest.DURATIONS_FILE = tmp_path / "durations.json"
        conftest.DURATIONS_FILE.write_text(json.dumps({"a.py": 1.0, "b.py": 30.0}))
        conftest.pytest_collection_modifyitems(None, None, items)
    finally:
        conftest.DURATIONS_FILE = old
    # b (30 s) first, then c (unknown: DEFAULT_MODULE_S = 5 s), then a (1 s); order inside a module kept
    assert [i.nodeid for i in items] == ["b.py::t1", "b.py::t2", "c.py::t1", "a.py::t1", "a.py::t2"]
    recorded = json.loads((ROOT / "test" / "durations.json").read_text())
    assert "test/test_demo_graph.py" in recorded and all(v >= 0 for v in recorded.values())
