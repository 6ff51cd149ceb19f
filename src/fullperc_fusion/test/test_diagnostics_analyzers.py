"""config/diagnostics_analyzers.yaml: diagnostic_aggregator's format, and every status our nodes publish lands in
exactly one analyzer (the matching rule of its GenericAnalyzer: ``startswith``), none in "Other"."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

SRC = Path(__file__).resolve().parents[2]
CONFIG = SRC / "fullperc_fusion" / "config" / "diagnostics_analyzers.yaml"
GENERIC, GROUP = "diagnostic_aggregator/GenericAnalyzer", "diagnostic_aggregator/AnalyzerGroup"
# the node sources and the components each publishes (Diagnostics: "<node name>: <component>")
NODES = {"fullperc_drivers/fullperc_drivers/omc_driver.py": ["omc"],
         "fullperc_drivers/fullperc_drivers/ndi_driver.py": ["link"],
         "fullperc_drivers/fullperc_drivers/diana_state.py": ["diana"],
         "fullperc_fusion/fullperc_fusion/fusion_node.py": ["target tool"],
         "fullperc_fusion/fullperc_fusion/margin_node.py": ["layout", "target tool", "base pose"]}


def _generic(tree: dict, path: str = "") -> dict[str, dict]:
    """Every GenericAnalyzer under ``tree`` by its aggregated path; asserts the format on the way."""
    out = {}
    for key, a in tree.items():
        if not isinstance(a, dict):
            continue
        assert a.get("type") in (GENERIC, GROUP) and a.get("path"), key
        here = f"{path}/{a['path']}"
        if a["type"] == GROUP:
            out.update(_generic(a["analyzers"], here))
        else:
            assert a.get("startswith") and a.get("timeout", 0) > 0, key
            out[here] = a
    return out


def test_every_status_of_our_nodes_is_in_exactly_one_analyzer():
    doc = yaml.safe_load(CONFIG.read_text())
    params = doc["analyzers"]["ros__parameters"]
    analyzers = _generic(params, params["path"])
    assert len(analyzers) == 5
    for src, components in NODES.items():
        node = re.search(r'super\(\).__init__\("(\w+)"', (SRC / src).read_text())[1]
        for c in components:
            name = f"{node}: {c}"
            hits = [p for p, a in analyzers.items() if any(name.startswith(s) for s in a["startswith"])]
            assert len(hits) == 1, (name, hits)


def test_the_components_named_here_are_the_nodes():
    """The component names above are those the node modules pass to their diagnostics (no stale list)."""
    assert 'HealthReport(self.diag, "omc"' in (SRC / "fullperc_drivers/fullperc_drivers/omc_driver.py").read_text()
    assert 'HealthReport(self.diag, "link"' in (SRC / "fullperc_drivers/fullperc_drivers/ndi_driver.py").read_text()
    assert 'HealthReport(self.diag, "diana"' in (SRC / "fullperc_drivers/fullperc_drivers/diana_state.py").read_text()
