"""fusion_node's ROS conventions across processes (issue 39): namespaces and frames, QoS that fits its drivers, and
run-time parameters. The installed node, synthetic drivers (synthetic_driver_pub.py) and this process's listener;
the scenarios run side by side, each in a DDS domain of its own (``scenarios``).

* two complete graphs in /or1 and /or2 on one domain, each fed its own poses, fuse only their own inputs (no
  cross-talk), in frames of their own on the shared /tf, with the velocity output of the primary filter;
* a best-effort driver is fused with the shipped fusion.yaml (``qos_reliability: auto`` remakes its inputs best
  effort, a WARN each); a ``qos_overrides`` parameter makes one subscription
  reliable (seen from another node through discovery) and a best-effort publisher on it is a WARN naming topic and
  policy;
* a run-time set of ``targets`` is refused as read-only, an invalid alarm threshold is refused naming the check, a
  valid one takes effect on /diagnostics.
"""

from __future__ import annotations

import itertools
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import (
    RosSession,
    SideBySide,
    SpunNode,
    installed_exe,
    load_by_path,
    selected_cases,
    wait_for,
    wait_for_first_line,
)

HERE = Path(__file__).resolve().parent
PUB = HERE / "synthetic_driver_pub.py"
PUBMOD = load_by_path(PUB, "synthetic_driver_pub")   # its log format (read_log, log_complete) and its scene
pytestmark = pytest.mark.system
SHIFT = 0.2   # [m] /or2's target runs this far from /or1's along base x
GLOBAL_TOPICS = {"/tf", "/tf_static", "/diagnostics", "/rosout", "/parameter_events"}
_IDS = itertools.count()


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class Listener(SpunNode):
    """Every message of ``topics`` (name -> type; reliable, deep) and /diagnostics, kept in arrival order."""

    def __init__(self, ctx, topics: dict[str, type]) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_common.tf import static_listener_qos

        super().__init__(ctx, f"ros_conventions_listener_{next(_IDS)}")   # one rosout publisher each
        self.got: dict[str, list] = {t: [] for t in [*topics, "/diagnostics"]}
        deep = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        for t, typ in {**topics, "/diagnostics": DiagnosticArray}.items():
            qos = static_listener_qos() if t == "/tf_static" else deep   # depth 100: both nodes' latched links
            self.node.create_subscription(typ, t, self.got[t].append, qos)
        self.start()

    def diag(self, name: str = "fusion_node: target tool") -> list:
        return [st for arr in list(self.got["/diagnostics"]) for st in arr.status if st.name == name]

    def call(self, srv_type, name: str, request, timeout: float = 20.0):
        cli = self.node.create_client(srv_type, name)
        wait_for(cli.service_is_ready, timeout, what=f"service {name}")
        fut = cli.call_async(request)
        wait_for(fut.done, timeout, what=f"answer of {name}")
        return fut.result()


def _start_node(procs, name: str, *args: str):
    p = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-p", "init_samples:=20",
                     "-p", "qos_depth:=5000", *args], name=name)
    wait_for_first_line(procs, p)
    return p


def _start_pub(procs, tmp: Path, name: str, *args: str):
    return procs.start([sys.executable, str(PUB), "--log", str(tmp / f"{name}.jsonl"), *args], name=name)


def _done(procs, pub, tmp: Path, name: str) -> None:
    """The publisher has written its last line (liveness bound only) and exits cleanly."""
    log = tmp / f"{name}.jsonl"
    wait_for(lambda: pub.poll() is not None or PUBMOD.log_complete(log), 90, what=f"{name}'s data",
             detail=lambda: procs.log(pub)[-2000:])
    wait_for(lambda: pub.poll() is not None, 30, what=f"{name} to exit")
    assert pub.returncode == 0, procs.log(pub)


def _t0(tmp: Path, name: str) -> int:
    return PUBMOD.read_log(tmp / f"{name}.jsonl")[1]


# ------------------------------------------------------------------------------------------------ namespaces
STATIC_LINKS = {("or1_omc", "or1_base"), ("or1_base", "or1_ots"), ("or2_omc", "or2_base"), ("or2_base", "or2_ots")}


def _pairs(msgs: list) -> set[tuple[str, str]]:
    """(parent, child) of every transform of the TFMessages ``msgs``."""
    return {(tf.header.frame_id, tf.child_frame_id) for m in list(msgs) for tf in m.transforms}


def _namespaces(tmp: Path) -> dict:
    from geometry_msgs.msg import PoseStamped, TwistWithCovarianceStamped

    from tf2_msgs.msg import TFMessage

    with RosSession(tmp) as s:
        nodes = {ns: _start_node(s.procs, f"fusion_{ns}", "-r", f"__ns:=/{ns}", "-p", "publish_velocity:=true",
                                 *(x for f in ("base", "omc", "ots") for x in ("-p", f"frames.{f}:={ns}_{f}")),
                                 "-p", f"tool.frame:={ns}_tool") for ns in ("or1", "or2")}
        topics = {f"/{ns}/fullperc/tool/{w}": typ for ns in nodes
                  for w, typ in (("pose", PoseStamped), ("velocity", TwistWithCovarianceStamped))}
        lis = Listener(s.context, {**topics, "/tf": TFMessage, "/tf_static": TFMessage})
        try:
            wait_for(lambda: all(lis.node.count_publishers(t) > 0 for t in topics), 60, what="the nodes' publishers")
            wait_for(lambda: all(sub.get_publisher_count() > 0 for sub in lis.node.subscriptions
                                 if sub.topic_name in topics), 30, what="subscriptions matched")
            pubs = {ns: _start_pub(s.procs, tmp, f"pub_{ns}", "--ns", f"/{ns}", "--duration", "4.0",
                                   "--shift", str(SHIFT if ns == "or2" else 0.0)) for ns in nodes}
            for ns, p in pubs.items():
                _done(s.procs, p, tmp, f"pub_{ns}")
            wait_for(lambda: all(len(lis.got[f"/{ns}/fullperc/tool/pose"]) > 200 for ns in nodes), 30,
                     what="fused poses of both graphs",
                     detail=lambda: {t: len(v) for t, v in lis.got.items()})
            # a node behind its inputs publishes a static link when its calibration completes, which can be after
            # these poses reached us (CI: or2's base->ots link missing when the poses were in)
            wait_for(lambda: STATIC_LINKS <= _pairs(lis.got["/tf_static"]), 30, what="both graphs' static links",
                     detail=lambda: _pairs(lis.got["/tf_static"]))
            graph = sorted(t for t, _ in lis.node.get_topic_names_and_types())
            return {"got": {k: list(v) for k, v in lis.got.items()}, "graph": graph,
                    "t0": {ns: _t0(tmp, f"pub_{ns}") for ns in nodes},
                    "alive": {ns: p.poll() is None for ns, p in nodes.items()},
                    "logs": {ns: s.procs.log(p)[-3000:] for ns, p in nodes.items()}}
        finally:
            lis.close()


def test_two_namespaces_fuse_only_their_own_inputs(scenarios, request):
    r = scenarios.result(request.node.name)
    assert all(r["alive"].values()), r["logs"]
    got = r["got"]
    # every topic of the graph is under /or1 or /or2, but the global ones
    assert not [t for t in r["graph"] if not t.startswith(("/or1/", "/or2/")) and t not in GLOBAL_TOPICS], r["graph"]
    for ns, shift, other in (("or1", 0.0, SHIFT), ("or2", SHIFT, 0.0)):
        poses = got[f"/{ns}/fullperc/tool/pose"]
        assert poses and all(m.header.frame_id == f"{ns}_base" for m in poses)
        own, others = [], []
        for m in poses:
            t = (_ns(m.header.stamp) - r["t0"][ns]) / 1e9
            p = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
            T = PUBMOD.truth(t)[:3, 3]
            own.append(np.linalg.norm(p - T - [shift, 0, 0]))
            others.append(np.linalg.norm(p - T - [other, 0, 0]))
        # its own target within the OMC's offset (4 mm) and noise, never near the other graph's (0.2 m away)
        assert max(own) < 0.01 and min(others) > SHIFT - 0.01, (ns, max(own), min(others))
        # velocity of the primary filter: the truth's derivative (2.5 cm/s at most) once both sources were seen
        vels = [m for m in got[f"/{ns}/fullperc/tool/velocity"] if (_ns(m.header.stamp) - r["t0"][ns]) / 1e9 > 1.5]
        assert vels and all(m.header.frame_id == f"{ns}_base" for m in vels)
        err, z = [], []
        for m in vels:
            t = (_ns(m.header.stamp) - r["t0"][ns]) / 1e9
            v_true = (PUBMOD.truth(t + 1e-3)[:3, 3] - PUBMOD.truth(t - 1e-3)[:3, 3]) / 2e-3
            v = m.twist.twist.linear
            err.append(np.array([v.x, v.y, v.z]) - v_true)
            C = np.array(m.twist.covariance).reshape(6, 6)
            assert np.all(np.diag(C)[:3] > 0) and np.all(np.diag(C)[3:] >= 1e6)
            z.append(np.abs(err[-1]) / np.sqrt(np.diag(C)[:3]))
        # unbiased (the white-acceleration model's velocity is noisy per sample: ~1 cm/s at 120 Hz of 0.2 mm noise),
        # and within its own covariance
        assert np.all(np.abs(np.mean(err, axis=0)) < 5e-3) and np.mean(z) < 4.0, (ns, np.mean(err, axis=0), np.mean(z))
    # the shared /tf: each graph's own frames, nothing in the default ones
    dyn, static = _pairs(got["/tf"]), _pairs(got["/tf_static"])
    assert dyn == {("or1_base", "or1_tool"), ("or2_base", "or2_tool")}, dyn
    assert STATIC_LINKS <= static and not any("base" in (p, c) for p, c in static), static


# ------------------------------------------------------------------------------------------------------- QoS
def _best_effort_defaults(tmp: Path) -> dict:
    """The shipped fusion.yaml, a best-effort driver: fused."""
    from geometry_msgs.msg import PoseStamped

    shipped = Path(installed_exe("fullperc_fusion", "fusion_node")).parents[2] / "share" / "fullperc_fusion" / \
        "config" / "fusion.yaml"
    with RosSession(tmp) as s:
        node = _start_node(s.procs, "fusion_node", "--params-file", str(shipped))
        lis = Listener(s.context, {"/fullperc/tool/pose": PoseStamped})
        try:
            wait_for(lambda: lis.node.get_subscriptions_info_by_topic("/omc/tool/pose"), 30, what="the node's input")
            info = lis.node.get_subscriptions_info_by_topic("/omc/tool/pose")
            pub = _start_pub(s.procs, tmp, "pub", "--best-effort", "--duration", "3.0")
            wait_for(lambda: len(lis.got["/fullperc/tool/pose"]) > 100, 60, what="fused poses from a best-effort "
                     "driver", detail=lambda: s.procs.log(node)[-2000:])
            after = lis.node.get_subscriptions_info_by_topic("/omc/tool/pose")
            _done(s.procs, pub, tmp, "pub")
            return {"reliability": [i.qos_profile.reliability for i in info],
                    "after": [i.qos_profile.reliability for i in after], "n": len(lis.got["/fullperc/tool/pose"]),
                    "log": s.procs.log(node)}
        finally:
            lis.close()


def test_a_best_effort_driver_is_fused_with_the_shipped_defaults(scenarios, request):
    from rclpy.qos import ReliabilityPolicy

    r = scenarios.result(request.node.name)
    # qos_reliability: auto -- reliable until the best-effort driver appears, then that input is remade best effort
    assert r["reliability"] == [ReliabilityPolicy.RELIABLE] and r["n"] > 100, r
    assert r["after"] == [ReliabilityPolicy.BEST_EFFORT], r
    line = next(x for x in r["log"].splitlines() if "a best-effort publisher on /omc/tool/pose" in x)
    assert line.startswith("[WARN]") and "now best effort" in line, line
    assert "incompatible QoS" not in r["log"], r["log"]


def _override(tmp: Path) -> dict:
    """``qos_reliability: best_effort`` with ``qos_overrides./omc/tool/pose.subscription.reliability: reliable``: that
    subscription is reliable (the others are not), and a best-effort publisher on it is a WARN in the node's log (an
    explicit override is never remade best effort)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    with RosSession(tmp) as s:
        node = _start_node(s.procs, "fusion_node", "-p", "qos_reliability:=best_effort",
                           "-p", "qos_overrides./omc/tool/pose.subscription.reliability:=reliable")
        lis = Listener(s.context, {})
        try:
            topics = ("/omc/tool/pose", "/omc/base/pose", "/ots/tool/pose")
            wait_for(lambda: all(lis.node.get_subscriptions_info_by_topic(t) for t in topics), 30,
                     what="the node's inputs")
            rel = {t: [i.qos_profile.reliability for i in lis.node.get_subscriptions_info_by_topic(t)] for t in topics}
            lis.node.create_publisher(PoseStamped, "/omc/tool/pose",
                                      QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
            wait_for(lambda: "incompatible QoS on /omc/tool/pose" in s.procs.log(node), 30,
                     what="the incompatible-QoS WARN", detail=lambda: s.procs.log(node)[-2000:])
            return {"rel": rel, "log": s.procs.log(node), "alive": node.poll() is None}
        finally:
            lis.close()


def test_a_qos_override_changes_the_subscription_and_an_incompatible_peer_is_warned(scenarios, request):
    from rclpy.qos import ReliabilityPolicy

    r = scenarios.result(request.node.name)
    assert r["alive"], r["log"]
    best_effort = [ReliabilityPolicy.BEST_EFFORT]
    assert r["rel"] == {"/omc/tool/pose": [ReliabilityPolicy.RELIABLE], "/omc/base/pose": best_effort,
                        "/ots/tool/pose": best_effort}, r["rel"]
    line = next(x for x in r["log"].splitlines() if "incompatible QoS on /omc/tool/pose" in x)
    assert line.startswith("[WARN]") and "RELIABILITY" in line and "subscription" in line, line


# ------------------------------------------------------------------------------------------ run-time parameters
def _runtime(tmp: Path) -> dict:
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters
    from rclpy.parameter import Parameter

    from fullperc_fusion.fusion_core import LIVE_PARAMS
    from fullperc_msgs.msg import FusionStatus

    r: dict = {}
    with RosSession(tmp) as s:
        node = _start_node(s.procs, "fusion_node")
        lis = Listener(s.context, {"/fullperc/tool/status": FusionStatus})
        srv = "/fusion_node"
        try:
            names = lis.call(ListParameters, f"{srv}/list_parameters", ListParameters.Request()).result.names
            desc = lis.call(DescribeParameters, f"{srv}/describe_parameters", DescribeParameters.Request(names=names))
            r["writable"] = sorted(d.name for d in desc.descriptors if not d.read_only)
            r["names"] = list(names)

            def set_(name, value):
                req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
                return lis.call(SetParameters, f"{srv}/set_parameters", req).results[0]
            r["targets"] = set_("targets", ["tool", "probe"])
            r["bad_bias"] = set_("alarm.bias_max", -1.0)
            r["bad_hops"] = set_("alarm.hop_max", 0)
            wait_for(lambda: lis.node.count_subscribers("/omc/tool/pose") > 0, 30, what="the node's inputs")
            pub = _start_pub(s.procs, tmp, "pub", "--duration", "6.0")
            # the bias learnt while both sources see the target (from 0.8 s on; |offset| = 3.7 mm): no alarm at 20 mm
            wait_for(lambda: [m for m in lis.got["/fullperc/tool/status"] if m.sources == 3
                              and math.hypot(m.bias.x, m.bias.y, m.bias.z) > 2.5e-3], 60,
                     what="a bias learnt", detail=lambda: s.procs.log(node)[-2000:])
            r["before"] = [st.message for st in lis.diag()]
            r["good"] = set_("alarm.bias_max", 0.002)
            r["warn"] = wait_for(lambda: [st for st in lis.diag() if "compensation" in st.message], 30,
                                 what="the bias alarm after the run-time set",
                                 detail=lambda: [st.message for st in lis.diag()][-3:])
            got = lis.call(GetParameters, f"{srv}/get_parameters", GetParameters.Request(names=["alarm.bias_max",
                                                                                                 "targets"]))
            r["values"] = (got.values[0].double_value, list(got.values[1].string_array_value),
                           got.values[0].type == ParameterType.PARAMETER_DOUBLE)
            _done(s.procs, pub, tmp, "pub")
            r["log"], r["alive"], r["live"] = s.procs.log(node), node.poll() is None, LIVE_PARAMS
            return r
        finally:
            lis.close()


def test_run_time_parameters_are_checked_and_applied_or_refused(scenarios, request):
    r = scenarios.result(request.node.name)
    assert r["alive"], r["log"]
    ours = [n for n in r["names"] if not n.startswith("qos_overrides.") and n not in ("use_sim_time",
                                                                                     "start_type_description_service")]
    assert len(ours) > 60
    assert [n for n in r["writable"] if n in ours] == sorted(r["live"])
    assert not [n for n in r["writable"] if n.startswith("qos_overrides.")]   # rclpy's: read-only
    t = r["targets"]
    assert not t.successful and "read-only" in t.reason and "targets" in t.reason, t.reason
    b = r["bad_bias"]
    assert not b.successful and b.reason == "parameter 'alarm.bias_max' = -1.0 is invalid: must be finite and > 0"
    h = r["bad_hops"]
    assert not h.successful and "'alarm.hop_max'" in h.reason and "must be >= 1" in h.reason, h.reason
    assert r["good"].successful, r["good"].reason
    assert not any("compensation" in m for m in r["before"]), r["before"]
    m = re.search(r"\|bias\| = ([0-9.]+) mm", r["warn"][0].message)
    assert m and float(m[1]) > 2.0, r["warn"][0].message
    assert r["values"] == (0.002, ["tool"], True)
    assert "run-time parameters applied: alarm.bias_max = 0.002" in r["log"]


@pytest.fixture(scope="module")
def scenarios(request, tmp_path_factory):
    """Every selected test's scenario, side by side, each in a domain of its own."""
    jobs = {"test_two_namespaces_fuse_only_their_own_inputs": _namespaces,
            "test_a_best_effort_driver_is_fused_with_the_shipped_defaults": _best_effort_defaults,
            "test_a_qos_override_changes_the_subscription_and_an_incompatible_peer_is_warned": _override,
            "test_run_time_parameters_are_checked_and_applied_or_refused": _runtime}
    tmps = {name: tmp_path_factory.mktemp(name[5:30]) for name in jobs}   # here: mktemp is not thread-safe
    import rclpy.executors  # noqa: F401 - imported once before the threads (see test_fusion_node.scenarios)
    import rclpy.node  # noqa: F401
    import rclpy.parameter  # noqa: F401
    sbs = SideBySide({n: (lambda fn=fn, n=n: fn(tmps[n])) for n, fn in jobs.items()}).start(
        selected_cases(request, jobs))
    yield sbs
    sbs.join()
