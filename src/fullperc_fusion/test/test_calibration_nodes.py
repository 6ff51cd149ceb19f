"""The calibration step across processes (issue 15 items 1-2): the installed ``calibrate`` executable and
``fusion_node``'s ``calibration_file``, ``~/calibrate`` and link monitoring, fed by synthetic_driver_pub.py."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import installed_exe, load_by_path, side_by_side_fixture, wait_for
from fullperc_common.transforms import inv_T

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
pytestmark = pytest.mark.system


def _load(name: str):
    return load_by_path(HERE / f"{name}.py", f"_calib_{name}")


PUBMOD = _load("synthetic_driver_pub")
T_OTS_BASE = inv_T(PUBMOD.T_OMC_OTS) @ PUBMOD.T_OMC_BASE


def _run_calibrate(procs, python_exe, tmp_path, pub_args, name):
    out = tmp_path / f"{name}.yaml"
    cal = procs.start([installed_exe("fullperc_fusion", "calibrate"), "--ros-args", "-p", "duration:=1.5",
                       "-p", "timeout:=40.0", "-p", f"output:={out}"], name=name)
    pub = procs.start([python_exe, str(PUB), "--log", str(tmp_path / f"{name}.jsonl"), "--static-only",
                       "--link-noise", "--duration", "2.5", *pub_args], name=f"{name}_pub")
    # liveness bounds only: discovery + 1.5 s of data + the estimate
    wait_for(lambda: cal.poll() is not None, 60, what="calibrate to exit")
    wait_for(lambda: pub.poll() is not None, 30, what="publisher to finish")
    return cal, out


def _calibrate_writes_the_links_of_a_still_scene(procs, ros_env, python_exe, tmp_path):
    from fullperc_fusion.calibration.io import load_calibration
    from fullperc_fusion.calibration.se3_stats import se3_residuals

    cal, out = _run_calibrate(procs, python_exe, tmp_path, [], "still")
    log = procs.log(cal)
    assert cal.returncode == 0, log
    assert re.search(rf"\[calibrate\] wrote {re.escape(str(out))}: calibrated over 1\.\d+ s: T_omc_base", log), log
    c = load_calibration(out)
    assert set(c.links) == {"T_omc_base", "T_base_ots", "T_rig_ots"}
    for name, truth, tol_mm in (("T_omc_base", PUBMOD.T_OMC_BASE, 0.1), ("T_base_ots", inv_T(T_OTS_BASE), 1.0),
                                ("T_rig_ots", np.eye(4), 1.0)):   # the synthetic rig is the OTS frame itself
        e = c.links[name]
        d = se3_residuals(truth, e.T[None])[0]
        assert 1e3 * np.linalg.norm(d[:3]) < tol_mm and np.linalg.norm(d[3:]) < 1e-3, (name, d)
        assert e.n_samples >= 80 and e.n_inliers >= 0.9 * e.n_samples and e.cov.shape == (6, 6)
    assert c.duration_s > 1.4 and c.stamp_ns > 0


def _calibrate_refuses_when_a_body_moves(procs, ros_env, python_exe, tmp_path):
    cal, out = _run_calibrate(procs, python_exe, tmp_path, ["--move-base", "0.8:0.005"], "moved")
    log = procs.log(cal)
    assert cal.returncode == 1, log
    lines = [x for x in log.splitlines() if x.startswith("[calibrate]")]
    assert len(lines) == 1, log                                    # the reason on one line
    assert "refused" in lines[0] and "OMC body 'base' moved during the collection" in lines[0], lines[0]
    assert "nothing written" in lines[0]
    assert not out.exists() and not list(tmp_path.glob("moved.yaml.*"))   # no file, no temporary left behind


def _fusion_node_refuses_a_bad_calibration_file(procs, ros_env, tmp_path):
    bad = tmp_path / "cal.yaml"
    bad.write_text("version: 1\nstamp_ns: 0\nduration_s: 1.0\nsource: x\nlinks: {T_omc_base: {position: [0, 0]}}\n")
    p = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p",
                     f"calibration_file:={bad}"], name="bad_cal")
    wait_for(lambda: p.poll() is not None, 30, what="fusion_node to exit")
    log = procs.log(p)
    assert p.returncode == 2, log
    assert "'calibration_file'" in log and str(bad) in log and "links.T_omc_base" in log and "Traceback" not in log


def _write_true_calibration(path):
    """A calibration file with the synthetic scene's true links (noise-free sightings through the Collector)."""
    from fullperc_fusion.calibration.collector import Collector
    from fullperc_fusion.calibration.io import save_calibration

    col = Collector(("T_omc_base", "T_base_ots"), duration_s=1.0)
    for k in range(121):
        t = 10**18 + k * 8_333_333
        col.add("omc", "base", t, PUBMOD.T_OMC_BASE)
        col.add("ots", "base", t, T_OTS_BASE)
    save_calibration(path, col.finish(source="test: the synthetic scene's truth"))


def _call(lis, service, timeout):
    from std_srvs.srv import Trigger

    cli = lis.node.create_client(Trigger, service)
    wait_for(cli.service_is_ready, 30, what=service)
    fut = cli.call_async(Trigger.Request())
    wait_for(fut.done, timeout, what=f"{service} response")
    return fut.result()


def _fusion_node_calibration_file_service_and_a_bumped_vega(procs, rclpy_context, python_exe, tmp_path):
    """fusion_node starts from a calibration file (init_samples is out of reach: only the file can give links),
    re-calibrates on ~/calibrate (writes calibration.output, swaps the links), and when the Vega is pushed 3 mm
    raises a WARN naming T_base_ots and the size, and link_bumped in FusionStatus."""
    from fullperc_common.diagnostics import as_level
    from fullperc_fusion.calibration.io import load_calibration
    from fullperc_fusion.calibration.se3_stats import se3_residuals

    Listener = _load("test_fusion_node").Listener
    cal_in, cal_out = tmp_path / "in.yaml", tmp_path / "out.yaml"
    _write_true_calibration(cal_in)
    topics = ["/fullperc/tool/pose", "/fullperc/tool/status"]
    lis = Listener(rclpy_context, topics)
    try:
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                            "-p", f"calibration_file:={cal_in}", "-p", "init_samples:=100000",
                            "-p", "calibration.duration:=1.0", "-p", f"calibration.output:={cal_out}",
                            "-p", "link_monitor.window:=0.5"], name="fusion_node")
        wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 30, what="node's publishers")
        wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions if p.topic_name in topics),
                 30, what="subscriptions matched")
        pub = procs.start([python_exe, str(PUB), "--log", str(tmp_path / "pub.jsonl"), "--link-noise",
                           "--duration", "6.0", "--bump-ots", "4.0:0.003"], name="pub")
        wait_for(lambda: lis.got["/fullperc/tool/pose"], 30, what="fused poses from the file's links")
        resp = _call(lis, "/fusion_node/calibrate", 30)     # collects 1 s of stamps, well before the bump at 4 s
        assert resp.success, resp.message
        assert "T_omc_base" in resp.message and "T_base_ots" in resp.message and str(cal_out) in resp.message
        bumped = wait_for(lambda: [s for s in lis.got["/fullperc/tool/status"] if s.link_bumped], 30,
                          what="link_bumped in FusionStatus")

        def warn():
            return [st for arr in list(lis.diag) for st in arr.status if st.name == "fusion_node: target tool"
                    and as_level(st.level) == 1 and "T_base_ots bumped" in st.message]
        warns = wait_for(warn, 30, what="WARN on /diagnostics")
        wait_for(lambda: pub.poll() is not None, 60, what="publisher to finish")
        assert pub.returncode == 0, procs.log(pub)
        assert node.poll() is None, procs.log(node)
    finally:
        lis.close()
    out = load_calibration(cal_out)
    assert set(out.links) == {"T_omc_base", "T_base_ots"} and "~/calibrate" in out.source
    d = se3_residuals(PUBMOD.T_OMC_BASE, out.T("T_omc_base")[None])[0]
    assert 1e3 * np.linalg.norm(d[:3]) < 0.2
    values = {kv.key: kv.value for arr in list(lis.diag) for st in arr.status if st.name == "fusion_node: target tool"
              for kv in st.values}
    assert "~/calibrate" in values["links_source"]
    # the flag comes after the bump, not before; the message names the link and gives the size (3 mm)
    start = PUBMOD.read_log(tmp_path / "pub.jsonl")[1]
    first = min((s.header.stamp.sec * 10**9 + s.header.stamp.nanosec - start) / 1e9 for s in bumped)
    assert first > 4.0
    before = [s for s in lis.got["/fullperc/tool/status"]
              if (s.header.stamp.sec * 10**9 + s.header.stamp.nanosec - start) / 1e9 < 3.9]
    assert before and not any(s.link_bumped for s in before)
    size = float(re.search(r"is ([0-9.]+) mm", warns[0].message).group(1))
    assert abs(size - 3.0) < 0.5, warns[0].message


def _calibrate_help_documents_the_parameters_and_the_exit_status(procs, ros_env):
    p = procs.start([installed_exe("fullperc_fusion", "calibrate"), "--help"], name="help")
    wait_for(lambda: p.poll() is not None, 30, what="calibrate --help")
    text = procs.log(p)
    assert p.returncode == 0, text
    for word in ("Exit status", "refused", "duration:", "output:", "links:", "omc_base_body:", "[s]"):
        assert word in text, word


scenarios = side_by_side_fixture(
    _calibrate_writes_the_links_of_a_still_scene,
    _calibrate_refuses_when_a_body_moves,
    _fusion_node_refuses_a_bad_calibration_file,
    _fusion_node_calibration_file_service_and_a_bumped_vega,
    _calibrate_help_documents_the_parameters_and_the_exit_status)


def test_calibrate_writes_the_links_of_a_still_scene(scenarios, request):
    scenarios.result(request.node.name)


def test_calibrate_refuses_when_a_body_moves(scenarios, request):
    scenarios.result(request.node.name)


def test_fusion_node_refuses_a_bad_calibration_file(scenarios, request):
    scenarios.result(request.node.name)


def test_fusion_node_calibration_file_service_and_a_bumped_vega(scenarios, request):
    scenarios.result(request.node.name)


def test_calibrate_help_documents_the_parameters_and_the_exit_status(scenarios, request):
    scenarios.result(request.node.name)


def test_calibrate_reads_its_sightings_under_the_nodes_namespace(rclpy_context):
    """Relative input names, as fusion_node's: started with ``-r __ns:=/or1`` (here in-process, the same remapping
    rule) calibrate reads /or1/omc/... and /or1/ots/..., so a calibration of one OR never takes another's poses."""
    from fullperc_fusion.calibrate import CalibrateNode

    ns = CalibrateNode(context=rclpy_context, cli_args=["--ros-args", "-r", "__ns:=/or1"])
    plain = CalibrateNode(context=rclpy_context)
    try:
        got = sorted(s.topic_name for s in ns.subscriptions)
        assert got and all(t.startswith("/or1/omc/") or t.startswith("/or1/ots/") for t in got), got
        assert sorted(s.topic_name for s in plain.subscriptions) == [t[len("/or1"):] for t in got]
    finally:
        ns.destroy_node()
        plain.destroy_node()
