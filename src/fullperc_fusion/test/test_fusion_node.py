"""fusion_node across processes: synthetic driver topics from one process (synthetic_driver_pub.py, or this one for
the time guard), the installed fusion_node in another, and this test subscribing to its outputs over DDS. The
module's scenarios run side by side, each in a ROS domain of its own (``scenarios``)."""

from __future__ import annotations

import math
import re
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import (
    RosSession,
    SideBySide,
    installed_exe,
    load_by_path,
    selected_cases,
    wait_for,
    wait_for_first_line,
)

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
pytestmark = pytest.mark.system


def _load_pub_module():
    return load_by_path(PUB, "synthetic_driver_pub")


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
        types = {"pose": PoseStamped, "pose_cov": PoseWithCovarianceStamped, "status": FusionStatus,
                 "final": PoseStamped}
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


def _ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _start_pub(procs, tmp: Path, *args: str):
    """synthetic_driver_pub, started once this test's listener is matched with the node's outputs."""
    return procs.start([sys.executable, str(PUB), "--log", str(tmp / "pub.jsonl"), *args], name="pub")


def _published(procs, pub, tmp: Path):
    """The publisher's rows and t0 once it has written its last line (the meta row; liveness bound only). It then
    keeps its publishers a second longer for reliable delivery, beside the test's own waits: the test checks its exit
    status at the end (:func:`_pub_exited`)."""
    log, mod = tmp / "pub.jsonl", _load_pub_module()
    wait_for(lambda: pub.poll() is not None or mod.log_complete(log), 90, what="the publisher's data",
             detail=lambda: procs.log(pub)[-2000:])
    assert pub.poll() in (None, 0), procs.log(pub)
    return mod.read_log(log)


def _pub_exited(procs, pub) -> None:
    wait_for(lambda: pub.poll() is not None, 30, what="the publisher to exit")
    assert pub.returncode == 0, procs.log(pub)


def _end_to_end(tmp: Path) -> dict:
    topics = ["/fullperc/tool/pose", "/fullperc/tool/pose_cov", "/fullperc/tool/status",
              "/fullperc/tool/kf/pose", "/fullperc/tool/kf/status", "/fullperc/tool/final"]
    with RosSession(tmp) as s:
        procs = s.procs
        # qos_depth 1000: every input queue holds the whole 4 s run, so a node stalled on a busy machine still gets
        # each bad sample this test expects named (the default 100 is 0.8 s of one 120 Hz topic; the stand-in
        # publishes no TrackingQuality, so a sample lost from a full queue would go unnoticed)
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                            "-p", "filters:=[kf]", "-p", "init_samples:=20", "-p", "qos_depth:=1000"],
                           name="fusion_node")
        wait_for_first_line(procs, node)   # the listener once the node is up: matched at once (wait_for_first_line)
        lis = Listener(s.context, topics)
        try:
            # start the data only once this listener is matched with every output of the node
            wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 60, what="node's publishers")
            wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions
                                 if p.topic_name in topics), 30, what="subscriptions matched")
            pub = _start_pub(procs, tmp, "--bad", "--duration", "4.0")
            rows, t0 = _published(procs, pub, tmp)   # liveness bounds only: discovery + 4 s of data
            # every item is final after idle_flush (its outputs, pose, pose_cov, status and kf, were published before
            # its final estimate): wait until the newest good tool sample is final and every output is in
            last_good = max(r["t_ns"] for r in rows if r["body"] == "tool" and "bad" not in r)
            got = lis.got

            def flushed():
                return (got["/fullperc/tool/final"] and _ns(got["/fullperc/tool/final"][-1].header.stamp) >= last_good
                        and got["/fullperc/tool/kf/pose"]
                        and _ns(got["/fullperc/tool/kf/pose"][-1].header.stamp) >= last_good
                        and len(got["/fullperc/tool/pose"]) == len(got["/fullperc/tool/pose_cov"])
                        == len(got["/fullperc/tool/status"]) and len(got["/fullperc/tool/kf/pose"])
                        == len(got["/fullperc/tool/kf/status"]))
            wait_for(flushed, 60, what="every output, the newest good sample final",
                     detail=lambda: ({t: len(v) for t, v in got.items()}, last_good, procs.log(node)[-2000:]))

            def texts():
                return " | ".join(st.message for arr in list(lis.diag) for st in arr.status
                                  if st.name.startswith("fusion_node"))
            # the backwards sample came last (after the node's final estimates passed it): /diagnostics names it
            # within a diagnostics period or two
            wait_for(lambda: "older than the history" in texts(), 30, what="the backwards sample on /diagnostics",
                     detail=texts)
            resp = lis.call_initialize()
            alive = node.poll() is None
            _pub_exited(procs, pub)
            return {"lis": lis, "rows": rows, "t0": t0, "resp": resp, "alive": alive, "log": procs.log(node)}
        finally:
            lis.close()


def test_fusion_node_end_to_end(scenarios, request):
    r = scenarios.result(request.node.name)
    lis, rows, t0, resp = r["lis"], r["rows"], r["t0"], r["resp"]
    assert resp.success and "re-estimating" in resp.message
    assert r["alive"], r["log"]
    n_good_in = sum(1 for r in rows if r["body"] == "tool" and "bad" not in r)
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


BAD_PARAMS = ["noise.global_std:=-1.0", "alarm.bias_max:=-0.02", "alarm.hop_max:=0", "T_rig_ots:=[1.0, 2.0, 3.0]"]
# The case given to the installed executable (a list on the command line, parsed by rcl): exit status and the line
# naming the parameter. The others are given to FusionNode in this process as parameter overrides of the types rcl
# parses them to (YAML): the node's own declarations and checks without three more process starts (~1.2 s of CPU
# each, beside this module's other scenarios). test_fusion_config.py checks each value against the table and that a
# getter (the node's path) and a params file map alike; test_node_lifecycle.py the exit of a bad value of each node.
BAD_PARAM_IN_A_PROCESS = "T_rig_ots:=[1.0, 2.0, 3.0]"


def _bad_parameter(tmp: Path, arg: str) -> tuple[int | None, str]:
    """(exit status, log) of fusion_node started with ``-p arg`` (:data:`BAD_PARAM_IN_A_PROCESS`); the other cases in
    this process: (None, the message of what the node's constructor raised, or "constructed" if it raised nothing)."""
    with RosSession(tmp) as s:
        if arg != BAD_PARAM_IN_A_PROCESS:
            import yaml
            from rclpy.exceptions import ParameterException
            from rclpy.parameter import Parameter

            from fullperc_common.params import ParameterError, parameter_exception_message
            from fullperc_fusion.fusion_node import FusionNode

            name, text = arg.split(":=", 1)
            try:
                node = FusionNode(context=s.context, parameter_overrides=[Parameter(name, value=yaml.safe_load(text))])
            except ParameterError as e:
                return None, str(e)
            except ParameterException as e:
                return None, parameter_exception_message(e)
            node.close()
            node.destroy_node()
            return None, "constructed"
        p = s.procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p", arg],
                          name="bad_params")
        wait_for(lambda: p.poll() is not None, 60, what="fusion_node to exit")
        return p.returncode, s.procs.log(p)


@pytest.mark.parametrize("case", BAD_PARAMS)
def test_fusion_node_rejects_bad_parameters(scenarios, request, tmp_path, case):
    if case == BAD_PARAM_IN_A_PROCESS:
        returncode, log = scenarios.result(request.node.name)
        assert returncode == 2 and "Traceback" not in log, log
    else:   # in this test's thread (the main one: the module's scenarios have imported what they need by now)
        _, log = _bad_parameter(tmp_path, case)
    assert f"'{case.split(':=')[0]}'" in log, log


def _statuses(lis, target):
    return [st for arr in list(lis.diag) for st in arr.status if st.name == f"fusion_node: target {target}"]


def _last_stamp(st) -> int:
    """``last_stamp_ns`` of a target's status: the stamp of the newest sample fused when it was made (0: none)."""
    return int({kv.key: kv.value for kv in st.values}.get("last_stamp_ns", 0) or 0)


def _alarms(tmp: Path) -> dict:
    from fullperc_common.diagnostics import as_level

    targets = ["tool", "probe", "broken"]
    topics = [f"/fullperc/{t}/status" for t in targets]
    with RosSession(tmp) as s:
        procs = s.procs
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                            "-p", "targets:=[tool, probe, broken]", "-p", "init_samples:=20",
                            "-p", "alarm.reject_timeout:=1.0", "-p", "qos_depth:=5000"], name="fusion_node")
        wait_for_first_line(procs, node)
        lis = Listener(s.context, topics)
        try:
            wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 60, what="node's publishers")
            wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions
                                 if p.topic_name in topics), 30, what="subscriptions matched")
            pub = _start_pub(procs, tmp, "--duration", "4.0", "--extra-bodies", "probe,broken", "--omc-jump",
                             "tool:2.0:1.0", "--omc-jump", "probe:2.0:0.003", "--omc-nan", "broken:1.5")
            rows, _ = _published(procs, pub, tmp)

            def raised(target, level, *words):
                return [st for st in _statuses(lis, target)
                        if as_level(st.level) == level and all(w in st.message for w in words)]
            # liveness bounds only: the alarms are held 10 s (problem_hold) after their condition last held
            def last_of(target):   # on a timeout: what the node said of the target last
                return lambda: [(st.message, {kv.key: kv.value for kv in st.values}) for st in
                                _statuses(lis, target)[-2:]]
            warn = wait_for(lambda: raised("tool", 1, "target 'tool'", "OMC body 'tool'", "compensation"), 30,
                            what="WARN on the 1 m jump of tool", detail=last_of("tool"))
            err = wait_for(lambda: raised("broken", 2, "target 'broken'", "OMC body 'broken'", "rejected"), 30,
                           what="ERROR on every sample of broken rejected", detail=last_of("broken"))
            # diagnostics of probe once the node has fused all of probe's samples (``last_stamp_ns``)
            last_probe = max(r["t_ns"] for r in rows if r["body"] == "probe")
            wait_for(lambda: [st for st in _statuses(lis, "probe") if _last_stamp(st) >= last_probe], 60,
                     what="diagnostics of probe after all its samples",
                     detail=lambda: [st.message for st in _statuses(lis, "probe")[-3:]])
            # and tool's FusionStatus of the newest sample those /diagnostics say it fused (the test reads the last
            # status's bias): the statuses go on a topic of their own, so /diagnostics can arrive before them
            newest = max(_last_stamp(st) for st in _statuses(lis, "tool"))
            wait_for(lambda: any(_ns(s.header.stamp) >= newest for s in list(lis.got["/fullperc/tool/status"])), 30,
                     what="tool's FusionStatus of its newest fused sample")
            hop_ns = min(r["t_ns"] for r in rows if r["body"] == "probe" and "jump" in r)
            _pub_exited(procs, pub)
            return {"lis": lis, "hop_ns": hop_ns, "warn": warn, "err": err, "alive": node.poll() is None,
                    "log": procs.log(node)}
        finally:
            lis.close()


def test_fusion_node_alarms_on_diagnostics(scenarios, request):
    """Issue 14: three OMC targets in one node. ``tool`` jumps by 1 m (while the OTS sees it): WARN naming the
    target and its OMC body; ``probe`` hops once by 3 mm (cameras changing): a hop in FusionStatus, no WARN;
    every OMC sample of ``broken`` is NaN from 1.5 s on: ERROR naming it once that lasted 1 s.

    The node's input queues hold the whole run (``qos_depth`` 5000): with the default 100 (0.8 s of each topic) a
    node that falls behind on a busy machine loses samples, and after such a gap the prediction's covariance has
    grown enough to take the 3 mm step as motion (no hop flag: right for that input, not what this test asks). The
    suspected cause of the one failure seen (two test workers on 2 cores; the figures were not recorded then: the
    message names them now)."""
    from fullperc_common.diagnostics import as_level

    r = scenarios.result(request.node.name)
    lis, warn, err = r["lis"], r["warn"], r["err"]
    assert r["alive"], r["log"]
    # the step is first rejected as implausible for (1 m - plausibility.jump) / max_speed ~ 0.5 s (rejected_jump),
    # then taken (the bound has grown past it): the bias the last WARN names is the whole jump
    biases = [(float(m.group(1)), w.message) for w in warn if (m := re.search(r"\|bias\| = ([0-9.]+) mm", w.message))]
    assert abs(biases[-1][0] - 1000) < 10, biases[-1][1]
    assert any("rejected_jump" in w.message for w in warn), "the step was not first taken for an injected sample"
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
    # and nothing about probe's data held it out of OK after the hop: a status after it is OK, or WARN only for what
    # is not probe's doing -- its stream ended (no OMC sample for over stale_timeout, soon after the last one) or
    # the machine (overload: the node behind on a busy machine). Not "the last status is OK": that raced the end of
    # the stream against stale_timeout, and lost to any lag.
    not_probes = re.compile(r"no OTS \(local\) sample[^;]*|no OMC \(global\) sample for[^;]*|overload: .*? samples "
                            r"waiting\)")
    after_hop = [st for st in _statuses(lis, "probe") if _last_stamp(st) > r["hop_ns"]]
    assert after_hop, [st.message for st in _statuses(lis, "probe")]
    for st in after_hop:
        why = [m for m in not_probes.sub("", st.message).split("; ") if m.strip()]
        assert as_level(st.level) == 0 or not why, st.message
    # the jump went into the bias of tool (the issue: 1.0 m), and tool's own samples were never all rejected
    b = lis.got["/fullperc/tool/status"][-1].bias
    assert abs(np.linalg.norm([b.x, b.y, b.z]) - 1.0) < 0.01
    assert not any(as_level(st.level) == 2 for st in _statuses(lis, "tool"))


class ScenePublisher:
    """synthetic_driver_pub's scene (geometry, motion, noise) published from this process in real time, phase by
    phase: the time-guard test starts its second phase only once the node has flushed the first, so the pause the
    node sees is a condition, not a length of time. One clock across the phases: frame k is stamped t0 + k/120 s."""

    TOPICS = ("/omc/base/pose", "/omc/ots_rig/pose", "/omc/tool/pose", "/ots/base/pose", "/ots/tool/pose")

    def __init__(self, ctx) -> None:
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.mod = _load_pub_module()
        self.node = rclpy.create_node("time_guard_drivers", context=ctx)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs = {t: self.node.create_publisher(PoseStamped, t, qos) for t in self.TOPICS}
        self.rng = np.random.default_rng(0)
        self.t0_ns: int | None = None
        self.t0 = 0.0
        self.bad_ns: int | None = None

    def matched(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.pubs.values())

    def _pub(self, topic, ns, frame, p, q) -> None:
        self.pubs[topic].publish(self.mod.msg(ns, frame, p, q))

    def run(self, seconds: float, ots_from: float | None = None, future: tuple[float, float] | None = None):
        """Publish ``seconds`` of frames at 120 Hz from now: OMC base, rig and tool; OTS base every other frame and,
        from ``ots_from`` s on, the OTS tool (3 ms later); ``future`` (at, ahead): at ``at`` s one more OMC tool pose
        stamped ``ahead`` s later (``bad_ns``). Returns the OMC tool stamps published, the future one apart."""
        from fullperc_common.transforms import T_to_pq, inv_T

        m = self.mod
        if self.t0_ns is None:
            self.t0_ns, self.t0 = time.time_ns(), time.monotonic()
        k = math.ceil((time.monotonic() - self.t0) * 120)
        end = k / 120.0 + seconds
        T_ots_base = inv_T(m.T_OMC_OTS) @ m.T_OMC_BASE
        stamps = []
        while (t := k / 120.0) <= end:
            time.sleep(max(0.0, self.t0 + t - time.monotonic()))
            ns = self.t0_ns + round(t * 1e9)
            p0, q = T_to_pq(m.T_OMC_BASE @ m.truth(t))
            p = p0 + m.OMC_OFFSET + self.rng.normal(0, 2e-4, 3)
            self._pub("/omc/base/pose", ns, "omc", *T_to_pq(m.T_OMC_BASE))
            self._pub("/omc/ots_rig/pose", ns, "omc", *T_to_pq(m.T_OMC_OTS))
            self._pub("/omc/tool/pose", ns, "omc", p, q)
            stamps.append(ns)
            if future is not None and t >= future[0] and self.bad_ns is None:
                self.bad_ns = ns + round(future[1] * 1e9)
                self._pub("/omc/tool/pose", self.bad_ns, "omc", p, q)
            if k % 2 == 0:
                self._pub("/ots/base/pose", ns + 3_000_000, "ots", *T_to_pq(T_ots_base))
                if ots_from is not None and t >= ots_from:
                    pl, ql = T_to_pq(T_ots_base @ m.truth(t + 0.003))
                    self._pub("/ots/tool/pose", ns + 3_000_000, "ots", pl + self.rng.normal(0, 1e-4, 3), ql)
            k += 1
        return stamps


# case id -> (processing, max_future [s])
TIME_GUARD = {"guard": ("arrival", 0.1), "guard-too-wide-restart": ("arrival", 7200.0),
              "ordered-guard": ("ordered", 0.1), "ordered-guard-too-wide": ("ordered", 7200.0)}


def _time_guard_scenario(tmp: Path, processing: str, max_future: float) -> dict:
    """One case of the time-guard test (below), in a domain of its own; returns what the checks need."""
    pose_t, final_t = "/fullperc/tool/pose", "/fullperc/tool/final"
    with RosSession(tmp) as s:
        # The drivers' writers before the node starts, this listener's readers once it is up: both are then matched at
        # once (a reader that exists before a new participant appears often waits ~3 s: wait_for_first_line).
        scene = ScenePublisher(s.context)
        node = s.procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args",
                              "-p", "init_samples:=20", "-p", f"max_future:={max_future}",
                              "-p", f"processing:={processing}", "-p", "qos_depth:=5000"], name="fusion_node")
        wait_for_first_line(s.procs, node)
        lis = Listener(s.context, [pose_t, final_t] if processing == "arrival" else [pose_t])
        r: dict = {}

        def stamps(topic):
            return [_ns(m.header.stamp) for m in list(lis.got[topic])]

        def after_pause():
            return [t for t in stamps(pose_t) if t >= r["t_b_ns"]]

        def why_not():
            sts = _statuses(lis, "tool")
            # every distinct problem the node named (the restart's message gives the stamp it restarted at)
            named = sorted({m for st in sts for m in st.message.split("; ") if "no OMC" not in m})
            return (f"{len(after_pause()) if 't_b_ns' in r else '-'} fused poses after the pause (of "
                    f"{len(lis.got[pose_t])}); the node's last /diagnostics: "
                    f"{(sts[-1].message, {kv.key: kv.value for kv in sts[-1].values}) if sts else None}; "
                    f"every message it had: {named}; t0 {scene.t0_ns} ns, bad stamp {scene.bad_ns} ns, pause ended "
                    f"at {r.get('t_b_ns')} ns; node log tail: {s.procs.log(node)[-2000:]}")
        try:
            topics = list(lis.got)
            wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 60, what="node's publishers")
            wait_for(lambda: all(p.get_publisher_count() > 0 for p in lis.node.subscriptions
                                 if p.topic_name in topics), 30, what="subscriptions matched")
            wait_for(scene.matched, 30, what="the node's subscriptions")
            a = scene.run(1.5, ots_from=0.8, future=(1.0, 3600.0))
            # The pause: nothing more is sent until the node, idle for idle_flush, has flushed the first phase -- its
            # last sample (arrival: final; ordered: published), or with the wide guard ordered, the hour-ahead one.
            flushed = final_t if processing == "arrival" else pose_t
            until = scene.bad_ns if (processing == "ordered" and max_future > 3600) else a[-1]
            wait_for(lambda: any(t >= until for t in stamps(flushed)), 60, what=f"the idle flush on {flushed}",
                     detail=why_not)
            b = scene.run(1.5)
            r["t_b_ns"] = b[0]

            def poses_after_pause():
                wait_for(lambda: len(after_pause()) > 50, 30, what="fused poses after the pause", detail=why_not)
            if max_future > 3600 and processing == "arrival":
                poses_after_pause()
                wait_for(lambda: [st for st in _statuses(lis, "tool") if "timeline_restart" in st.message], 30,
                         what="the timeline restart on /diagnostics", detail=why_not)
            elif max_future > 3600:
                # the late samples are named on /diagnostics
                wait_for(lambda: [st for st in _statuses(lis, "tool") if "late x" in st.message], 30,
                         what="late samples on /diagnostics", detail=why_not)
            else:   # liveness bounds only
                poses_after_pause()
                r["named"] = wait_for(lambda: [st for st in _statuses(lis, "tool")
                                               if "rejected_future" in st.message], 30,
                                      what="the rejected stamp on /diagnostics", detail=why_not)
            r["alive"] = node.poll() is None
            r["log"] = s.procs.log(node)
        finally:
            lis.close()
            scene.node.destroy_node()
        r.update(bad_ns=scene.bad_ns, poses=stamps(pose_t), after_pause=after_pause())
        return r


@pytest.fixture(scope="module")
def scenarios(request, tmp_path_factory):
    """Every scenario of this module's selected tests, started at once, side by side (each in its own domain; most
    of a scenario is waiting: for a node to start, for data sent in real time); each test checks its own."""
    def job(fn, name, *args):
        tmp = tmp_path_factory.mktemp(re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:30])   # here: mktemp is not thread-safe
        return lambda: fn(tmp, *args)
    guard = "test_fusion_node_time_guard_one_sample_an_hour_ahead_does_not_stall"
    bad = "test_fusion_node_rejects_bad_parameters"
    jobs = {"test_fusion_node_end_to_end": job(_end_to_end, "end_to_end"),
            "test_fusion_node_alarms_on_diagnostics": job(_alarms, "alarms"),
            **{f"{guard}[{cid}]": job(_time_guard_scenario, cid, *TIME_GUARD[cid]) for cid in TIME_GUARD},
            f"{bad}[{BAD_PARAM_IN_A_PROCESS}]": job(_bad_parameter, "bad_param", BAD_PARAM_IN_A_PROCESS)}
    # rclpy imported here, once, before the threads: threads importing rclpy's modules at once can get one of them
    # partially initialised (they import each other)
    import rclpy.exceptions  # noqa: F401
    import rclpy.executors  # noqa: F401
    import rclpy.node  # noqa: F401
    import rclpy.parameter  # noqa: F401
    sbs = SideBySide(jobs).start(selected_cases(request, jobs))
    yield sbs
    sbs.join()


@pytest.mark.parametrize("case", list(TIME_GUARD))
def test_fusion_node_time_guard_one_sample_an_hour_ahead_does_not_stall(scenarios, request, case):
    """Issue 16 item 2: one OMC sample stamped an hour ahead of the node clock, then a pause (> idle_flush): the
    sample is rejected and named on /diagnostics, and the node keeps publishing after the pause. With ``max_future``
    wider than an hour the sample gets in: ordered processing stalls (what the guard prevents; the control that shows
    this test can fail); processing on arrival restarts its timeline after a history's worth of samples behind it
    (named on /diagnostics) and goes on. Input and output queues hold the whole run (``qos_depth`` 5000): a node or
    listener behind on a busy machine must not lose the samples after the pause.

    The pause is a condition, not a length of time: the second phase starts once the node has flushed the first (its
    last sample final or published; in the ordered control, the hour-ahead sample published by the flush). A fixed
    pause is shortened by the node's lag (a node 0.3 s behind sees a 0.8 s pause as 0.5 s): a CI run under heavy load
    timed out waiting for the control's late samples, most likely because the node never idled for idle_flush during
    the pause, so nothing was flushed before the samples after it. A failure names what the node had (``why_not``)."""
    r = scenarios.result(request.node.name)
    processing, max_future = TIME_GUARD[case]
    bad_ns = r["bad_ns"]
    assert r["alive"], r["log"]
    if max_future > 3600 and processing == "arrival":
        assert bad_ns in r["poses"], "it was fused"
        return
    if max_future > 3600:
        # nothing after the pause but the hour-ahead sample itself, published by the idle flush
        assert r["after_pause"] == [bad_ns]
        return
    # The node names the stamp, how far ahead it is and its own clock then. The sample was stamped 3600 s after this
    # process's clock at publishing; the node's clock reads later by the delivery delay (0.9 s seen with a second test
    # worker beside it), so 'ahead' is just under 3600 s and is the difference of the two stamps it names.
    named = r["named"]
    m = re.search(rf"OMC body 'tool': stamp {bad_ns} ns is (\d+\.\d+) s ahead of the clock \((\d+) ns;",
                  named[0].message)
    assert m, named[0].message
    ahead, clock_ns = float(m[1]), int(m[2])
    assert ahead == pytest.approx((bad_ns - clock_ns) / 1e9, abs=1e-3), named[0].message
    assert 3600.0 - 30.0 < ahead <= 3600.0 + 1e-3, named[0].message
    stamps = r["poses"]
    assert stamps == sorted(stamps) and max(stamps) < bad_ns
