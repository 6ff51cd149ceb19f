"""System test: the installed fusion_node with two local sources (issue 18 item 1, sources.py).

The node runs with a params file declaring omc (global) + ots (local, paired) + atracsys (a second local tracker
under /atracsys/<tool>/pose, its own static link estimated from its view of the base marker, its own noise_std).
This process publishes all three devices' views of a known trajectory plus the base markers; the OMC's tool pose
carries a visible bias. Asserted: both local sources are fused (per-source counts on /diagnostics), the fused pose
follows the truth within a bound derived from the injected local noise, and after the OTS goes silent the output
keeps that accuracy through the Atracsys while the OMC-only estimate (the ``omc`` pass-through beside it) is off
by the bias. Waits on conditions with generous timeouts; no wall-clock assertion (busy 2-core machine).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from fullperc_common.diagnostics import as_level
from fullperc_common.testing import SpunNode, installed_exe, side_by_side_fixture, wait_for

pytestmark = pytest.mark.system

LOCAL_STD = 1.0e-4                          # [m] per axis, injected on both local trackers
OMC_STD = 3.0e-4                            # [m] per axis on the OMC
OMC_BIAS = np.array([3e-3, -2e-3, 1e-3])    # [m] systematic OMC error (in omc axes): the OMC-only error
DRIFT = np.array([0.5e-3, 0.0, 0.0])        # [m/s] and its slow drift once the OTS is silent: without a local
                                            # source no filter can tell it from motion (the compensation needs one)
# mean 3-D error of one local sample is sqrt(8/pi) * LOCAL_STD (1.6 sigma); a fused estimate should do no worse than
# a single sample up to a factor for the filter's bias transient: 4 sigma per axis, as a 3-D norm
BOUND = 4 * LOCAL_STD * np.sqrt(3)          # 0.69 mm, 5x below |OMC_BIAS| (3.7 mm)
N_FUSED = 300                               # samples per local source fused in each phase


def _T(p, rz_deg=0.0):
    from fullperc_common.transforms import make_T

    a = np.radians(rz_deg) / 2
    return make_T(p, [0.0, 0.0, np.sin(a), np.cos(a)])


T_OMC_BASE = _T([1.0, 0.5, 0.8], 30)
T_OTS_BASE = _T([0.1, -0.2, -1.5], -20)
T_ATR_BASE = _T([-0.4, 0.6, -1.2], 75)


def truth(t_s: float) -> np.ndarray:
    """The tool in base at stamp t [s]: a slow circle (1.5 cm/s)."""
    return _T([0.4 + 0.03 * np.sin(0.5 * t_s), 0.03 * np.cos(0.5 * t_s), 0.3])


PARAMS = """fusion_node:
  ros__parameters:
    targets: [tool]
    static_links: average
    init_samples: 20
    filter: cbkf
    filters: [omc]
    sources: [omc, ots, atracsys]
    omc: {role: global}
    ots: {role: local}
    atracsys: {role: local, topic_prefix: /atracsys, base_tool: base, noise_std: 1.5e-4}
    tool: {atracsys: tool}
"""


class Listener(SpunNode):
    def __init__(self, ctx) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        super().__init__(ctx, "two_local_listener")
        qos = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
        self.pose: dict[str, list[tuple[int, np.ndarray]]] = {"cbkf": [], "omc": []}
        self.diag: dict[str, str] = {}
        self.messages: list[str] = []
        for name, topic in (("cbkf", "/fullperc/tool/pose"), ("omc", "/fullperc/tool/omc/pose")):
            self.node.create_subscription(PoseStamped, topic, lambda m, n=name: self._pose(n, m), qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 100)
        self.start()

    def _pose(self, name, m) -> None:
        p = m.pose.position
        with self.lock:
            self.pose[name].append((m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                                    np.array([p.x, p.y, p.z])))

    def _diag(self, arr) -> None:
        with self.lock:
            for st in arr.status:
                if st.name.endswith("target tool"):
                    self.diag = {kv.key: kv.value for kv in st.values}
                    self.messages.append(f"{as_level(st.level)} {st.message}")

    def count(self, key: str) -> int:
        with self.lock:
            return int(self.diag.get(key, 0) or 0)


def _errors_mm(outs, t0_ns: int, t_from: int, t_to: int) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [s from t0], errors [mm]) of the outputs stamped in [t_from, t_to)."""
    sel = [(t, p) for t, p in outs if t_from <= t < t_to]
    t_s = np.array([(t - t0_ns) * 1e-9 for t, _ in sel])
    e = np.array([1e3 * np.linalg.norm(p - truth(ts)[:3, 3]) for ts, (_, p) in zip(t_s, sel, strict=True)])
    assert len(e) > 50, f"only {len(e)} outputs in the window"
    return t_s, e


def _mean_err_mm(outs, t0_ns: int, t_from: int, t_to: int) -> float:
    return float(np.mean(_errors_mm(outs, t0_ns, t_from, t_to)[1]))


def _describe(outs, t0_ns: int, t_from: int, t_to: int) -> str:
    """What a failed bound saw: how many outputs were far off, the worst and when (to tell one wild output from a
    wrong estimate)."""
    t_s, e = _errors_mm(outs, t0_ns, t_from, t_to)
    k = int(np.argmax(e))
    return (f"{len(e)} outputs, median {np.median(e):.3f} mm, {int((e > 10).sum())} above 10 mm, worst {e[k]:.1f} mm "
            f"at {t_s[k]:.3f} s (window {(t_from - t0_ns) * 1e-9:.2f}-{(t_to - t0_ns) * 1e-9:.2f} s)")


def _two_local_sources_fused_and_the_second_keeps_accuracy_when_the_first_goes_silent(
        procs, rclpy_context, tmp_path):
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from fullperc_common.ros_conv import pose_stamped
    from fullperc_common.transforms import T_to_pq

    params = tmp_path / "two_local.yaml"
    params.write_text(PARAMS)
    out = Listener(rclpy_context)
    pub_node = rclpy.create_node("two_local_drivers", context=rclpy_context)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {(d, b): pub_node.create_publisher(PoseStamped, f"/{d}/{b}/pose", qos)
            for d in ("omc", "ots", "atracsys") for b in ("base", "tool")}
    rng = np.random.default_rng(7)
    t0 = time.time_ns()

    t_stop = None

    def publish(devices) -> None:
        ns = time.time_ns()
        bias = OMC_BIAS + (0 if t_stop is None else DRIFT * (ns - t_stop) * 1e-9)
        T = truth((ns - t0) * 1e-9)
        for dev, T_dev_base, std, dt in (("omc", T_OMC_BASE, OMC_STD, 0), ("ots", T_OTS_BASE, LOCAL_STD, 0),
                                         ("atracsys", T_ATR_BASE, LOCAL_STD, 1_000_000)):
            if dev not in devices:
                continue
            Tt = T_dev_base @ T
            Tt[:3, 3] += rng.normal(0, std, 3) + (bias if dev == "omc" else 0)
            pubs[(dev, "base")].publish(pose_stamped(ns + dt, dev, *T_to_pq(T_dev_base)))
            pubs[(dev, "tool")].publish(pose_stamped(ns + dt, dev, *T_to_pq(Tt)))

    def run_until(devices, done, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not done():
            assert time.monotonic() < end, f"timed out; diagnostics: {out.diag}; {out.messages[-3:]}"
            assert node.poll() is None, procs.log(node)
            publish(devices)
            time.sleep(0.01)

    try:
        node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "--params-file",
                            str(params)], name="fusion_node")
        wait_for(lambda: pub_node.count_subscribers("/atracsys/tool/pose") > 0 and
                 pub_node.count_subscribers("/ots/tool/pose") > 0, 60, what="the node's subscriptions")
        # phase A: all three sources
        run_until({"omc", "ots", "atracsys"},
                  lambda: out.count("ots_fused") >= N_FUSED and out.count("atracsys_fused") >= N_FUSED, 300)
        t_stop = time.time_ns()
        n_atr = out.count("atracsys_fused")
        n_ots = out.count("ots_fused")
        # phase B: the OTS (the first local source) goes silent, the Atracsys goes on
        run_until({"omc", "atracsys"}, lambda: out.count("atracsys_fused") >= n_atr + N_FUSED, 300)
        t_end = time.time_ns()
        wait_for(lambda: out.messages and "no OTS (local) sample for" in out.messages[-1], 60,
                 what="/diagnostics to report the OTS silent")
        assert node.poll() is None, procs.log(node)
    finally:
        pub_node.destroy_node()
        out.close()
    with out.lock:
        fused, omc_only = list(out.pose["cbkf"]), list(out.pose["omc"])
        diag = dict(out.diag)
    assert int(diag["atracsys_in"]) > n_atr and int(diag["ots_fused"]) >= n_ots, diag
    t_a = t_stop - (t_stop - t0) // 3            # the last third of phase A (links and bias settled)
    t_b = t_stop + 1_000_000_000                 # phase B from 1 s after the OTS stopped
    bias_mm = 1e3 * float(np.linalg.norm(OMC_BIAS))
    err_a = _mean_err_mm(fused, t0, t_a, t_stop)
    err_b = _mean_err_mm(fused, t0, t_b, t_end)
    err_omc = _mean_err_mm(omc_only, t0, t_b, t_end)
    assert err_omc > 0.8 * bias_mm, f"the OMC-only estimate shows the injected bias: {err_omc:.3f} mm"
    assert err_a < 1e3 * BOUND, (f"both local sources: mean error {err_a:.3f} mm > {1e3 * BOUND:.3f} mm; "
                                 f"{_describe(fused, t0, t_a, t_stop)}")
    assert err_b < 1e3 * BOUND, (f"OTS silent, Atracsys on: mean error {err_b:.3f} mm > {1e3 * BOUND:.3f} mm "
                                 f"(OMC only: {err_omc:.3f} mm); {_describe(fused, t0, t_b, t_end)}")
    print(f"mean error: both locals {err_a:.3f} mm, Atracsys only {err_b:.3f} mm, OMC only {err_omc:.3f} mm")


BAD_SOURCES = {
    "two_global": ("    sources: [omc, ots, atracsys]\n    omc: {role: global}\n    ots: {role: local}\n"
                   "    atracsys: {role: global}\n", "exactly one source needs role global"),
    "no_block": ("    sources: [omc, ots, atracsys]\n    omc: {role: global}\n    ots: {role: local}\n",
                 "source 'atracsys' (parameter 'sources') has no block"),
    "bad_role": ("    sources: [omc, atracsys]\n    omc: {role: global}\n    atracsys: {role: remote}\n",
                 "'atracsys.role'"),
}


def _a_bad_sources_configuration_stops_the_node_with_exit_2(procs, tmp_path, bad, match):
    params = tmp_path / "bad.yaml"
    params.write_text("fusion_node:\n  ros__parameters:\n" + bad)
    node = procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "--params-file", str(params)],
                       name="fusion_node")
    wait_for(lambda: node.poll() is not None, 120, what="the node to exit")
    assert node.returncode == 2 and match in procs.log(node), procs.log(node)


# every test's processes at once, side by side (each in a domain of its own)
scenarios = side_by_side_fixture(
    _two_local_sources_fused_and_the_second_keeps_accuracy_when_the_first_goes_silent,
    **{f"test_a_bad_sources_configuration_stops_the_node_with_exit_2[{k}]":
       (_a_bad_sources_configuration_stops_the_node_with_exit_2, {"bad": bad, "match": match})
       for k, (bad, match) in BAD_SOURCES.items()})


def test_two_local_sources_fused_and_the_second_keeps_accuracy_when_the_first_goes_silent(scenarios, request):
    scenarios.result(request.node.name)


@pytest.mark.parametrize("case", list(BAD_SOURCES))
def test_a_bad_sources_configuration_stops_the_node_with_exit_2(scenarios, request, case):
    scenarios.result(request.node.name)
