"""Every driver parameter file in config/ is accepted by its node: each name is declared, each type matches, and each
value is the node's built-in default unless the file says why not.

A file a user copies is the parameter reference (``<exe> --help`` prints it), so a name the node no longer declares
(rclpy ignores it without a word), a value of the wrong type (exit 2 at start), or a value that silently differs from
the default (ndi_vega.yaml once set ``tool_priorities`` against a default of all D, beside a latency comment that
read like a measured setting) all mislead. The node is built in this process from the file, as ``run_node`` builds
it, with rclpy's ``declare_parameter`` recorded: the declarations give the names and the defaults, the built node
the values. Only the device addresses are moved to free ports / a missing serial device, so that nothing is bound
or opened that another test uses. ``test_omc_driver`` and ``test_diana_state`` also start the installed files in a
process; ``test_qos_depth`` and ``test_ros_naming`` check single fields of them.
"""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any

import pytest
import yaml

from fullperc_common.ports import free_port

CONFIG = Path(__file__).resolve().parents[1] / "config"

# Per file: the parameters deliberately not at the node's default; the file's comment on each says why.
DELIBERATE = {
    "ndi_vega.yaml": {"tool_priorities"},
    "ndi_spectra.yaml": {"transport", "mode", "tool_priorities"},
    "omc.yaml": set(),
    "diana.yaml": set(),
}
RCLPY_OWN = {"use_sim_time", "start_type_description_service"}   # every rclpy node declares these itself
NODE = {"ndi_vega.yaml": "ndi_driver", "ndi_spectra.yaml": "ndi_driver", "omc.yaml": "omc_driver",
        "diana.yaml": "diana_state"}


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _same(a: Any, b: Any) -> bool:
    """Equal values; a list parameter may come back from rclpy as another sequence type."""
    return list(a) == list(b) if isinstance(b, list) else a == b


def _file_params(name: str) -> dict[str, Any]:
    doc = yaml.safe_load((CONFIG / name).read_text())
    (key, body), = doc.items()
    assert key.split("/")[-1] == NODE[name], f"{name}: section {key!r} does not name {NODE[name]}"
    return _flatten(body["ros__parameters"])


def _build(name: str, tmp_path: Path, monkeypatch) -> tuple[dict[str, Any], dict[str, Any]]:
    """(declared name -> default, declared name -> value) of the node built from config/``name``."""
    import rclpy
    from rclpy.node import Node

    from fullperc_drivers import diana_state, ndi_driver, omc_driver

    cls = {"ndi_driver": ndi_driver.NdiDriverNode, "omc_driver": omc_driver.OmcDriverNode,
           "diana_state": diana_state.DianaStateNode}[NODE[name]]
    moved = {"ndi_driver": [f"port:={free_port(socket.SOCK_STREAM)}", f"serial_device:={tmp_path / 'no_tty'}"],
             "omc_driver": [f"stream_port:={free_port(socket.SOCK_DGRAM)}"],
             "diana_state": [f"stream_port:={free_port(socket.SOCK_DGRAM)}"]}[NODE[name]]
    defaults: dict[str, Any] = {}
    original = Node.declare_parameter

    def recording(self, pname, value=None, *args, **kwargs):
        if pname not in RCLPY_OWN:
            defaults[pname] = value
        return original(self, pname, value, *args, **kwargs)

    monkeypatch.setattr(Node, "declare_parameter", recording)
    rclpy.init(args=["--ros-args", "--params-file", str(CONFIG / name), *(a for m in moved for a in ("-p", m))])
    try:
        node = cls()
        try:
            values = {n: node.get_parameter(n).value for n in defaults}
        finally:
            node.close()
            node.destroy_node()
    finally:
        rclpy.shutdown()
    return defaults, values


@pytest.mark.parametrize("name", sorted(DELIBERATE))
def test_every_driver_file_is_accepted_by_its_node(name, ros_env, tmp_path, monkeypatch):
    assert sorted(p.name for p in CONFIG.glob("*.yaml") if p.name != "ndi_emulator_example.yaml") \
        == sorted(DELIBERATE), "a new driver parameter file: add it here"
    given = _file_params(name)
    defaults, values = _build(name, tmp_path, monkeypatch)
    assert not (unknown := sorted(set(given) - set(defaults))), f"{name}: not parameters of {NODE[name]}: {unknown}"
    assert not (undocumented := sorted(set(defaults) - set(given))), \
        f"{name}: parameters of {NODE[name]} the file does not list: {undocumented}"
    for k, v in given.items():
        d = defaults[k]
        assert type(v) is type(d) and (not isinstance(v, list) or {type(x) for x in v} <= {type(x) for x in d}), \
            f"{name}: {k} = {v!r} is a {type(v).__name__}, the node declares a {type(d).__name__} ({d!r})"
        if k not in ("port", "serial_device", "stream_port"):       # moved above
            assert _same(values[k], v), f"{name}: {k}: the node got {values[k]!r}, not {v!r}"
    differ = {k for k, v in given.items() if not _same(v, defaults[k])}
    assert differ == DELIBERATE[name], f"{name}: differs from the node's defaults in {sorted(differ)}"
    text = (CONFIG / name).read_text()
    lines = text.splitlines()
    for k in DELIBERATE[name]:
        i = next(i for i, ln in enumerate(lines) if ln.strip().startswith(f"{k.split('.')[-1]}:"))
        comment = [lines[i], *_takewhile_comments(lines[i + 1:])]
        assert "default" in " ".join(comment), \
            f"{name}: {k} differs from the node's default; its comment must say why: {comment!r}"


def _takewhile_comments(lines: list[str]) -> list[str]:
    """The comment-only lines that continue a parameter's trailing comment."""
    out = []
    for ln in lines:
        if not ln.strip().startswith("#"):
            break
        out.append(ln)
    return out
