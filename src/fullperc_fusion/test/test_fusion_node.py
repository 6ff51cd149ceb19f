"""fusion_node across processes: synthetic driver topics from one process, the installed fusion_node in
another, and this test subscribing to its outputs over DDS."""

from __future__ import annotations

import importlib.util
import json
import math
import re
import threading
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import installed_exe, wait_for

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
pytestmark = pytest.mark.system


def _load_pub_module():
    spec = importlib.util.spec_from_file_location("synthetic_driver_pub", PUB)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class Listener:
    """Subscribes to the node's outputs in this process (own context, spun in a thread)."""

    def __init__(self, ctx, topics):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_msgs.msg import FusionStatus

        self.node = rclpy.create_node("fusion_test_listener", context=ctx)
        qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
        self.got: dict[str, list] = {t: [] for t in topics}
        self.diag: list = []
        types = {"pose": PoseStamped, "pose_cov": PoseWithCovarianceStamped, "status": FusionStatus}
        for t in topics:
            self.node.create_subscription(types[t.rsplit("/", 1)[1]], t, lambda m, t=t: self.got[t].append(m), qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 100)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self._stop = False
        self.th = threading.Thread(target=self._spin, daemon=True)
        self.th.start()

    def _spin(self):
        while not self._stop:
            self.ex.spin_once(timeout_sec=0.05)

    def call_initialize(self, timeout=20.0):
        from std_srvs.srv import Trigger
        cli = self.node.create_client(Trigger, "/fusion_node/initialize")
        wait_for(lambda: cli.service_is_ready(), timeout, what="~/initialize service")
        fut = cli.call_async(Trigger.Request())
        wait_for(fut.done, timeout, what="~/initialize response")
        return fut.result()

    def close(self):
        self._stop = True
        self.th.join(2)
        self.node.destroy_node()


def _read_log(path):
    rows = [json.loads(line) for line in Path(path).read_text().splitlines()]
    meta = next(r for r in rows if r["kind"] == "meta")
    return [r for r in rows if r["kind"] != "meta"], meta["t0_ns"]


def _ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_fusion_node_end_to_end(procs, rclpy_context, python_exe, tmp_path):
    topics = ["/fullperc/tool/pose", "/fullperc/tool/pose_cov", "/fullperc/tool/status",
              "/fullperc/tool/kf/pose", "/fullperc/tool/kf/status"]
    lis = Listener(rclpy_context, topics)
    try:
        # qos_depth 1000: every input queue holds the whole 4 s run, so a node stalled on a busy machine still gets
        # each bad sample this test expects named (the default 100 is 0.8 s of one 120 Hz topic; the stand-in
        # publishes no TrackingQuality, so a sample lost from a full queue would go unnoticed)
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                            "-p", "filters:=[kf]", "-p", "init_samples:=20", "-p", "qos_depth:=1000"],
                           name="fusion_node")
        # start the data only once this listener is matched with every output of the node
        wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 30, what="node's publishers")
        wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions if p.topic_name in topics),
                 30, what="subscriptions matched")
        log = tmp_path / "pub.jsonl"
        pub = procs.start([python_exe, str(PUB), "--log", str(log), "--bad", "--duration", "4.0"], name="pub")
        # liveness bounds only: discovery + 4 s of data
        wait_for(lambda: pub.poll() is not None, 60, what="publisher to finish")
        assert pub.returncode == 0, procs.log(pub)
        wait_for(lambda: len(lis.got["/fullperc/tool/pose"]) > 0 and node.poll() is None, 10,
                 what="fused poses")
        rows, t0 = _read_log(log)
        n_good_in = sum(1 for r in rows if r["body"] == "tool" and "bad" not in r)
        # all pending items are flushed after idle_flush: wait until the counts stop growing
        last = [-1]

        def settled():
            n = len(lis.got["/fullperc/tool/pose"])
            done = n == last[0]
            last[0] = n
            return done
        wait_for(settled, 20, interval=1.0, what="outputs to settle")
        resp = lis.call_initialize()
        assert resp.success and "re-estimating" in resp.message
        assert node.poll() is None, procs.log(node)
    finally:
        lis.close()

    mod = _load_pub_module()
    good = {(r["kind"], r["t_ns"]) for r in rows if r["body"] == "tool" and "bad" not in r}
    good_stamps = {t for _, t in good}
    poses = lis.got["/fullperc/tool/pose"]
    covs = lis.got["/fullperc/tool/pose_cov"]
    stats = lis.got["/fullperc/tool/status"]
    assert len(poses) == len(covs) == len(stats)
    # frames, stamps = acquisition stamps of good input samples, no NaN, in order
    stamps = [_ns(m.header.stamp) for m in poses]
    assert stamps == sorted(stamps)
    for m in poses + covs:
        assert m.header.frame_id == "base"
    assert set(stamps) <= good_stamps
    for m in poses:
        v = [m.pose.position.x, m.pose.position.y, m.pose.position.z, m.pose.orientation.x,
             m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w]
        assert all(math.isfinite(x) for x in v)
        assert abs(np.linalg.norm(v[3:]) - 1) < 1e-6
    for m in covs:
        assert all(math.isfinite(x) for x in m.pose.covariance) and m.pose.covariance[0] > 0
    # nothing lost: one output per processed item; at most the items before initialization are missing
    assert len(poses) >= 0.8 * (n_good_in - len([r for r in rows if r["kind"] == "ots" and r["body"] == "tool"]))
    # accuracy against the publisher's truth once both sources were seen (cbkf, bias compensated)
    errs = []
    for m in poses:
        t = (_ns(m.header.stamp) - t0) / 1e9
        if 1.5 < t < 2.5:
            p = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
            errs.append(np.linalg.norm(p - mod.truth(t)[:3, 3]))
    assert errs and 1e3 * np.mean(errs) < 0.8
    # status: primary filter, both sources while the OTS sees the target, a bias estimate of the offset
    assert all(s.filter == "cbkf" and s.target == "tool" for s in stats)
    assert any(s.sources == 3 and s.orientation_source == 2 for s in stats)
    late = [s for s in stats if (_ns(s.header.stamp) - t0) / 1e9 > 3.0]
    assert late and all(s.sources == 1 and s.time_since_local > 0.4 for s in late)
    offset_base = mod.T_OMC_BASE[:3, :3].T @ mod.OMC_OFFSET
    b = late[-1].bias
    assert np.linalg.norm(np.array([b.x, b.y, b.z]) - offset_base) < 0.5e-3
    # side-by-side filter
    kf = lis.got["/fullperc/tool/kf/pose"]
    assert kf and all(m.header.frame_id == "base" for m in kf)
    # (arrival processing: side-by-side filters are fused when an item leaves the history -- every item, final --
    # the primary on arrival; they agree on the items whose newest sample came last)
    kf_stamps = [_ns(m.header.stamp) for m in kf]
    assert kf_stamps == sorted(kf_stamps) and set(kf_stamps) <= good_stamps
    assert len(set(kf_stamps) & set(stamps)) >= 0.8 * len(stamps)
    assert all(s.filter == "kf" for s in lis.got["/fullperc/tool/kf/status"])
    # diagnostics explained the bad input
    texts = " | ".join(st.message for arr in lis.diag for st in arr.status if st.name.startswith("fusion_node"))
    assert "non-finite pose" in texts, texts
    assert "non-unit quaternion" in texts, texts
    # arrival processing (default): a sample sent once the node's final estimates had passed its stamp is beyond
    # the 0.2 s history however far the node lagged (synthetic_driver_pub --bad)
    back = [r for r in rows if r.get("bad") == "backwards"]
    assert back and back[0]["node_final_ns"] >= back[0]["t_ns"] + 200_000_000, \
        f"the node's final estimates never passed the backwards sample's stamp: {back}"
    assert "older than the history" in texts, texts
    assert "no OTS (local) sample for" in texts      # the OTS went silent at 2.5 s
    # single bad samples and the usual hops are no alarm (fusion_health)
    from fullperc_common.diagnostics import as_level
    assert not any(as_level(st.level) == 2 for arr in lis.diag for st in arr.status), texts
    assert "hops too often" not in texts and "compensation" not in texts


@pytest.mark.parametrize("arg", ["noise.global_std:=-1.0", "alarm.bias_max:=-0.02", "alarm.hop_max:=0",
                                 "T_rig_ots:=[1.0, 2.0, 3.0]"])
def test_fusion_node_rejects_bad_parameters(procs, arg):
    p = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p", arg], name="bad_params")
    wait_for(lambda: p.poll() is not None, 30, what="fusion_node to exit")
    assert p.returncode != 0
    assert f"'{arg.split(':=')[0]}'" in procs.log(p)


def _statuses(lis, target):
    return [st for arr in list(lis.diag) for st in arr.status if st.name == f"fusion_node: target {target}"]


def test_fusion_node_alarms_on_diagnostics(procs, rclpy_context, python_exe, tmp_path):
    """Issue 14: three OMC targets in one node. ``tool`` jumps by 1 m (while the OTS sees it): WARN naming the
    target and its OMC body; ``probe`` hops once by 3 mm (cameras changing): a hop in FusionStatus, no WARN;
    every OMC sample of ``broken`` is NaN from 1.5 s on: ERROR naming it once that lasted 1 s.

    The node's input queues hold the whole run (``qos_depth`` 5000): with the default 100 (0.8 s of each topic) a
    node that falls behind on a busy machine loses samples, and after such a gap the prediction's covariance has
    grown enough to take the 3 mm step as motion (no hop flag: right for that input, not what this test asks). The
    suspected cause of the one failure seen (two test workers on 2 cores; the figures were not recorded then: the
    message names them now)."""
    from fullperc_common.diagnostics import as_level

    targets = ["tool", "probe", "broken"]
    topics = [f"/fullperc/{t}/status" for t in targets]
    lis = Listener(rclpy_context, topics)
    try:
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                            "-p", "targets:=[tool, probe, broken]", "-p", "init_samples:=20",
                            "-p", "alarm.reject_timeout:=1.0", "-p", "qos_depth:=5000"], name="fusion_node")
        wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 30, what="node's publishers")
        wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions if p.topic_name in topics),
                 30, what="subscriptions matched")
        pub = procs.start([python_exe, str(PUB), "--log", str(tmp_path / "pub.jsonl"), "--duration", "4.0",
                           "--extra-bodies", "probe,broken", "--omc-jump", "tool:2.0:1.0",
                           "--omc-jump", "probe:2.0:0.003", "--omc-nan", "broken:1.5"], name="pub")
        wait_for(lambda: pub.poll() is not None, 60, what="publisher to finish")
        assert pub.returncode == 0, procs.log(pub)

        def raised(target, level, *words):
            return [st for st in _statuses(lis, target)
                    if as_level(st.level) == level and all(w in st.message for w in words)]
        # liveness bounds only: the alarms are held 10 s (problem_hold) after their condition last held
        warn = wait_for(lambda: raised("tool", 1, "target 'tool'", "OMC body 'tool'", "compensation"), 30,
                        what="WARN on the 1 m jump of tool")
        err = wait_for(lambda: raised("broken", 2, "target 'broken'", "OMC body 'broken'", "rejected"), 30,
                       what="ERROR on every sample of broken rejected")
        wait_for(lambda: len(_statuses(lis, "probe")) >= 3, 30, what="diagnostics of probe")
        assert node.poll() is None, procs.log(node)
    finally:
        lis.close()
    bias_mm = float(re.search(r"\|bias\| = ([0-9.]+) mm", warn[0].message).group(1))
    assert abs(bias_mm - 1000) < 10, warn[0].message
    assert "non-finite" in err[0].message
    # the single hop of probe: in FusionStatus, not on /diagnostics
    probe = lis.got["/fullperc/probe/status"]
    last = {kv.key: kv.value for kv in _statuses(lis, "probe")[-1].values}
    assert any(s.hop for s in probe), (
        f"the 3 mm step of probe raised no hop flag: {len(probe)} statuses, stamps "
        f"{[round((_ns(s.header.stamp) - _ns(probe[0].header.stamp)) / 1e9, 3) for s in probe[::50]]}; "
        f"node's last figures: {last}")
    assert sum(s.hop for s in probe) <= 5
    for st in _statuses(lis, "probe"):
        assert "hops too often" not in st.message and "compensation" not in st.message, st.message
        assert as_level(st.level) < 2, st.message
    assert as_level(_statuses(lis, "probe")[-1].level) == 0, _statuses(lis, "probe")[-1].message
    # the jump went into the bias of tool (the issue: 1.0 m), and tool's own samples were never all rejected
    b = lis.got["/fullperc/tool/status"][-1].bias
    assert abs(np.linalg.norm([b.x, b.y, b.z]) - 1.0) < 0.01
    assert not any(as_level(st.level) == 2 for st in _statuses(lis, "tool"))


@pytest.mark.parametrize("processing, max_future", [("arrival", 0.1), ("arrival", 7200.0), ("ordered", 0.1),
                                                     ("ordered", 7200.0)],
                         ids=["guard", "guard-too-wide-restart", "ordered-guard", "ordered-guard-too-wide"])
def test_fusion_node_time_guard_one_sample_an_hour_ahead_does_not_stall(procs, rclpy_context, python_exe, tmp_path,
                                                                         processing, max_future):
    """Issue 16 item 2: one OMC sample stamped an hour ahead of the node clock, then a 2.5 s pause (> idle_flush):
    the sample is rejected and named on /diagnostics, and the node keeps publishing after the pause. With
    ``max_future`` wider than an hour the sample gets in: ordered processing stalls (what the guard prevents; the
    control that shows this test can fail); processing on arrival restarts its timeline after a history's worth of
    samples behind it (named on /diagnostics) and goes on. Input and output queues hold the whole run (``qos_depth``
    5000): a node or listener behind on a busy machine must not lose the 1.5 s after the pause (with the default
    100 the arrival case once got fewer than 50 poses after the pause within 20 s, under two test workers). The
    pause is what the node must see as idle, and a node behind on a busy machine sees it shorter by its lag: with
    0.8 s, a CI run under heavy load (its demo graph lost 1,816 samples) timed out waiting for the stall's late
    samples in the ordered control, possibly because the node, over 0.3 s behind, never idled for idle_flush
    during the pause, so nothing was flushed before the samples after it (and nothing was late); 2.5 s leaves 2 s.
    Not reproduced (the old pause passed pinned to one core beside three busy loops); a failure now names what the
    node had (``why_not``)."""
    topics = ["/fullperc/tool/pose"]
    lis = Listener(rclpy_context, topics)
    try:
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                            "-p", "init_samples:=20", "-p", f"max_future:={max_future}",
                            "-p", f"processing:={processing}", "-p", "qos_depth:=5000"], name="fusion_node")
        wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 30, what="node's publishers")
        wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions if p.topic_name in topics),
                 30, what="subscriptions matched")
        log = tmp_path / "pub.jsonl"
        pub = procs.start([python_exe, str(PUB), "--log", str(log), "--duration", "6.0",
                           "--future", "1.5:3600", "--pause", "2.0:2.5"], name="pub")
        wait_for(lambda: pub.poll() is not None, 60, what="publisher to finish")
        assert pub.returncode == 0, procs.log(pub)
        rows, t0 = _read_log(log)
        bad_ns = next(r["t_ns"] for r in rows if r.get("bad") == "future")

        def after_pause():
            return [m for m in lis.got["/fullperc/tool/pose"] if (_ns(m.header.stamp) - t0) / 1e9 > 3.0]

        def why_not():
            sts = _statuses(lis, "tool")
            # every distinct problem the node named (the restart's message gives the stamp it restarted at)
            named = sorted({m for st in sts for m in st.message.split("; ") if "no OMC" not in m})
            return (f"{len(after_pause())} fused poses after the pause (of {len(lis.got['/fullperc/tool/pose'])}); "
                    f"the node's last /diagnostics: "
                    f"{(sts[-1].message, {kv.key: kv.value for kv in sts[-1].values}) if sts else None}; "
                    f"every message it had: {named}; t0 {t0} ns, bad stamp {bad_ns} ns; node log tail: "
                    f"{procs.log(node)[-2000:]}")

        def poses_after_pause():
            wait_for(lambda: len(after_pause()) > 50, 20, what="fused poses after the pause", detail=why_not)
        if max_future > 3600 and processing == "arrival":
            poses_after_pause()
            wait_for(lambda: [st for st in _statuses(lis, "tool") if "timeline_restart" in st.message], 20,
                     what="the timeline restart on /diagnostics", detail=why_not)
            assert bad_ns in [_ns(m.header.stamp) for m in lis.got["/fullperc/tool/pose"]], "it was fused"
            return
        if max_future > 3600:
            # the late samples are named on /diagnostics; by then the publisher is done and the node has flushed
            wait_for(lambda: [st for st in _statuses(lis, "tool") if "late x" in st.message], 20,
                     what="late samples on /diagnostics", detail=why_not)
            # nothing after the pause but the hour-ahead sample itself, published by the idle flush
            assert [_ns(m.header.stamp) for m in after_pause()] == [bad_ns]
            return
        # liveness bounds only
        poses_after_pause()
        named = wait_for(lambda: [st for st in _statuses(lis, "tool") if "rejected_future" in st.message], 20,
                         what="the rejected stamp on /diagnostics", detail=why_not)
        assert node.poll() is None, procs.log(node)
    finally:
        lis.close()
    # The node names the stamp, how far ahead it is and its own clock then. The publisher stamped it 3600 s after
    # its clock at publishing; the node's clock reads later by the delivery delay (0.9 s seen with a second test
    # worker beside it), so 'ahead' is just under 3600 s and is the difference of the two stamps it names.
    m = re.search(rf"OMC body 'tool': stamp {bad_ns} ns is (\d+\.\d+) s ahead of the clock \((\d+) ns;",
                  named[0].message)
    assert m, named[0].message
    ahead, clock_ns = float(m[1]), int(m[2])
    assert ahead == pytest.approx((bad_ns - clock_ns) / 1e9, abs=1e-3), named[0].message
    assert 3600.0 - 30.0 < ahead <= 3600.0 + 1e-3, named[0].message
    stamps = [_ns(m.header.stamp) for m in lis.got["/fullperc/tool/pose"]]
    assert stamps == sorted(stamps) and max(stamps) < bad_ns
