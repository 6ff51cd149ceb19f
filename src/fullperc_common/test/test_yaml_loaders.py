"""libyaml reads every YAML file of the repository as PyYAML's pure-Python loaders do (issue 38 item 5).

:func:`fullperc_common.yaml_file.load_yaml_file` parses through libyaml where PyYAML has it (the layout, calibration,
noise-model and params files of every offline evaluation); the same safe constructor and resolvers are meant to give
the same Python objects. Pinned here on the repository's own files (configs, calibrations, bag metadata) with both
loaders the callers ask for, and on the numbers the ROS params loader reads differently from YAML 1.1.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from fullperc_common import yaml_file

ROOT = Path(__file__).resolve().parents[3]


def _yaml_files() -> list[Path]:
    skip = {".venv", "build", "install", "log", ".git", "node_modules"}
    return sorted(p for p in ROOT.rglob("*.yaml") if not skip & set(p.relative_to(ROOT).parts))


def test_libyaml_is_used_when_pyyaml_has_it():
    if not hasattr(yaml, "CSafeLoader"):
        pytest.skip("PyYAML built without libyaml")   # the pure-Python loaders are used then: nothing to compare
    assert yaml_file._FAST[yaml.SafeLoader] is yaml.CSafeLoader
    assert issubclass(yaml_file._FAST[yaml_file.RosParamsLoader], yaml.CSafeLoader)


@pytest.mark.parametrize("loader", [yaml.SafeLoader, yaml_file.RosParamsLoader])
def test_repository_yaml_reads_the_same_through_libyaml(loader):
    files = _yaml_files()
    assert len(files) > 10
    fast = yaml_file._FAST.get(loader, loader)
    for f in files:
        text = f.read_text()
        try:
            want: object = yaml.load(text, Loader=loader)
        except yaml.YAMLError as e:
            want = type(e)
        try:
            got: object = yaml.load(text, Loader=fast)
        except yaml.YAMLError as e:
            got = type(e)
        assert repr(got) == repr(want), f


def test_ros_params_numbers_through_libyaml(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("a: 1e-3\nb: '1e-3'\nc: 1.5e3\nd: -2E+2\ne: 1.0\nf: .nan\ng: 0x1f\n")
    want = yaml.load(f.read_text(), Loader=yaml_file.RosParamsLoader)
    got = yaml_file.load_yaml_file(f, "params file", ValueError, yaml_file.RosParamsLoader)
    assert repr(got) == repr(want)
    assert got["a"] == 0.001 and got["b"] == "1e-3" and got["d"] == -200.0
    assert yaml_file.load_yaml_file(f, "plain file", ValueError)["a"] == "1e-3"   # YAML 1.1: a string
