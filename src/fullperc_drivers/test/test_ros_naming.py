"""The drivers' ROS conventions, from their source: relative topic names and read-only parameters.

A real process under ``-r __ns:=/or1`` and the parameter services are checked in test/test_node_lifecycle.py
(``test_namespace_and_read_only_parameters``); these pin the rules where a new line of code could break them:
no absolute topic name in a driver (only the global ``/tf`` and ``/diagnostics`` of fullperc_common's helpers),
every driver parameter declared through ``declare_fixed`` (read-only: a driver reads its parameters once, at start).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from fullperc_drivers.ndi_driver import prefix_topic, tool_topic

PKG = Path(__file__).resolve().parents[1] / "fullperc_drivers"
NODES = ["omc_driver.py", "ndi_driver.py", "diana_state.py", "node_common.py"]
# the name argument of create_publisher / create_subscription / create_service / create_client when it is a literal
NAME_ARG = re.compile(r"create_(?:publisher|subscription|service|client)\(\s*\w+,\s*(f?\"[^\"]*\")")


@pytest.mark.parametrize("module", NODES)
def test_topic_names_are_relative(module):
    names = NAME_ARG.findall((PKG / module).read_text())
    assert all(not n.lstrip("f").startswith('"/') for n in names), names


def test_every_node_makes_its_topics_with_a_literal_or_tool_topic():
    """The scan above sees each node's topics (a name built elsewhere would escape it)."""
    found = {m: NAME_ARG.findall((PKG / m).read_text()) for m in NODES[:3]}
    assert found["omc_driver.py"] == ['"omc/bodies"', 'f"omc/{tok}/pose"', 'f"omc/{tok}/quality"']
    assert found["diana_state.py"] == ['"diana/joint_states"', '"diana/flange_pose"', '"diana/tool_pose"']
    assert found["ndi_driver.py"] == []   # tool_topic(prefix, ...) and prefix_topic(prefix, ...), tested below
    assert "tool_topic(prefix, n, \"pose\")" in (PKG / "ndi_driver.py").read_text()
    assert "prefix_topic(prefix, \"bodies\")" in (PKG / "ndi_driver.py").read_text()


@pytest.mark.parametrize("module", NODES)
def test_every_parameter_is_read_only(module):
    text = (PKG / module).read_text()
    assert not re.search(r"\bdeclare\(|declare_parameter\(", text)
    assert re.search(r"\bdeclare_fixed\(", text)


@pytest.mark.parametrize("prefix, topic", [
    ("ots", "ots/tool/pose"),            # the default: /ots/tool/pose in the default namespace, /or1/ots/... in /or1
    ("ots/", "ots/tool/pose"),
    ("/ots", "/ots/tool/pose"),          # an absolute prefix stays absolute (the user asked for it)
    ("", "tool/pose"),                   # empty: relative, not "/tool/pose"
    ("/", "/tool/pose"),
    ("or/vega", "or/vega/tool/pose"),
])
def test_ndi_tool_topic(prefix, topic):
    assert tool_topic(prefix, "tool", "pose") == topic
    assert prefix_topic(prefix, "bodies") == topic.replace("tool/pose", "bodies")   # the frame's TrackedBodies


@pytest.mark.parametrize("config", ["omc.yaml", "diana.yaml", "ndi_vega.yaml", "ndi_spectra.yaml"])
def test_shipped_files_name_relative_topics(config):
    text = (PKG.parent / "config" / config).read_text()
    assert not re.search(r"^\s*topic_prefix:\s*/", text, re.M)
