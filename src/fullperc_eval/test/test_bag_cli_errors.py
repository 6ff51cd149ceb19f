"""The installed ``play`` and ``record`` on bad input: a clear error on stderr, a non-zero exit, no traceback, nothing
left behind (issue 8). Split from test_bag_record_play.py (the multi-process record/play tests), whose generated
bag (``_small_bag``) these use.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from fullperc_common.testing import installed_exe

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_bag_record_play import _small_bag  # noqa: E402


def _run_exe(exe: str, *args: str, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([installed_exe("fullperc_eval", exe), *args], capture_output=True, text=True,
                          timeout=60, env=env)


def _assert_clean_error(p: subprocess.CompletedProcess, *needles: str) -> None:
    assert p.returncode != 0
    assert "Traceback" not in p.stderr + p.stdout, p.stderr
    for n in needles:
        assert n in p.stderr, p.stderr


def test_play_missing_bag(tmp_path, ros_env):
    _assert_clean_error(_run_exe("play", str(tmp_path / "nope"), env=ros_env), "error:", "does not exist")


def test_play_missing_metadata(tmp_path, ros_env):
    bag = _small_bag(tmp_path / "gen")
    (bag / "metadata.yaml").unlink()
    _assert_clean_error(_run_exe("play", str(bag), env=ros_env), "no metadata.yaml", "reindex")


def test_play_corrupt_storage_file(tmp_path, ros_env):
    bag = _small_bag(tmp_path / "gen")
    (bag / "gen_0.mcap").write_bytes(b"this is not an mcap file" * 10)
    _assert_clean_error(_run_exe("play", str(bag), env=ros_env), "error:", "gen_0.mcap")


def test_play_corrupt_chunk(tmp_path, ros_env):
    """Damage inside the data section (valid head and footer): still a clear error."""
    bag = _small_bag(tmp_path / "gen")
    f = bag / "gen_0.mcap"
    raw = bytearray(f.read_bytes())
    mid = len(raw) // 3
    raw[mid:mid + 64] = b"\xff" * 64
    f.write_bytes(bytes(raw))
    _assert_clean_error(_run_exe("play", str(bag), env=ros_env), "error:")


def test_play_corrupt_metadata(tmp_path, ros_env):
    bag = _small_bag(tmp_path / "gen")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    _assert_clean_error(_run_exe("play", str(bag), env=ros_env), "not a valid rosbag2 metadata file")


def test_play_unknown_message_type(tmp_path, ros_env):
    from fullperc_eval.bag.writer import BagWriter

    bag = tmp_path / "unknown"
    with BagWriter(bag) as w:
        w.add_topic("/x", "nonexistent_msgs/msg/Thing", msgdef="int32 a\n", type_hash="")
        w.write("/x", 1_000, b"\x00\x01\x00\x00\x07\x00\x00\x00")
    _assert_clean_error(_run_exe("play", str(bag), env=ros_env), "nonexistent_msgs/msg/Thing", "/x")


def test_record_refuses_existing_output_and_bad_args(tmp_path, ros_env):
    (tmp_path / "exists").mkdir()
    _assert_clean_error(_run_exe("record", "-o", str(tmp_path / "exists"), "--all", env=ros_env), "already exists")
    p = _run_exe("record", "-o", str(tmp_path / "x"), env=ros_env)  # nothing selected
    _assert_clean_error(p, "--topics")
    assert not (tmp_path / "x").exists()
    bad = tmp_path / "qos.yaml"
    bad.write_text("/a: {reliability: sometimes}\n")
    p = _run_exe("record", "-o", str(tmp_path / "y"), "--all", "--qos-profile-overrides-path", str(bad), env=ros_env)
    _assert_clean_error(p, "reliability")
    assert not (tmp_path / "y").exists()
