"""``omc_driver`` across processes: the installed executable against a UDP sender in another process.

The sender (this file run as a script) speaks the simulator's OMC wire format (``streams.encode_omc``) with a
device clock deliberately offset from the host clock, a reported latency, a frame-number gap, a body that is
lost (tracking flag cleared, then sentinel coordinates), a body not in the ``bodies`` filter, and garbage
datagrams; it writes the truth (frame number -> capture time on the host clock) to a file, then stops, so
the test also sees the "stream stopped" diagnosis. A second test runs the node on the SDK backend with the
compiled C double, and a third checks the clear error for a wrong library path. Another sender run checks
``/omc/bodies`` against the per-body topics, frame by frame.
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import struct
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.ports import free_port
from fullperc_common.testing import side_by_side_fixture

FIRST_FRAME, GAP_AT, GAP = 5000, 150, 4
FLAG_LOST = (60, 80)  # tool: tracked flag cleared
SENTINEL_LOST = (100, 115)  # tool: UNDEFINED coordinates with the flag still set
BAD_EVERY = 25  # one garbage datagram (cycling over 5 kinds) every BAD_EVERY frames
DEVICE_OFFSET_NS = -7_345_678_901  # device clock = host clock + offset
LATENCY_S = 0.0035


def frame_number(k: int) -> int:
    return FIRST_FRAME + k + (GAP if k >= GAP_AT else 0)


def base_mm(k: int) -> np.ndarray:
    return np.array([1000.0 + 0.25 * k, -500.0, 750.125])


def tool_mm(k: int) -> np.ndarray:
    return np.array([200.0, 300.0 - 0.5 * k, 1200.0 + math.sin(k / 10.0)])


def tool_quat(k: int) -> np.ndarray:
    a = 0.02 * k
    return np.array([math.sin(a / 2), 0.0, 0.0, math.cos(a / 2)])


def run_sender(port: int, frames: int, rate: float, truth: Path) -> None:
    from fullperc_drivers.streams import OmcBody, OmcFrame, encode_omc

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    lines, bad = [], 0
    period = 1.0 / rate
    t0 = time.monotonic()
    for k in range(frames):
        time.sleep(max(0.0, t0 + (k + 1) * period - time.monotonic()))
        tool_flag = not (FLAG_LOST[0] <= k < FLAG_LOST[1])
        tool_pos = np.full(3, 999999.9999) if SENTINEL_LOST[0] <= k < SENTINEL_LOST[1] else tool_mm(k)
        capture = time.time_ns() - int(LATENCY_S * 1e9)
        f = OmcFrame(frame_number(k), capture + DEVICE_OFFSET_NS, LATENCY_S, [
            OmcBody(1, "base", base_mm(k), np.array([0.0, 0.0, 0.0, 1.0]), 0.11, True, 4),
            OmcBody(2, "tool", tool_pos, tool_quat(k), 0.2, tool_flag, 5 if tool_flag else 0),
            OmcBody(3, "ots_rig", np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0, 1.0]), 0.1, True, 4),
        ])
        data = encode_omc(f)
        sock.sendto(data, ("127.0.0.1", port))
        lines.append(f"{f.frame_number} {capture}\n")
        if k % BAD_EVERY == BAD_EVERY - 1:
            kind = (k // BAD_EVERY) % 5
            garbage = [data[: len(data) // 2],  # truncated
                       os.urandom(len(data)),  # garbled
                       b"XXXX" + data[4:],  # wrong magic
                       data[:4] + struct.pack("<H", 99) + data[6:],  # wrong version
                       data[:12]][kind]  # shorter than the header
            sock.sendto(garbage, ("127.0.0.1", port))
            bad += 1
    truth.write_text("".join(lines) + f"bad {bad}\n")


def free_udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


class Listener:
    """In-test subscriber node collecting the driver's output."""

    def __init__(self, ctx, bodies=("base", "tool"), frames: bool = False):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_msgs.msg import TrackingQuality

        self.node = Node("omc_test_listener", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        self.poses: dict[str, list] = {b: [] for b in bodies}
        self.quality: dict[str, list] = {b: [] for b in bodies}
        self.diag: list = []
        self.frames: list = []   # /omc/bodies (TrackedBodies), when ``frames``
        for b in bodies:
            self.node.create_subscription(PoseStamped, f"/omc/{b}/pose", self.poses[b].append, qos)
            self.node.create_subscription(TrackingQuality, f"/omc/{b}/quality", self.quality[b].append, qos)
        if frames:
            from fullperc_msgs.msg import TrackedBodies

            self.node.create_subscription(TrackedBodies, "/omc/bodies", self.frames.append, qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 100)

    def spin(self, seconds: float = 0.05) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.01)

    def last_status(self, name_part: str):
        for arr in reversed(self.diag):
            for st in arr.status:
                if name_part in st.name:
                    return st, {kv.key: kv.value for kv in st.values}
        return None, {}

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()


def wait_matched(lis: Listener, procs, node) -> None:
    """Both sides of discovery, as conditions: this listener's subscriptions matched the driver's publishers, and the
    driver says its pose publishers matched this listener (``subscribers on <topic>: 1``, its SubscriberLog) --
    samples it sent before would not reach us (a fixed 0.5 s for the second half was short on a busy machine)."""
    from fullperc_common.testing import wait_for

    wait_for(lambda: (lis.spin(), all(s.get_publisher_count() >= 1 for s in lis.node.subscriptions
                                      if s.topic_name.startswith("/omc/")))[1], timeout=30, what="listener matched")
    wait_for(lambda: (lis.spin(), all(f"subscribers on /omc/{b}/pose: 1" in procs.log(node) for b in lis.poses))[1],
             timeout=30, what="the driver matched this listener", detail=lambda: procs.log(node)[-1500:])


def _stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _stream_backend_across_processes(procs, rclpy_context, tmp_path, python_exe):
    from fullperc_common.testing import installed_exe, wait_for

    port = free_udp_port()
    frames, rate = 260, 100.0
    node = procs.start([installed_exe("fullperc_drivers", "omc_driver"), "--ros-args",
                        "-p", "backend:=stream", "-p", f"stream_port:={port}", "-p", "bodies:=[base, tool]",
                        "-p", "qos_depth:=1000", "-p", "stale_timeout_s:=0.5", "-p", "diagnostics_period_s:=0.2"])
    lis = Listener(rclpy_context)
    try:
        def matched():
            lis.spin()
            return all(lis.node.count_publishers(f"/omc/{b}/{t}") >= 1 for b in ("base", "tool")
                       for t in ("pose", "quality"))
        wait_for(matched, timeout=30, what="omc_driver topics")
        wait_matched(lis, procs, node)
        truth_file = tmp_path / "truth.txt"
        sender = procs.start([python_exe, __file__, "--port", str(port), "--frames", str(frames),
                              "--rate", str(rate), "--truth", str(truth_file)], name="sender")
        wait_for(lambda: (lis.spin(), sender.poll() is not None)[1], timeout=60, what="sender to finish")
        assert sender.returncode == 0, procs.log(sender)

        def stopped_diagnosed():
            lis.spin()
            st, _ = lis.last_status("omc")
            return st is not None and "stream stopped" in st.message
        wait_for(stopped_diagnosed, timeout=20, what="'stream stopped' diagnosis")
        assert node.poll() is None, procs.log(node)  # no crash
        st, values = lis.last_status("omc")
        assert st.level == b"\x02" or st.level == 2  # ERROR while stopped
    finally:
        lis.close()

    lines = truth_file.read_text().split("\n")
    truth = {int(a): int(b) for a, b in (ln.split() for ln in lines if ln and not ln.startswith("bad"))}
    n_bad = int(next(ln for ln in lines if ln.startswith("bad")).split()[1])
    k_of = {frame_number(k): k for k in range(frames)}

    # Counters on /diagnostics: garbage counted, gap counted as dropped frames, stall counted.
    assert int(values["decode_errors"]) == n_bad > 0
    assert int(values["dropped_frames"]) == GAP
    assert int(values["stalls"]) >= 1 and int(values["frames"]) == frames

    base = lis.poses["base"]
    assert len(base) == frames  # reliable QoS, deep queues: every frame arrives
    errors = []
    assert all(m.header.frame_id == "omc" for m in base)
    # Poses carry no frame number: pair them with the quality messages (same stamp, same frame).
    qual_by_stamp = {_stamp_ns(q): q for q in lis.quality["base"]}
    for m in base:
        q = qual_by_stamp[_stamp_ns(m)]
        k = k_of[q.frame_number]
        p = m.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], base_mm(k) / 1000.0, atol=1e-12)
        assert q.visible and q.body == "base" and q.markers_used == 4 and q.fit_error == pytest.approx(0.11e-3)
        assert q.header.frame_id == "omc"
        if k >= 50:  # after the offset estimate has seen a few frames
            errors.append(_stamp_ns(m) - truth[q.frame_number])
    errors = np.array(errors)
    print(f"\nOMC stamp error vs truth [us]: median {np.median(errors) / 1e3:.1f}, "
          f"min {errors.min() / 1e3:.1f}, max {errors.max() / 1e3:.1f}, n={errors.size}")
    assert np.all(np.abs(errors) < 1_000_000), "capture stamp not within 1 ms of the truth"

    tool_q = {q.frame_number: q for q in lis.quality["tool"]}
    assert len(tool_q) == frames
    tool_pose_stamps = {_stamp_ns(m) for m in lis.poses["tool"]}
    for k in range(frames):
        q = tool_q[frame_number(k)]
        lost = FLAG_LOST[0] <= k < FLAG_LOST[1] or SENTINEL_LOST[0] <= k < SENTINEL_LOST[1]
        assert q.visible is (not lost), k
        assert (_stamp_ns(q) in tool_pose_stamps) is (not lost), k
    for m in lis.poses["tool"]:
        v = [m.pose.position.x, m.pose.position.y, m.pose.position.z, m.pose.orientation.x, m.pose.orientation.w]
        assert all(math.isfinite(x) for x in v) and abs(m.pose.position.x) < 10


def _sdk_backend_across_processes_with_c_double(procs, rclpy_context, tmp_path):
    """The node on the nokov_sdk backend, loading the compiled double: names (incl. a late body), sentinels."""
    from fullperc_common.testing import installed_exe, wait_for

    sys.path.insert(0, str(Path(__file__).parent))
    from test_nokov_sdk import C_DIR, compile_double

    lib = compile_double(C_DIR / "fake_nokov_sdk.c", tmp_path / "libnokov_sdk.so")
    start = tmp_path / "start"  # the double plays its frames once this file exists
    node = procs.start([installed_exe("fullperc_drivers", "omc_driver"), "--ros-args", "-p", "backend:=nokov_sdk",
                 "-p", f"sdk_library:={lib}", "-p", "server:=10.1.1.198", "-p", "sdk_timestamp_unit_ns:=1000",
                 "-p", "bodies:=[base, tool]", "-p", "qos_depth:=1000", "-p", "diagnostics_period_s:=0.2"],
                env={**procs.env, "FAKE_NOKOV_START_FILE": str(start)})
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: (lis.spin(), all(lis.node.count_publishers(f"/omc/{b}/{t}") >= 1 for b in ("base", "tool")
                                          for t in ("pose", "quality")))[1], timeout=30, what="omc_driver topics")
        wait_matched(lis, procs, node)
        start.touch()
        # The double plays 300 frames at 200 Hz from Initialize on; wait for its end (the quality of frame
        # index 299, numbered 1000 + 299 + 3), then for the stall diagnosis.
        wait_for(lambda: (lis.spin(), any(q.frame_number == 1302 for q in lis.quality["base"]))[1],
                 timeout=40, what="the last frame of the C double")
        wait_for(lambda: (lis.spin(), (lis.last_status("omc")[1].get("stalls", "0") != "0"))[1], timeout=20,
                 what="stall diagnosis")
    finally:
        lis.close()
    _, values = lis.last_status("omc")
    assert values["sdk_version"] == "2.5.53.12" and int(values["dropped_frames"]) == 3
    tool = lis.quality["tool"]
    assert tool, "late body 'tool' never resolved by name"
    lost = [q for q in tool if 1000 + 120 <= q.frame_number < 1000 + 140]
    assert lost and not any(q.visible for q in lost)
    visible = [q for q in tool if q.visible]
    assert len(visible) >= 300 - 50 - 20 - 20  # appears at 50, lost for 20, a few unnamed right after it appears
    assert all(m.header.frame_id == "omc" for m in lis.poses["tool"])
    assert max(abs(m.pose.position.x - 0.5) for m in lis.poses["tool"]) < 1e-6  # 500 mm -> 0.5 m


def _bodies_carries_every_frame_as_the_per_body_topics_do(procs, rclpy_context, tmp_path, python_exe):
    """``/omc/bodies``: one TrackedBodies per device frame, whose stamp and frame_id are those of the frame's per-body
    messages (matched by stamp), one body per quality message of the frame in the order of the ``bodies`` filter
    (``ots_rig``, sent but filtered out, absent), each with its quality's fields and its pose message's pose; a lost
    body (tracking flag cleared, sentinel coordinates) ``visible: false`` with an all-zero pose and no pose message."""
    from geometry_msgs.msg import Pose

    from fullperc_common.testing import installed_exe, wait_for

    port = free_udp_port()
    frames = SENTINEL_LOST[1] + 10   # both lost spells of "tool"
    node = procs.start([installed_exe("fullperc_drivers", "omc_driver"), "--ros-args", "-p", "backend:=stream",
                        "-p", f"stream_port:={port}", "-p", "bodies:=[base, tool]", "-p", "qos_depth:=1000"])
    lis = Listener(rclpy_context, frames=True)
    try:
        wait_for(lambda: (lis.spin(), lis.node.count_publishers("/omc/bodies") >= 1)[1], timeout=30,
                 what="omc_driver's /omc/bodies")
        wait_matched(lis, procs, node)
        sender = procs.start([python_exe, __file__, "--port", str(port), "--frames", str(frames),
                              "--rate", "100", "--truth", str(tmp_path / "truth.txt")], name="sender")
        wait_for(lambda: (lis.spin(), sender.poll() is not None)[1], timeout=60, what="sender to finish")
        assert sender.returncode == 0, procs.log(sender)
        wait_for(lambda: (lis.spin(), len(lis.frames) >= frames and len(lis.quality["tool"]) >= frames)[1],
                 timeout=30, what=f"{frames} frames on /omc/bodies and the quality topics",
                 detail=lambda: (len(lis.frames), len(lis.quality["tool"])))
        lis.spin(0.2)   # nothing more may come
    finally:
        lis.close()
    assert len(lis.frames) == frames   # reliable, deep queues: every frame once
    quality = {b: {_stamp_ns(q): q for q in lis.quality[b]} for b in ("base", "tool")}
    poses = {b: {_stamp_ns(m): m for m in lis.poses[b]} for b in ("base", "tool")}
    lost = []
    for f in lis.frames:
        t = _stamp_ns(f)
        assert [b.name for b in f.bodies] == ["base", "tool"], [b.name for b in f.bodies]
        for b in f.bodies:
            q = quality[b.name][t]   # the quality message of this body with the frame's stamp
            assert f.header == q.header and f.header.frame_id == "omc" and f.latency == q.latency
            assert (b.visible, b.fit_error, b.frame_number, b.markers_used, b.port_status) == \
                (q.visible, q.fit_error, q.frame_number, q.markers_used, q.port_status), b.name
            if b.visible:
                assert poses[b.name][t].header == f.header and b.pose == poses[b.name][t].pose, b.name
            else:
                assert t not in poses[b.name] and b.pose == Pose(), b.name
                lost.append((b.name, q.frame_number))
    assert [f.bodies[0].frame_number for f in lis.frames] == [frame_number(k) for k in range(frames)]
    assert lost == [("tool", frame_number(k)) for k in range(frames)
                    if FLAG_LOST[0] <= k < FLAG_LOST[1] or SENTINEL_LOST[0] <= k < SENTINEL_LOST[1]]


def _wrong_sdk_library_path_exits_with_clear_error(procs, tmp_path):
    from fullperc_common.testing import installed_exe, wait_for

    bad = tmp_path / "missing" / "libnokov_sdk.so"
    p = procs.start([installed_exe("fullperc_drivers", "omc_driver"), "--ros-args", "-p", "backend:=nokov_sdk",
                     "-p", f"sdk_library:={bad}"])
    wait_for(lambda: p.poll() is not None, timeout=30, what="omc_driver to exit")
    assert p.returncode == 2
    assert str(bad) in procs.log(p) and "not found" in procs.log(p)


def _shipped_params_file_starts_the_node(procs, rclpy_context):
    """config/omc.yaml parses and passes parameter validation; the node then waits for frames (WARN)."""
    from fullperc_common.testing import installed_exe, wait_for, workspace_root

    cfg = workspace_root() / "install/fullperc_drivers/share/fullperc_drivers/config/omc.yaml"
    p = procs.start([installed_exe("fullperc_drivers", "omc_driver"), "--ros-args", "--params-file", str(cfg),
                     "-p", f"stream_port:={free_udp_port()}"])
    lis = Listener(rclpy_context)
    try:
        wait_for(lambda: (lis.spin(), lis.last_status("omc")[0] is not None)[1], timeout=30, what="diagnostics")
    finally:
        lis.close()
    st, values = lis.last_status("omc")
    assert p.poll() is None and "no frame received yet" in st.message and values["backend"] == "stream"


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--truth", type=Path, required=True)
    a = ap.parse_args()
    run_sender(a.port, a.frames, a.rate, a.truth)


scenarios = side_by_side_fixture(
    _stream_backend_across_processes,
    _sdk_backend_across_processes_with_c_double,
    _bodies_carries_every_frame_as_the_per_body_topics_do,
    _wrong_sdk_library_path_exits_with_clear_error,
    _shipped_params_file_starts_the_node)


def test_stream_backend_across_processes(scenarios, request):
    scenarios.result(request.node.name)


def test_sdk_backend_across_processes_with_c_double(scenarios, request):
    scenarios.result(request.node.name)


def test_bodies_carries_every_frame_as_the_per_body_topics_do(scenarios, request):
    scenarios.result(request.node.name)


def test_wrong_sdk_library_path_exits_with_clear_error(scenarios, request):
    scenarios.result(request.node.name)


def test_shipped_params_file_starts_the_node(scenarios, request):
    scenarios.result(request.node.name)
