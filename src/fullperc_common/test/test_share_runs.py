"""share_path finds a package's shipped data (installed or source tree); runs() encodes label runs."""

from pathlib import Path

import numpy as np
import pytest

from fullperc_common.runs import runs
from fullperc_common.share import share_candidates, share_path


def test_share_path_finds_a_shipped_file():
    p = share_path("fullperc_fusion", "config", "or_layout.yaml")
    assert p.is_file() and p.name == "or_layout.yaml"


def test_share_path_names_every_place_it_looked():
    with pytest.raises(FileNotFoundError) as e:
        share_path("fullperc_fusion", "config", "no_such_file.yaml")
    for cand in share_candidates("fullperc_fusion", "config", "no_such_file.yaml"):
        assert str(cand) in str(e.value)


def test_source_tree_is_always_a_candidate():
    src = Path(__file__).resolve().parents[2]
    assert src / "fullperc_drivers" / "config" / "emulator_roms" / "tool.rom" in share_candidates(
        "fullperc_drivers", "config", "emulator_roms", "tool.rom")


def test_runs_inclusive_ends():
    assert runs([1, 1, 2, 3, 3, 3]) == [(1, 0, 1), (2, 2, 2), (3, 3, 5)]
    assert runs(np.array([7])) == [(7, 0, 0)]
    assert runs([]) == []


def test_load_yaml_file_names_the_file_as_the_callers_error(tmp_path):
    from fullperc_common.yaml_file import load_yaml_file

    class MyError(ValueError):
        pass

    good = tmp_path / "a.yaml"
    good.write_text("a: [1, 2]\n")
    assert load_yaml_file(good, "thing file", MyError) == {"a": [1, 2]}
    bad = tmp_path / "b.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(MyError, match=f"thing file {bad}: not valid YAML"):
        load_yaml_file(bad, "thing file", MyError)
    with pytest.raises(MyError, match="thing file .*missing.yaml: cannot read"):
        load_yaml_file(tmp_path / "missing.yaml", "thing file", MyError)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00")     # not UTF-8: the caller's error too, not a UnicodeDecodeError
    with pytest.raises(MyError, match="thing file .*binary.yaml: cannot read"):
        load_yaml_file(binary, "thing file", MyError)
