"""System test: a bump of the Vega stand in the twin is reported by fusion_node's link monitor, across processes.

The twin simulates a task in which the Vega (with its OMC rig body) is moved by a few millimetres and tilted by a
fraction of a degree mid-run (``run_task(vega_bump=...)``, the python side of ``sim --vega-bump``) and writes it as
a bag. ``play`` publishes its raw driver topics to two installed ``fusion_node`` processes on a private domain:
one with ``link_monitor.recalibrate:=false`` (it must keep reporting the bump) and one with ``true`` (it must
re-calibrate and stop reporting it). The test listens to ``/diagnostics`` and both nodes' ``FusionStatus``.

Played, not live: the same data reach both nodes on any machine, and the node fuses on the samples' stamps, so a
busy machine only makes the run slower, never different -- provided nothing is dropped on the way: the nodes' QoS
depth and play's publisher depth (``DEPTH``) hold a whole task per topic. With the node's default depth (100, a
quarter of a second of the Vega's samples) a node that stalled on a busy machine lost samples and with them the
evaluations right after the bump (seen once, with a second test suite running beside this one). The time limits
below are liveness bounds only. For the same reason the bag is played at twice its speed, and only as far as the
checks need (re-calibration done and 500 statuses after it); the twin simulates the task while the nodes start.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from fullperc_common.diagnostics import as_level
from fullperc_common.testing import SpunNode, installed_exe, wait_for

pytestmark = pytest.mark.system

TASK, SEED = "B-G-P", 0
BUMP_AT_S, BUMP_DX_M, BUMP_TILT_DEG = 10.0, 0.004, 0.3
CAL_S = 3.0        # calibration.duration of the nodes: short, so re-calibration ends well inside the task
POSE_TOPICS = ["/omc/base/pose", "/omc/ots_rig/pose", "/omc/tool/pose", "/ots/base/pose", "/ots/tool/pose"]
NODES = ("keep", "recal")   # link_monitor.recalibrate false / true
DEPTH = 20000               # > samples per topic of the task (28 s at <= 400 Hz): nothing dropped on a busy machine
PLAY_S = 23.0               # [s] of the task played: the bump at 10 s, re-calibration done by 16.5 s, then > 4.2 s of
                            # 120 Hz statuses (> 500) to show it cleared
RATE = 2.0                  # play's rate: the nodes fuse on stamps (calibration and link monitor windows included)


class Listener(SpunNode):
    """FusionStatus of both nodes (remapped to /<node>/status) and every /diagnostics status, with stamps."""

    def __init__(self, context) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from fullperc_msgs.msg import FusionStatus

        super().__init__(context, "bump_listener")
        self.status: dict[str, list[tuple[int, bool]]] = {n: [] for n in NODES}
        self.diag: list[tuple[str, int, str]] = []
        qos = QoSProfile(depth=DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        for n in NODES:
            self.node.create_subscription(FusionStatus, f"/{n}/status", lambda m, n=n: self._on_status(n, m), qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 100)
        self.start()

    def _on_status(self, node: str, m) -> None:
        with self.lock:
            self.status[node].append((m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                                      bool(m.link_bumped)))

    def _on_diag(self, m) -> None:
        with self.lock:
            self.diag += [(s.name, as_level(s.level), s.message) for s in m.status]

    def snapshot(self):
        with self.lock:
            return {n: list(v) for n, v in self.status.items()}, list(self.diag)


def bumped_bag(out):
    """The twin's task with the Vega bumped at BUMP_AT_S, as a bag; (bag, bump stamp, stamp where the play stops)."""
    from fullperc_eval.sim import run_task
    from fullperc_eval.sim.dataset import EPOCH_NS, content_from_sim, write_bag
    from fullperc_eval.sim.scene import VegaBump

    run = run_task(TASK, seed=SEED, vega_bump=VegaBump(BUMP_AT_S, BUMP_DX_M, BUMP_TILT_DEG))
    bag = write_bag(out / "bag", content_from_sim(run))
    return bag, EPOCH_NS + round(BUMP_AT_S * 1e9), EPOCH_NS + min(int(run.omc.t_ns[-1]), round(PLAY_S * 1e9))


def test_fusion_node_reports_the_bump_and_recovers_by_recalibrating(procs, rclpy_context, tmp_path):
    listener = Listener(rclpy_context)
    try:
        for n, recal in zip(NODES, ("false", "true"), strict=True):
            procs.start([installed_exe("fullperc_fusion", "fusion_node"), "--ros-args", "-r", f"__node:={n}",
                         "-r", f"/fullperc/tool/status:=/{n}/status", "-p", f"calibration.duration:={CAL_S}",
                         "-p", f"link_monitor.recalibrate:={recal}", "-p", f"qos_depth:={DEPTH}"], name=n)
        bag, bump_ns, end_ns = bumped_bag(tmp_path)   # while the nodes start
        play = procs.start([installed_exe("fullperc_eval", "play"), str(bag), "--topics", *POSE_TOPICS,
                            "--publisher-depth", str(DEPTH), "--wait-for-subscribers", "120", "--rate", str(RATE),
                            "--playback-duration", str(PLAY_S)], name="play")
        wait_for(lambda: play.poll() is not None, timeout=600, what="play to finish")
        assert play.returncode == 0, procs.log(play)[-2000:]
        # the last outputs come after the idle flush (0.5 s of no target samples)
        wait_for(lambda: all(s and s[-1][0] > end_ns - 1_000_000_000 for s in listener.snapshot()[0].values()),
                 timeout=120, what="both nodes' last outputs")
    finally:
        status, diag = listener.snapshot()
        listener.close()

    for n in NODES:
        t = np.array([s[0] for s in status[n]])
        b = np.array([s[1] for s in status[n]])
        assert len(t) > 1000, n
        # before the bump: never bumped (the calibration and the 1 s window see a still Vega)
        assert not b[t < bump_ns].any(), f"{n}: link_bumped before the bump"
        # within 2 windows after it: bumped (first evaluation after a full window, then every half window)
        soon = (t > bump_ns + 2_000_000_000) & (t < bump_ns + 2_500_000_000)
        assert soon.any() and b[soon].all(), f"{n}: link_bumped not set 2 s after the bump"
    keep_t = np.array([s[0] for s in status["keep"]])
    keep_b = np.array([s[1] for s in status["keep"]])
    assert keep_b[keep_t > bump_ns + 2_000_000_000].all(), "without re-calibration the bump must stay reported"
    rec_t = np.array([s[0] for s in status["recal"]])
    rec_b = np.array([s[1] for s in status["recal"]])
    # re-calibration: starts at the first bumped evaluation (<= 1.5 s after the bump), collects CAL_S s of stamps;
    # then the new link is the reference and the monitor's next evaluations are within limits
    late = rec_t > bump_ns + round((1.5 + CAL_S + 2.0) * 1e9)
    assert late.sum() > 500 and not rec_b[late].any(), "re-calibration did not clear the bump"

    warns = [(name, m) for name, level, msg in diag if level == 1
             and (m := re.search(r"static link T_base_ots bumped: the .*? is ([0-9.]+) mm", msg))]
    assert {name.split(":")[0] for name, _ in warns} >= set(NODES), f"no WARN naming the link: {diag[-5:]}"
    # the WARN names the size, which is the bump's (4 mm + 0.3 deg at the base marker: several mm)
    assert min(float(m.group(1)) for _, m in warns) > 2.0
