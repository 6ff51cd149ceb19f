"""The installed ``evaluate`` executable: good bags give tables, report and JSON; bad input gives a clear error.

Every bad input must end with exit code 1, one ``error: ...`` line naming the problem, and no traceback.

The executable (the console script around ``fullperc_eval.evaluation.cli.main``: its exit code is main's return value,
its stderr main's) runs as a process for the good bag and for a missing bag; the other bad inputs call the same
``main`` in this process (:func:`run_main`: each process start costs about a CPU second of imports). There, "no
traceback" is "main returned": an exception escaping it fails the test, as it would print a traceback in the process.
``evaluate_all`` likewise: a process for the bags, ``main`` in this process for the missing ones.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import subprocess
from collections.abc import Callable

import pytest
import yaml

from fullperc_common.testing import installed_exe
from fullperc_eval.bag.writer import BagWriter
from fullperc_eval.sim.dataset import synthetic_content, write_bag
from fullperc_fusion.pipeline.ordered import FILTER_NAMES

TIMEOUT = 300   # liveness bound for a hung process, not a performance limit


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory):
    content, _ = synthetic_content(3.0)
    return write_bag(tmp_path_factory.mktemp("cli") / "good", content)


@pytest.fixture(scope="module")
def good_run(good_bag, tmp_path_factory):
    """``evaluate`` of the good bag with a report and the JSON (one run: the good-bag test checks it, another test
    compares its JSON with a bag that holds more topics)."""
    out = tmp_path_factory.mktemp("good_run")
    return run(good_bag, "--out", out / "rep", "--json", out / "r.json"), out


def run(*args, env=None):
    return subprocess.run([installed_exe("fullperc_eval", "evaluate"), *map(str, args), "--quiet"],
                          capture_output=True, text=True, timeout=TIMEOUT, env=env)


def run_main(main: Callable[[list[str]], int], *args) -> subprocess.CompletedProcess:
    """``main(args + ['--quiet'])`` in this process, as the executable would run it: (exit code, stdout, stderr)."""
    argv = [*map(str, args), "--quiet"]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return subprocess.CompletedProcess(argv, rc, out.getvalue(), err.getvalue())


def run_in_process(*args) -> subprocess.CompletedProcess:
    """``evaluate ARGS --quiet`` through the executable's ``main`` (cli.main) in this process."""
    from fullperc_eval.evaluation.cli import main

    return run_main(main, *args)


def copy_bag(src, dst):
    shutil.copytree(src, dst)
    return dst


def assert_clean_error(p, *fragments):
    out = p.stdout + p.stderr
    assert p.returncode == 1, out
    assert "Traceback" not in out, out
    err = p.stderr.strip().splitlines()
    assert err and err[-1].startswith("error: "), out
    for f in fragments:
        assert f in p.stderr, out


def test_good_bag_prints_tables_and_writes_report_and_json(good_run):
    p, tmp_path = good_run
    assert p.returncode == 0, p.stdout + p.stderr
    assert "Table 1" in p.stdout and "CBKF" in p.stdout and "Table 2" in p.stdout
    data = json.loads((tmp_path / "r.json").read_text())
    assert set(data["mae_mm"]) == set(FILTER_NAMES)
    assert f"{data['mae_mm']['omc']:6.2f}" in p.stdout
    assert json.loads((tmp_path / "rep" / "eval.json").read_text()) == data
    for f in ("index.html", "trajectory.png", "errors.png"):
        assert (tmp_path / "rep" / f).is_file()


def test_missing_bag(tmp_path):
    assert_clean_error(run(tmp_path / "nope"), "does not exist")


def test_missing_metadata(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / "b")
    (bag / "metadata.yaml").unlink()
    assert_clean_error(run_in_process(bag), "metadata.yaml", "reindex")


def test_garbage_metadata(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / "b")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [1, 2\n")
    assert_clean_error(run_in_process(bag), "not a valid rosbag2 metadata file")


def test_storage_file_that_is_not_mcap(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / "b")
    (f,) = bag.glob("*.mcap")
    f.write_bytes(b"this is not a bag" * 100)
    assert_clean_error(run_in_process(bag), "not an MCAP file")


def test_truncated_mcap(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / "b")
    (f,) = bag.glob("*.mcap")
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    assert_clean_error(run_in_process(bag), "incomplete")


def test_corrupt_chunk_inside_a_complete_mcap(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / "b")
    (f,) = bag.glob("*.mcap")
    data = bytearray(f.read_bytes())
    mid = len(data) // 3
    data[mid:mid + 2000] = bytes(2000)          # zero a stretch of compressed chunk data; magic bytes intact
    f.write_bytes(bytes(data))
    assert_clean_error(run_in_process(bag), "corrupt")


def test_needed_topic_with_an_unknown_type(tmp_path):
    bag = tmp_path / "unknown"
    with BagWriter(bag) as w:
        w.add_topic("/omc/tool/pose", "foo_msgs/msg/Pose", msgdef="float64 x\n", type_hash="")
        w.add_topic("/diana/joint_states", "sensor_msgs/msg/JointState")
        w.write("/omc/tool/pose", 1, b"\x00\x01\x00\x00" + bytes(8))
    (bag / "calibration.yaml").write_text(yaml.safe_dump({"T_base_diana_base": [0, 0, 0, 0, 0, 0, 1],
                                                          "T_flange_tool": [0, 0, 0, 0, 0, 0, 1]}))
    assert_clean_error(run_in_process(bag),
                       "/omc/tool/pose has type foo_msgs/msg/Pose, expected geometry_msgs/msg/PoseStamped")


def test_unknown_types_on_other_topics_are_ignored(good_bag, good_run, tmp_path):
    """A bag with extra topics of types nobody here knows still evaluates (we read only what we need)."""
    bag = copy_bag(good_bag, tmp_path / "extra")
    p, out = good_run   # the good bag's evaluation: the same bag without the extra topic
    ref = json.loads(p.returncode == 0 and (out / "r.json").read_text())
    side = tmp_path / "side"
    with BagWriter(side) as w:
        w.add_topic("/vendor/blob", "vendor_msgs/msg/Blob", msgdef="", type_hash="")
        w.write("/vendor/blob", 1, b"\x00\x01\x00\x00\xff\xff\xff\xff")
    # merge: put the foreign topic's file beside the good one and list it in the metadata
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    (sf,) = side.glob("*.mcap")
    shutil.copy(sf, bag / "extra_1.mcap")
    info = meta["rosbag2_bagfile_information"]
    side_info = yaml.safe_load((side / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    info["relative_file_paths"].append("extra_1.mcap")
    info["files"].append({**side_info["files"][0], "path": "extra_1.mcap"})
    info["topics_with_message_count"] += side_info["topics_with_message_count"]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    p = run_in_process(bag, "--json", tmp_path / "b.json")
    assert p.returncode == 0, p.stdout + p.stderr
    assert json.loads((tmp_path / "b.json").read_text())["mae_mm"] == ref["mae_mm"]


def test_no_joint_states(tmp_path):
    content, _ = synthetic_content(2.0)
    content.diana.t_ns = content.diana.t_ns[:0]
    content.diana.q = content.diana.q[:0]
    content.diana.dq = None
    bag = write_bag(tmp_path / "nojs", content)
    assert_clean_error(run_in_process(bag), "/diana/joint_states", "ground truth")


def test_missing_calibration(good_bag, tmp_path):
    bag = copy_bag(good_bag, tmp_path / "b")
    (bag / "calibration.yaml").unlink()
    assert_clean_error(run_in_process(bag), "calibration", "--calibration")


def test_bad_fusion_config(good_bag, tmp_path):
    cfg = tmp_path / "f.yaml"
    cfg.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {"local_chain": "sideways"}}}))
    assert_clean_error(run_in_process(good_bag, "--fusion-config", cfg), "local_chain")


def test_bad_layout(good_bag, tmp_path):
    lay = tmp_path / "l.yaml"
    lay.write_text("cameras: 3\n")
    assert_clean_error(run_in_process(good_bag, "--layout", lay), "layout")


# --------------------------------------------------------------------------------------------- evaluate_all
def run_all(*args):
    import sys

    return subprocess.run([sys.executable, "-m", "fullperc_eval.evaluation.evaluate_all", *map(str, args), "--quiet"],
                          capture_output=True, text=True, timeout=TIMEOUT)


def test_evaluate_all_writes_the_eval_json_schema(tmp_path):
    bags = tmp_path / "bags"
    for name, off in (("P-G-B", (0.004, 0.0, 0.0)), ("G-B-P", (0.0, 0.002, 0.0))):
        content, _ = synthetic_content(3.0, omc_offset=off)
        content.custom_data["task"] = name
        write_bag(bags / name, content)
    (bags / "not-a-bag").mkdir()
    p = run_all("--bags", bags, "--json", bags / "eval.json")
    assert p.returncode == 0, p.stdout + p.stderr
    data = json.loads((bags / "eval.json").read_text())
    rows = data["tasks"]
    assert [r["task"] for r in rows] == ["G-B-P", "P-G-B"]            # the paper's task order
    for r, off in zip(rows, (2.0, 4.0), strict=True):
        assert set(r["mae_mm"]) == set(FILTER_NAMES)
        assert r["mae_mm"]["omc"] == pytest.approx(off, abs=1e-6)      # the injected offset [mm]
        assert "b_to_p" in r and r["bag"].endswith(r["task"])
    assert data["paper"]["table1_mae_mm"]["G-B-P"]["cbkf"] == 1.63
    lines = p.stdout.splitlines()
    assert any(line.startswith("G-B-P ") for line in lines) and any(line.startswith("P-G-B ") for line in lines)
    assert "CBKF/OMC" in p.stdout and "Comparison with the paper" in p.stdout


def test_evaluate_all_without_bags_is_a_clean_error(tmp_path):
    from fullperc_eval.evaluation.evaluate_all import main

    assert_clean_error(run_main(main, "--bags", tmp_path / "none"), "does not exist")
    (tmp_path / "empty").mkdir()
    assert_clean_error(run_main(main, "--bags", tmp_path / "empty"), "no bags")
