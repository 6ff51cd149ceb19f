"""The live benches' rule for a lost sample (bench/live_fusion.uncovered): a target sample stamped ``s`` is covered
by a fused pose stamped in ``[s, s + slop]`` -- its own output (fusion on arrival) or the output of its
approximate-time pair (stamped with the newer stamp); anything else is lost."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from live_fusion import target_params, uncovered  # noqa: E402

MS = 1_000_000


def test_own_stamp_and_pair_partner_are_covered() -> None:
    sent = np.array([0, 3 * MS, 10 * MS, 20 * MS])
    # 0 and 3 ms paired -> one output at 3 ms; 10 ms alone; 20 ms alone
    assert uncovered(sent, [3 * MS, 10 * MS, 20 * MS], 4 * MS) == 0


def test_missing_outputs_are_lost() -> None:
    sent = np.array([0, 10 * MS, 20 * MS, 30 * MS])
    assert uncovered(sent, [10 * MS, 30 * MS], 4 * MS) == 2        # 0 and 20 ms: no output within slop
    assert uncovered(sent, [5 * MS, 25 * MS], 4 * MS) == 4         # outputs more than slop after: not theirs
    assert uncovered(sent, [], 4 * MS) == 4
    assert uncovered(sent, [-1], 4 * MS) == 4                       # an output before a sample never covers it


def test_target_params_name_each_target_body_and_tool() -> None:
    args = target_params(["t0", "t1"])
    assert args[:2] == ["-p", "targets:=[t0, t1]"]
    assert "t1.omc_body:=t1" in args and "t1.ots_tool:=t1" in args


@pytest.mark.parametrize("outputs, want", [("every", ["pose", "pose_cov", "/tf", "status"]), ("pose", ["pose"]),
                                           ("none", [])])
def test_the_echo_floors_split_publishes_what_it_names(outputs: str, want: list[str]) -> None:
    """``echo_floor.py --outputs``, the split of bench_node_cost's floor: ``pose`` sends the pose alone, stamped as the
    input came, ``none`` nothing; ``every`` (the floor) the four messages. The per-sample path alone, no DDS."""
    from echo_floor import EchoFloor
    from geometry_msgs.msg import PoseStamped

    sent: list[tuple[str, object]] = []

    class Pub:
        def __init__(self, key: str) -> None:
            self.key = key

        def publish(self, m) -> None:
            sent.append((self.key, m))

    echo = object.__new__(EchoFloor)   # no rclpy node: only what echo() reads
    echo.outputs, echo.tf = outputs, Pub("/tf")
    echo.out = {"tool": (Pub("pose"), Pub("pose_cov"), Pub("status"))}
    m = PoseStamped()
    m.header.stamp.sec, m.header.stamp.nanosec, m.pose.position.x = 3, 7, 0.5
    echo.echo("tool", m)
    assert [k for k, _ in sent] == want
    if "pose" in want:
        ps = sent[0][1]
        assert (ps.header.stamp.sec, ps.header.stamp.nanosec, ps.header.frame_id, ps.pose.position.x) == \
            (3, 7, "base", 0.5)


def test_the_echo_floor_publishes_four_messages_per_target_sample(rclpy_context, ros_env) -> None:
    """bench/echo_floor.py, the baseline of bench_node_cost: every OMC or OTS sample of a target goes out as pose,
    pose_cov, status and one /tf message, stamped as it came; base bodies are taken and nothing is published."""
    import subprocess

    import rclpy
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.testing import wait_for
    from fullperc_common.tf import dynamic_qos
    from fullperc_msgs.msg import FusionStatus
    from tf2_msgs.msg import TFMessage

    bench = Path(__file__).resolve().parents[1] / "bench"
    proc = subprocess.Popen([sys.executable, str(bench / "echo_floor.py"), "--targets", "tool"], env=ros_env,
                            start_new_session=True)
    try:
        node = rclpy.create_node("echo_floor_check", context=rclpy_context)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        got: dict[str, list[int]] = {"pose": [], "pose_cov": [], "status": [], "/tf": []}

        def keep(key):
            return lambda m: got[key].append(
                (m.transforms[0].header if key == "/tf" else m.header).stamp.nanosec)

        for key, typ in (("pose", PoseStamped), ("pose_cov", PoseWithCovarianceStamped), ("status", FusionStatus)):
            node.create_subscription(typ, f"/fullperc/tool/{key}", keep(key), qos)
        node.create_subscription(TFMessage, "/tf", keep("/tf"), dynamic_qos())
        pubs = {t: node.create_publisher(PoseStamped, t, qos)
                for t in ("/omc/tool/pose", "/ots/tool/pose", "/omc/base/pose")}
        ex = SingleThreadedExecutor(context=rclpy_context)
        ex.add_node(node)

        def spin_until(pred, what):
            wait_for(lambda: (ex.spin_once(timeout_sec=0.05), pred())[1], timeout=60, what=what)

        spin_until(lambda: all(p.get_subscription_count() for p in pubs.values()), "the echo floor's inputs")

        def publish(stamp: int, topics=tuple(pubs)) -> None:
            for topic in topics:
                m = PoseStamped()
                m.header.stamp.nanosec = stamp + (topic == "/ots/tool/pose")
                m.pose.orientation.w = 1.0
                pubs[topic].publish(m)

        # warm-up: the echo's writers match these readers in their own time (volatile: what goes out before is lost)
        spin_until(lambda: publish(2, ["/omc/tool/pose"]) or all(got.values()), "every output matched")
        for k in range(1, 11):
            publish(k * 100)
        want = sorted(k * 100 + d for k in range(1, 11) for d in (0, 1))
        counted = {k: lambda k=k: sorted(s for s in got[k] if s >= 100) for k in got}
        spin_until(lambda: all(len(c()) >= len(want) for c in counted.values()), "20 echoes on each output")
        for _ in range(10):   # nothing more comes: the base body's samples are not echoed
            ex.spin_once(timeout_sec=0.05)
        assert {k: c() for k, c in counted.items()} == {k: want for k in got}
    finally:
        proc.send_signal(2)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert proc.returncode == 0


def test_graph_cpu_counts_every_descendant_by_its_executable(tmp_path) -> None:
    """bench/graph_cpu.py (docs/performance.md "The executor"): a process's descendants at any depth, not its
    siblings; a process named by the script it runs (``python .../fusion_node --ros-args ...``: fusion_node)."""
    import subprocess
    import time

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import graph_cpu

    parents = {10: 1, 11: 10, 12: 11, 13: 1, 14: 12}
    assert graph_cpu.family(10, parents) == {10, 11, 12, 14}
    assert graph_cpu.family(13, parents) == {13}
    script = tmp_path / "fake_node"
    script.write_text("import time\ntime.sleep(30)\n")
    p = subprocess.Popen([sys.executable, "-u", str(script), "--ros-args", "-p", "x:=1"])
    try:
        deadline = time.monotonic() + 10
        while graph_cpu._exe_name(p.pid) != "fake_node" and time.monotonic() < deadline:
            time.sleep(0.05)   # until the process has exec'd the interpreter with its arguments
        assert graph_cpu._exe_name(p.pid) == "fake_node"
    finally:
        p.kill()
        p.wait()
