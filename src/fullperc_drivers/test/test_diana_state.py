"""``diana_state`` across processes: the installed executable against a joint-state sender in another process,
and on the ``diana_api`` backend with the compiled C double.

The sender (this file run as a script) uses ``streams.encode_diana`` with a device clock offset from the host
clock, a sequence gap, samples with NaN and with the wrong joint count, and garbage datagrams, writes the
truth (sequence -> sample time on the host clock) and stops. Flange/tool poses are checked against a plain
numpy modified-DH product written in test_diana_kinematics.py (not the pinocchio model under test).
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.testing import side_by_side_fixture

sys.path.insert(0, str(Path(__file__).parent))
from test_diana_api import C_DIR, compile_double  # noqa: E402  (here, not in a scenario thread: test_stream_health)
from test_diana_kinematics import _DOC_TABLE, _mdh_product  # noqa: E402
from test_omc_driver import Listener as _OmcListener  # noqa: E402  (same spin helpers)
from test_omc_driver import free_udp_port  # noqa: E402

FIRST_SEQ, GAP_AT, GAP = 10, 120, 2
NAN_AT, SIX_AT = (40, 41), (70,)
DEVICE_OFFSET_NS = 123_456_789_012
TOOL = [0.01, 0.02, 0.15, *Rotation.from_euler("xyz", [0.1, 0.0, -0.3]).as_quat()]


def seq_of(k: int) -> int:
    return FIRST_SEQ + k + (GAP if k >= GAP_AT else 0)


def q_of(k: int) -> np.ndarray:
    return np.array([0.3 * math.sin(k / 50 + j) + 0.1 * j for j in range(7)]) + np.array([0, 0, 0, 1.0, 0, 0, 0])


def run_sender(port: int, samples: int, rate: float, truth: Path) -> None:
    from fullperc_drivers.streams import DianaState, encode_diana

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    lines, bad = [], 0
    t0 = time.monotonic()
    for k in range(samples):
        time.sleep(max(0.0, t0 + (k + 1) / rate - time.monotonic()))
        q, dq = q_of(k), np.full(7, 0.01 * k)
        if k in NAN_AT:
            q = q.copy()
            q[2] = np.nan
        if k in SIX_AT:
            q, dq = q[:6], dq[:6]
        t = time.time_ns()
        sock.sendto(encode_diana(DianaState(seq_of(k), t + DEVICE_OFFSET_NS, q, dq)), ("127.0.0.1", port))
        lines.append(f"{seq_of(k)} {t}\n")
        if k % 30 == 29:
            sock.sendto([b"FPDA\x01", os.urandom(40), b"FPDA" + b"\x07\x00" + bytes(200)][(k // 30) % 3],
                        ("127.0.0.1", port))
            bad += 1
    truth.write_text("".join(lines) + f"bad {bad}\n")


class Listener(_OmcListener):
    def __init__(self, ctx):  # noqa: D107 - different topics than the OMC listener
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState

        self.node = Node("diana_test_listener", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        self.js, self.flange, self.tool, self.diag = [], [], [], []
        self.node.create_subscription(JointState, "/diana/joint_states", self.js.append, qos)
        self.node.create_subscription(PoseStamped, "/diana/flange_pose", self.flange.append, qos)
        self.node.create_subscription(PoseStamped, "/diana/tool_pose", self.tool.append, qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 100)


def _ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _T(pose) -> np.ndarray:
    T = np.eye(4)
    o = pose.orientation
    T[:3, :3] = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix()
    T[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return T


def _stream_backend_across_processes(procs, rclpy_context, tmp_path, python_exe):
    from fullperc_common.testing import installed_exe, wait_for

    port = free_udp_port()
    n, rate = 200, 100.0
    node = procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", "-p", "backend:=stream",
                        "-p", f"stream_port:={port}", "-p", "publish_tool:=true",
                        "-p", f"tool_offset:=[{', '.join(repr(float(v)) for v in TOOL)}]",
                        "-p", "qos_depth:=1000", "-p", "stale_timeout_s:=0.5", "-p", "diagnostics_period_s:=0.2"])
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: (lis.spin(), all(lis.node.count_publishers(t) >= 1 for t in
                                          ("/diana/joint_states", "/diana/flange_pose", "/diana/tool_pose")))[1],
                 timeout=30, what="diana_state topics")
        # discovery is two-sided: this listener's subscriptions matched (a condition), then a moment for the driver's
        # publishers to match it as well (diana_state does not say when: no SubscriberLog)
        wait_for(lambda: (lis.spin(), all(s.get_publisher_count() >= 1 for s in lis.node.subscriptions
                                          if s.topic_name.startswith("/diana/")))[1], timeout=30,
                 what="listener matched")
        lis.spin(0.5)
        truth_file = tmp_path / "truth.txt"
        sender = procs.start([python_exe, __file__, "--port", str(port), "--samples", str(n), "--rate", str(rate),
                              "--truth", str(truth_file)], name="sender")
        wait_for(lambda: (lis.spin(), sender.poll() is not None)[1], timeout=60, what="sender to finish")
        assert sender.returncode == 0, procs.log(sender)
        def stopped():
            lis.spin()
            st, _ = lis.last_status("diana")
            return st is not None and "stream stopped" in st.message
        wait_for(stopped, timeout=20, what="'stream stopped' diagnosis")
        # the three topics' last messages can still be in flight when the diagnosis arrives (a loaded run: one
        # flange pose short): wait, spinning, until the counts agree -- a liveness bound, the equality asserted below
        wait_for(lambda: (lis.spin(), len(lis.js) == len(lis.flange) == len(lis.tool))[1], timeout=20,
                 what="the last joint state, flange and tool pose", detail=lambda: (len(lis.js), len(lis.flange),
                                                                                   len(lis.tool)))
        assert node.poll() is None, procs.log(node)
    finally:
        lis.close()
    lines = truth_file.read_text().split("\n")
    truth = {int(a): int(b) for a, b in (ln.split() for ln in lines if ln and not ln.startswith("bad"))}
    n_bad = int(next(ln for ln in lines if ln.startswith("bad")).split()[1])
    _, values = lis.last_status("diana")
    assert int(values["decode_errors"]) == n_bad > 0
    assert int(values["invalid"]) == len(NAN_AT) + len(SIX_AT)
    assert int(values["dropped"]) == GAP + len(NAN_AT) + len(SIX_AT)  # rejected samples leave sequence gaps
    good = [k for k in range(n) if k not in NAN_AT and k not in SIX_AT]
    assert len(lis.js) == len(lis.flange) == len(lis.tool) == len(good)

    errors = []
    flange_by_stamp = {_ns(m): m for m in lis.flange}
    tool_by_stamp = {_ns(m): m for m in lis.tool}
    for js in lis.js:
        assert list(js.name) == [f"joint{i}" for i in range(1, 8)] and js.header.frame_id == "diana_base"
        assert all(math.isfinite(v) for v in js.position)
        # Identify the sample by its joint values (the stamp is what is under test).
        k = next(k for k in good if np.allclose(js.position, q_of(k), atol=0, rtol=0))
        np.testing.assert_allclose(js.velocity, np.full(7, 0.01 * k))
        if k >= 30:
            errors.append(_ns(js) - truth[seq_of(k)])
        T_ref = _mdh_product(q_of(k), _DOC_TABLE)
        f = flange_by_stamp[_ns(js)]
        assert f.header.frame_id == "diana_base"
        np.testing.assert_allclose(_T(f.pose), T_ref, atol=1e-9)
        T_tool = np.eye(4)
        T_tool[:3, :3] = Rotation.from_quat(TOOL[3:]).as_matrix()
        T_tool[:3, 3] = TOOL[:3]
        np.testing.assert_allclose(_T(tool_by_stamp[_ns(js)].pose), T_ref @ T_tool, atol=1e-9)
    errors = np.array(errors)
    print(f"\nDiana stamp error vs truth [us]: median {np.median(errors) / 1e3:.1f}, "
          f"min {errors.min() / 1e3:.1f}, max {errors.max() / 1e3:.1f}, n={errors.size}")
    assert np.all(np.abs(errors) < 1_000_000)


def _api_backend_across_processes_with_c_double(procs, rclpy_context, tmp_path):
    from fullperc_common.testing import installed_exe, wait_for

    lib = compile_double(C_DIR / "fake_diana_api.c", tmp_path / "libDianaApi.so")
    procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", "-p", "backend:=diana_api",
                 "-p", f"api_library:={lib}", "-p", "robot_ip:=192.168.10.75", "-p", "dh_source:=controller",
                 "-p", "rate_hz:=50.0", "-p", "diagnostics_period_s:=0.2"])
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: (lis.spin(), len(lis.flange) >= 10)[1], timeout=30, what="flange poses")
        wait_for(lambda: (lis.spin(), lis.last_status("diana")[1].get("vendor_tcp_vs_fk_mm", "n/a") != "n/a")[1],
                 timeout=10, what="diagnostics with the vendor cross-check")
    finally:
        lis.close()
    # The double's controller sits at q = 0: reference/diana_eval.md gives the flange at (-0.087, 0, 1.3165) m.
    p = lis.flange[-1].pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], [-0.087, 0.0, 1.3165], atol=1e-9)
    assert list(lis.js[-1].position) == [0.0] * 7 and list(lis.js[-1].velocity) == []
    st, values = lis.last_status("diana")
    assert values["dh_loaded"] == "True" and float(values["vendor_tcp_vs_fk_mm"]) < 1e-6
    assert "receiving" in st.message


def _wrong_api_library_path_exits_with_clear_error(procs, tmp_path):
    from fullperc_common.testing import installed_exe, wait_for

    bad = tmp_path / "nope" / "libDianaApi.so"
    p = procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", "-p", "backend:=diana_api",
                     "-p", f"api_library:={bad}"])
    wait_for(lambda: p.poll() is not None, timeout=30, what="diana_state to exit")
    assert p.returncode == 2 and str(bad) in procs.log(p)


BAD_PARAMETERS = [(["-p", "dh_source:=controller"], "dh_source"), (["-p", "dh_d:=[1.0, 2.0]"], "dh_d")]


def _bad_parameters_exit_naming_the_parameter(procs, args, needle):
    from fullperc_common.testing import installed_exe, wait_for

    p = procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", *args])
    wait_for(lambda: p.poll() is not None, timeout=30, what="diana_state to exit")
    assert p.returncode == 2 and needle in procs.log(p)


def _shipped_params_file_matches_reference_table_and_starts(procs, rclpy_context):
    import yaml

    from fullperc_common.testing import installed_exe, wait_for, workspace_root

    cfg = workspace_root() / "install/fullperc_drivers/share/fullperc_drivers/config/diana.yaml"
    params = yaml.safe_load(cfg.read_text())["/**/diana_state"]["ros__parameters"]
    table = np.array(_DOC_TABLE)  # alpha, a, d, theta rows from reference/diana_eval.md
    for key, col in (("dh_alpha", 0), ("dh_a", 1), ("dh_d", 2), ("dh_theta", 3)):
        np.testing.assert_allclose(params[key], table[:, col], atol=1e-15, err_msg=key)
    p = procs.start([installed_exe("fullperc_drivers", "diana_state"), "--ros-args", "--params-file", str(cfg),
                     "-p", f"stream_port:={free_udp_port()}", "-p", "dh_source:=parameters"])
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: (lis.spin(), lis.last_status("diana")[0] is not None)[1], timeout=30, what="diagnostics")
    finally:
        lis.close()
    st, values = lis.last_status("diana")
    assert p.poll() is None and "no joint state received yet" in st.message and values["dh_source"] == "parameters"


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--samples", type=int, default=200)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--truth", type=Path, required=True)
    a = ap.parse_args()
    run_sender(a.port, a.samples, a.rate, a.truth)


scenarios = side_by_side_fixture(
    _stream_backend_across_processes,
    _api_backend_across_processes_with_c_double,
    _wrong_api_library_path_exits_with_clear_error,
    _shipped_params_file_matches_reference_table_and_starts,
    **{f"test_bad_parameters_exit_naming_the_parameter[args{k}-{needle}]":
       (_bad_parameters_exit_naming_the_parameter, {"args": args, "needle": needle})
       for k, (args, needle) in enumerate(BAD_PARAMETERS)})


def test_stream_backend_across_processes(scenarios, request):
    scenarios.result(request.node.name)


def test_api_backend_across_processes_with_c_double(scenarios, request):
    scenarios.result(request.node.name)


def test_wrong_api_library_path_exits_with_clear_error(scenarios, request):
    scenarios.result(request.node.name)


@pytest.mark.parametrize("args, needle", BAD_PARAMETERS)
def test_bad_parameters_exit_naming_the_parameter(scenarios, request, args, needle):
    scenarios.result(request.node.name)


def test_shipped_params_file_matches_reference_table_and_starts(scenarios, request):
    scenarios.result(request.node.name)
