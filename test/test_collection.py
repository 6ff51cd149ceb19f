"""Every package's tests run under ``make test``: a ``src/<pkg>/test`` that pytest does not collect fails here.

Why: ``pyproject.toml``'s ``testpaths`` once listed packages one by one and left ``fullperc_common`` out, so its
tests never ran in CI. This reads pytest's own configuration of this run (``testpaths``, ``python_files``,
``norecursedirs``: what a plain ``pytest`` / ``make test`` collects) and checks every test file against it, without
collecting the suite a second time; when this session is such a plain run, the files it collected are checked too.
"""

from __future__ import annotations

import fnmatch
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _uncollected(config, files: set[str]) -> list[str]:
    """The ``files`` (relative to ROOT) a plain ``pytest`` in ROOT would not collect under ``config``'s settings."""
    testpaths = [ROOT / p for p in config.getini("testpaths")]
    patterns = config.getini("python_files")
    norecurse = config.getini("norecursedirs")
    missing = []
    for f in sorted(files):
        path = ROOT / f
        under = next((tp for tp in testpaths if path.is_relative_to(tp)), None)
        dirs = path.relative_to(under).parts[:-1] if under else ()
        if (under is None or not any(fnmatch.fnmatch(path.name, p) for p in patterns)
                or any(fnmatch.fnmatch(d, p) for d in dirs for p in norecurse)):
            missing.append(f)
    return missing


def test_every_package_test_file_is_collected(request):
    expected = {p.relative_to(ROOT).as_posix() for p in ROOT.glob("src/*/test/test_*.py")}
    expected |= {p.relative_to(ROOT).as_posix() for p in ROOT.glob("test/test_*.py")}
    assert {p.split("/")[1] for p in expected if p.startswith("src/")} >= {
        "fullperc_common", "fullperc_drivers", "fullperc_fusion", "fullperc_eval"}
    missing = _uncollected(request.config, expected)
    assert not missing, f"test files a plain `pytest` does not collect (check testpaths in pyproject.toml):\n{missing}"
    if not request.config.invocation_params.args:     # this session is the plain run: it collected them all
        collected = {Path(str(item.path)).relative_to(ROOT).as_posix() for item in request.session.items}
        assert not sorted(expected - collected), sorted(expected - collected)


def test_the_check_finds_a_package_left_out_of_testpaths(request):
    """The check above can fail: with ``testpaths`` naming only two packages, the others' files are reported."""

    class Narrow:
        def getini(self, name):
            return ["src/fullperc_fusion", "test"] if name == "testpaths" else request.config.getini(name)

    missing = _uncollected(Narrow(), {"src/fullperc_common/test/test_tf.py", "src/fullperc_fusion/test/test_filters.py",
                                      "test/test_collection.py"})
    assert missing == ["src/fullperc_common/test/test_tf.py"]
    assert _uncollected(request.config, {"src/fullperc_common/test/helper_tf.py"}) == [
        "src/fullperc_common/test/helper_tf.py"], "a file not named test_*.py is not collected"
