"""Every package's tests run under ``make test``: a ``src/<pkg>/test`` that pytest does not collect fails here.

Why: ``pyproject.toml``'s ``testpaths`` once listed packages one by one and left ``fullperc_common`` out, so its
tests never ran in CI. This asks pytest itself, with the repository's own configuration and no arguments (what
``make test`` runs), which test files it collects.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_test_file_is_collected():
    expected = {p.relative_to(ROOT).as_posix() for p in ROOT.glob("src/*/test/test_*.py")}
    assert {p.split("/")[1] for p in expected} >= {"fullperc_common", "fullperc_drivers", "fullperc_fusion",
                                                   "fullperc_eval"}
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q"], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    collected = {line.split("::", 1)[0] for line in out.stdout.splitlines() if "::" in line}
    missing = sorted(expected - collected)
    assert not missing, f"test files not collected by a plain `pytest` (check testpaths):\n{missing}\n{out.stderr}"
