"""fullperc/poses (fullperc_msgs/FusedPoseArray, issue 38 item 1): every target's newest fused pose of one wake-up in
one message.

Unit (fusion_publish.PosesPublisher, fake publishers): the entries' values, their order (the node's ``targets``, not
the order they came in), the covariance flattened row-major as pose_cov carries it, the newest output of a target
per wake-up, a refused pose or covariance left out (never NaN), nothing built or sent without a reader, the
parameter and the relative topic name. System (marked): the installed fusion_node with two targets fed by
synthetic_driver_pub over Fast DDS, fusing on arrival (the default) and in stamp order (``processing: ordered``, whose
timer releases both targets' items in one wake-up); every entry of every array equals the same target's message of
the same stamp on its own pose and pose_cov topics.
"""

from __future__ import annotations

import copy
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.ros_conv import ns_to_stamp
from fullperc_common.testing import installed_exe, load_by_path, side_by_side_fixture, wait_for, wait_for_first_line
from fullperc_fusion import fusion_publish
from fullperc_fusion.fusion_publish import OutputPublisher, PosesPublisher, publish_outputs
from fullperc_fusion.pipeline.ordered import FusedOutput

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
S = 1_000_000_000


class FakePub:
    def __init__(self, subs: int = 1) -> None:
        self.subs = subs
        self.sent: list = []

    def get_subscription_count(self) -> int:
        return self.subs

    def publish(self, msg) -> None:
        self.sent.append(copy.deepcopy(msg))   # what rclpy serialises at this moment (the message is refilled)


def _out(target="tool", filt="cbkf", t_ns=1_700_000_000 * S + 123_456_789, k=0.0):
    """An output whose every number differs by target and ``k``; an asymmetric covariance (a transposed or
    column-major layout would not equal it)."""
    q = np.array([0.1, 0.2 + k, 0.3, 0.9])
    off = {"tool": 0.0, "probe": 1.0, "stray": 2.0}[target]
    return FusedOutput(target=target, filter=filt, t_ns=t_ns, p=np.array([0.1, -0.2, 0.3]) + off + k,
                       q=q / np.linalg.norm(q), cov=np.arange(36.0).reshape(6, 6) * 1e-6 + off + k,
                       bias=np.zeros(3), innovation=np.zeros(3), nis=1.0, hop=False, sources=3,
                       orientation_source=2, time_since_local=0.0, reset=False)


def _pose(m) -> list[float]:
    p, q = m.position, m.orientation
    return [p.x, p.y, p.z, q.x, q.y, q.z, q.w]


def _ns(stamp) -> int:
    return stamp.sec * S + stamp.nanosec


def test_one_message_per_wakeup_holds_each_targets_newest_output_in_the_targets_order():
    pub = FakePub()
    poses = PosesPublisher(pub, "or1_base", ["tool", "probe", "stray"])
    t = 1_700_000_000 * S
    probe_old, tool, probe_new = _out("probe", t_ns=t + 5, k=0.01), _out("tool", t_ns=t + 9), \
        _out("probe", t_ns=t + 7, k=0.02)
    for target, o in (("probe", probe_old), ("tool", tool), ("probe", probe_new)):
        poses.add(target, o)
    msg = poses.flush()
    assert pub.sent and len(pub.sent) == 1 and msg is not None
    m = pub.sent[0]
    assert m.header.frame_id == "or1_base" and m.header.stamp == ns_to_stamp(t + 9)   # the newest entry's stamp
    assert [e.target for e in m.poses] == ["tool", "probe"]   # `targets` order; stray had nothing: absent
    for e, o in zip(m.poses, (tool, probe_new), strict=True):
        assert _ns(e.stamp) == o.t_ns
        assert np.allclose(_pose(e.pose.pose), [*o.p, *o.q], rtol=0, atol=1e-15)
        cov = np.array(e.pose.covariance)
        assert cov.shape == (36,) and np.array_equal(cov, o.cov.reshape(-1))   # row-major: cov[6 * i + j] = C[i, j]
        assert cov[1] == o.cov[0, 1] != o.cov[1, 0]
    # the next wake-up starts empty: nothing new, nothing sent; then only what it brought
    assert poses.flush() is None and len(pub.sent) == 1
    poses.add("stray", _out("stray", t_ns=t + 3))
    poses.flush()
    assert [(e.target, _ns(e.stamp)) for e in pub.sent[1].poses] == [("stray", t + 3)]
    assert pub.sent[1].header.stamp == ns_to_stamp(t + 3)


def test_entries_equal_what_pose_and_pose_cov_carry_and_only_the_primary_goes_in():
    """Through publish_outputs, as fusion_node calls it: a side-by-side filter's output is not an entry, a primary
    output refused on its pose topic (NaN) is not either -- the earlier good one of that wake-up stays the entry."""
    sets = {(t, k): OutputPublisher(FakePub(), FakePub() if k == "" else None, FakePub())
            for t in ("tool", "probe") for k in ("", "kf")}
    arr = FakePub()
    poses = PosesPublisher(arr, "base", ["tool", "probe"])
    t = 1_700_000_000 * S
    good, bad = _out("probe", t_ns=t + 1), replace(_out("probe", t_ns=t + 2), p=np.array([np.nan, 0.0, 0.0]))
    errors = []
    for target, outs in (("probe", [good, _out("probe", "kf", t_ns=t + 1, k=0.5), bad]),
                         ("tool", [_out("tool", t_ns=t + i, k=0.001 * i) for i in range(3)])):
        publish_outputs(sets, target, outs, "cbkf", ["kf"], 0, on_primary=lambda o: None,
                        on_error=lambda o, why: errors.append(o.t_ns), tf_of=None, poses=poses)
    poses.flush()
    assert errors == [t + 2] and len(arr.sent) == 1
    entries = {e.target: e for e in arr.sent[0].poses}
    assert list(entries) == ["tool", "probe"]
    for target in entries:
        pose, cov = sets[(target, "")].pose_pub.sent[-1], sets[(target, "")].cov_pub.sent[-1]
        e = entries[target]
        assert e.stamp == pose.header.stamp == cov.header.stamp
        assert _pose(e.pose.pose) == _pose(pose.pose) == _pose(cov.pose.pose)   # bit for bit
        assert list(e.pose.covariance) == list(cov.pose.covariance)
    assert _ns(entries["probe"].stamp) == t + 1 and _ns(entries["tool"].stamp) == t + 2


@pytest.mark.parametrize("fault", ["nan_position", "inf_quaternion", "non_unit_quaternion", "nan_covariance",
                                   "covariance_shape"])
def test_a_refused_entry_is_left_out_and_reported_never_sent_as_nan(fault):
    o = _out("probe", t_ns=7 * S)
    bad = {"nan_position": replace(o, p=np.array([0.0, math.nan, 0.0])),
           "inf_quaternion": replace(o, q=np.array([0.0, 0.0, math.inf, 1.0])),
           "non_unit_quaternion": replace(o, q=np.array([0.0, 0.0, 0.0, 1.01])),
           "nan_covariance": replace(o, cov=np.where(np.eye(6) > 0, math.nan, o.cov)),
           "covariance_shape": replace(o, cov=np.eye(3))}[fault]
    pub, errors = FakePub(), []
    poses = PosesPublisher(pub, "base", ["tool", "probe"], on_error=lambda t, o, why: errors.append((t, o, why)))
    poses.add("tool", _out("tool", t_ns=5 * S))
    poses.add("probe", bad)
    poses.flush()
    assert [(t, o is bad) for t, o, _ in errors] == [("probe", True)] and "fullperc/poses" in errors[0][2]
    m = pub.sent[0]
    assert [e.target for e in m.poses] == ["tool"] and m.header.stamp == ns_to_stamp(5 * S)
    assert all(np.isfinite(_pose(e.pose.pose)).all() and np.isfinite(e.pose.covariance).all() for e in m.poses)
    # every entry refused: no message at all (an array is never empty)
    poses.add("probe", bad)
    assert poses.flush() is None and len(pub.sent) == 1 and len(errors) == 2


def test_nothing_is_built_or_sent_without_a_reader(monkeypatch):
    """Volatile like every output: with no reader matched the wake-up's entries are dropped unbuilt (no fill_pose
    call), and a reader that matches later gets the next wake-up's, not stale ones; ``publish_poses: false`` (no
    publisher) keeps nothing at all."""
    calls = []
    real = fusion_publish.fill_pose
    monkeypatch.setattr(fusion_publish, "fill_pose", lambda *a: (calls.append(a), real(*a)))
    pub = FakePub(subs=0)
    poses = PosesPublisher(pub, "base", ["tool"])
    for i in range(5):
        poses.add("tool", _out(t_ns=(i + 1) * S))
    assert poses.flush() is None and pub.sent == [] and calls == []
    pub.subs = 1
    assert poses.flush() is None and pub.sent == []   # nothing left over from the unread wake-up
    poses.add("tool", _out(t_ns=9 * S))
    poses.flush()
    assert [_ns(m.header.stamp) for m in pub.sent] == [9 * S] and len(calls) == 1
    off = PosesPublisher(None, "base", ["tool"])
    off.add("tool", _out())
    assert off.flush() is None and off._newest == {}


@pytest.mark.system
def test_publish_poses_switches_the_topic_and_its_name_is_relative(rclpy_context):
    """``publish_poses`` (default true) makes the node's ``fullperc/poses`` publisher, under its namespace; false
    makes none."""
    from rclpy.parameter import Parameter

    from fullperc_fusion.fusion_node import FusionNode

    for kw, want in (({}, "/fullperc/poses"), ({"namespace": "/or1"}, "/or1/fullperc/poses")):
        node = FusionNode(context=rclpy_context, **kw)
        try:
            assert node._poses.pub.topic_name == want
            assert node._poses.msg.header.frame_id == "base" and list(node._poses._entries) == ["tool"]
        finally:
            node.destroy_node()
    node = FusionNode(context=rclpy_context, parameter_overrides=[Parameter("publish_poses", value=False)])
    try:
        assert node._poses.pub is None
    finally:
        node.destroy_node()


# ------------------------------------------------------------------------------------------ across processes
TARGETS = ("tool", "probe")   # tool: OMC + OTS; probe: a further OMC body on the same path (OMC only)


def _two_targets_over_dds(procs, rclpy_context, tmp_path, processing: str) -> dict:
    """The installed node fusing tool and probe; this process subscribes to fullperc/poses and to each target's
    pose and pose_cov (reliable, deep: every message kept), then runs synthetic_driver_pub for 3 s."""
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.testing import SpunNode
    from fullperc_msgs.msg import FusedPoseArray

    mod = load_by_path(PUB, "synthetic_driver_pub")
    node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p", "targets:=[tool, probe]",
                        "-p", "init_samples:=20", "-p", "qos_depth:=5000", "-p", f"processing:={processing}"],
                       name="fusion_node")
    wait_for_first_line(procs, node)
    topics = {"/fullperc/poses": FusedPoseArray} | {f"/fullperc/{t}/{w}": typ for t in TARGETS
                                                     for w, typ in (("pose", PoseStamped),
                                                                    ("pose_cov", PoseWithCovarianceStamped))}
    lis = SpunNode(rclpy_context, "poses_listener")
    got: dict[str, list] = {t: [] for t in topics}
    qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
    for t, typ in topics.items():
        lis.node.create_subscription(typ, t, got[t].append, qos)
    lis.start()
    try:
        wait_for(lambda: all(s.get_publisher_count() > 0 for s in lis.node.subscriptions), 60,
                 what="subscriptions matched with fusion_node's outputs", detail=lambda: procs.log(node)[-2000:])
        pub = procs.start([sys.executable, str(PUB), "--log", str(tmp_path / "pub.jsonl"), "--duration", "3.0",
                           "--extra-bodies", "probe"], name="pub")
        log = tmp_path / "pub.jsonl"
        wait_for(lambda: pub.poll() is not None or mod.log_complete(log), 90, what="the publisher's data",
                 detail=lambda: procs.log(pub)[-2000:])
        rows, _ = mod.read_log(log)
        last = {t: max(r["t_ns"] for r in rows if r["body"] == t) for t in TARGETS}

        def newest(target: str) -> int:   # stamp of the target's newest entry in the arrays received so far
            return max((_ns(e.stamp) for m in list(got["/fullperc/poses"]) for e in m.poses if e.target == target),
                       default=0)
        # liveness bounds only: every sample fused (its pose out), and the array of that wake-up in
        wait_for(lambda: all(got[f"/fullperc/{t}/pose"] and _ns(got[f"/fullperc/{t}/pose"][-1].header.stamp)
                             >= last[t] and newest(t) >= last[t] for t in TARGETS), 60,
                 what="every target's newest sample fused and in fullperc/poses",
                 detail=lambda: ({t: len(v) for t, v in got.items()}, procs.log(node)[-2000:]))
        wait_for(lambda: pub.poll() is not None, 30, what="the publisher to exit")
        assert pub.returncode == 0, procs.log(pub)
        return {"got": {t: list(v) for t, v in got.items()}, "alive": node.poll() is None, "log": procs.log(node)}
    finally:
        lis.close()


MODES = ("arrival", "ordered")
scenarios = side_by_side_fixture(**{f"test_two_targets_over_dds[{m}]": (_two_targets_over_dds, {"processing": m})
                                    for m in MODES})


@pytest.mark.system
@pytest.mark.parametrize("processing", MODES)
def test_two_targets_over_dds(scenarios, request, processing):
    r = scenarios.result(request.node.name)
    assert r["alive"], r["log"]
    got = r["got"]
    arrays = got["/fullperc/poses"]
    pose = {t: {_ns(m.header.stamp): m for m in got[f"/fullperc/{t}/pose"]} for t in TARGETS}
    cov = {t: {_ns(m.header.stamp): m for m in got[f"/fullperc/{t}/pose_cov"]} for t in TARGETS}
    assert all(len(pose[t]) > 150 for t in TARGETS), {t: len(v) for t, v in pose.items()}
    per_target: dict[str, list[int]] = {t: [] for t in TARGETS}
    both = 0
    for m in arrays:
        names = [e.target for e in m.poses]
        assert m.poses and m.header.frame_id == "base" and names == [t for t in TARGETS if t in names], names
        assert _ns(m.header.stamp) == max(_ns(e.stamp) for e in m.poses)
        both += len(names) == 2
        for e in m.poses:
            ns = _ns(e.stamp)
            ps, pc = pose[e.target][ns], cov[e.target][ns]   # KeyError: an entry no pose topic carried
            assert _pose(e.pose.pose) == _pose(ps.pose) == _pose(pc.pose.pose), (e.target, ns)
            assert list(e.pose.covariance) == list(pc.pose.covariance), (e.target, ns)
            assert np.all(np.isfinite(e.pose.covariance)) and e.pose.covariance[0] > 0
            per_target[e.target].append(ns)
    for t in TARGETS:
        # one entry per wake-up, its newest: stamps rise from array to array, and the last is the topic's last
        s = per_target[t]
        assert s and all(b > a for a, b in zip(s, s[1:], strict=False)), t
        assert s[-1] == max(pose[t]), t
    if processing == "ordered":   # the timer releases both targets' items of a stamp in one tick: one array
        assert both > 0, "no array held both targets"
