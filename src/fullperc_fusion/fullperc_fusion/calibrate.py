"""calibrate: calibrate the static links of the frame chain from live sightings, write a calibration YAML, exit.

Subscribes (names as fusion_node's parameters ``omc_base_body``, ``omc_rig_body``, ``ots_base_tool``; relative, as
fusion_node's: ``-r __ns:=/or1`` reads ``/or1/omc/...``):
  omc/<omc_base_body>/pose   the OMC's sightings of the reference marker          -> T_omc_base
  ots/<ots_base_tool>/pose   the OTS's sightings of the reference marker (eq. 2)  -> T_base_ots
  omc/<omc_rig_body>/pose    the OMC's sightings of the marker on the OTS (eq. 1) -> T_rig_ots (with both above)
for ``duration`` seconds of sensor stamps from the first sighting, while the setup stands still; then estimates
each link in ``links`` separately with the robust SE(3) mean of :mod:`fullperc_fusion.calibration.se3_stats` (outliers
rejected, 6x6 covariance of the mean) and writes ``output`` (:mod:`fullperc_fusion.calibration.io`; written to a
temporary file and renamed, so never a partial file), which ``fusion_node`` loads with ``calibration_file``.

Exit status: 0 = calibrated and written (one summary line on stdout); 1 = refused -- a body moved during the
collection, too few sightings came within ``duration`` + ``timeout`` s, or the run was stopped before the end --
with the reason on ONE line on stderr (``[calibrate] refused: ...``, naming the body) and nothing written;
2 = bad parameter (node_main). Parameters: config/calibrate.yaml (printed by ``--help``).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy

from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare
from fullperc_common.ros_conv import pose_to_pq, stamp_to_ns
from fullperc_fusion.calibration.io import save_calibration
from fullperc_fusion.calibration.run import CalibrationRun, summary
from fullperc_fusion.calibration.se3_stats import (
    LINK_NAMES,
    CalibrationBodies,
    CalibrationSettings,
    StaticThresholds,
)
from fullperc_fusion.fusion_config import Param, convert
from fullperc_fusion.pipeline.frame_chain import ChainConfig

NAME = "calibrate"
_C = ChainConfig()
_S = CalibrationSettings()


def _pos(v) -> bool:
    return math.isfinite(v) and v > 0


PARAMS: tuple[Param, ...] = (
    Param("omc_base_body", _C.omc_base, "str", bool, "must not be empty", "", "OMC rigid body of the reference marker"),
    Param("omc_rig_body", _C.omc_rig, "str", bool, "must not be empty", "", "OMC rigid body attached to the OTS"),
    Param("ots_base_tool", _C.ots_base, "str", bool, "must not be empty", "", "OTS tool on the reference marker"),
    Param("links", list(LINK_NAMES), "str_list", lambda v: len(v) > 0 and all(x in LINK_NAMES for x in v),
          f"a non-empty list of {list(LINK_NAMES)}", "", "links to calibrate (T_rig_ots brings T_omc_base)"),
    Param("duration", 10.0, "float", _pos, "must be finite and > 0", "s", "sensor time collected"),
    Param("output", "calibration.yaml", "str", bool, "must not be empty", "", "calibration YAML written"),
    Param("timeout", 10.0, "float", _pos, "must be finite and > 0", "s",
          "host time allowed beyond duration for the sightings to come"),
    Param("min_samples", _S.min_samples, "int", lambda v: v >= 2, "must be >= 2", "samples",
          "fewer sightings of a body: refused"),
    Param("max_drift", _S.static.max_drift_m, "float", _pos, "must be finite and > 0", "m",
          "a body's mean moved more than this (and significantly) during the collection: refused"),
    Param("max_rot_drift", _S.static.max_drift_rad, "float", _pos, "must be finite and > 0", "rad",
          "the same for its rotation"),
    Param("pair_tol", _S.pair_tol_ns * 1e-9, "float", _pos, "must be finite and > 0", "s",
          "T_rig_ots: OMC rig and OTS base sightings closer than this form a pair"),
    Param("qos_reliability", "reliable", "str", lambda v: v in ("reliable", "best_effort"),
          "reliable or best_effort", "", "QoS reliability of the subscriptions"),
    Param("qos_depth", 1000, "int", lambda v: v > 0, "must be > 0", "messages", "QoS history depth"),
)
_ROS_TYPES = {"str_list": Parameter.Type.STRING_ARRAY}


class CalibrateNode(Node):
    def __init__(self, **kw) -> None:
        super().__init__(NAME, **kw)
        v: dict[str, Any] = {}
        for p in PARAMS:
            default = p.default if p.default not in (None, []) else _ROS_TYPES[p.kind]
            v[p.name] = convert(p, declare(self, p.name, default, description=p.description))
        bodies = CalibrationBodies(v["omc_base_body"], v["ots_base_tool"], v["omc_rig_body"])
        settings = CalibrationSettings(min_samples=v["min_samples"], pair_tol_ns=int(round(v["pair_tol"] * 1e9)),
                                       static=StaticThresholds(max_drift_m=v["max_drift"],
                                                               max_drift_rad=v["max_rot_drift"]))
        self.output = v["output"]
        self.run = CalibrationRun(v["links"], bodies, v["duration"], settings, now=time.monotonic(),
                                  timeout_s=v["timeout"], source=f"calibrate, {v['duration']:g} s")
        self.status: int | None = None      # 0 written, 1 refused; None while collecting
        self.message = ""
        qos = QoSProfile(depth=v["qos_depth"], reliability=ReliabilityPolicy.RELIABLE
                         if v["qos_reliability"] == "reliable" else ReliabilityPolicy.BEST_EFFORT)
        topics = []
        for key in self.run.collector.counts():
            dev, body = key.split(":", 1)
            topic = f"{dev}/{body}/pose"   # relative: under the node's namespace, as fusion_node's inputs
            sub = self.create_subscription(PoseStamped, topic, lambda m, d=dev, b=body: self._on_pose(d, b, m), qos)
            topics.append(sub.topic_name)
        self.create_timer(0.05, self._on_timer)
        self.get_logger().info(f"calibrating {list(self.run.collector.links)} from {topics} over {v['duration']:g} s "
                               f"of sightings; keep the OTS and the reference marker still")

    def _on_pose(self, dev: str, body: str, msg: PoseStamped) -> None:
        p, q = pose_to_pq(msg.pose)
        self.run.add(dev, body, stamp_to_ns(msg.header.stamp), p, q)

    def _on_timer(self) -> None:
        if self.status is not None or not self.run.poll(time.monotonic()):
            return
        if self.run.result is None:
            self.status, self.message = 1, f"refused: {self.run.error}; nothing written"
        else:
            try:
                save_calibration(self.output, self.run.result)
                self.status, self.message = 0, f"wrote {self.output}: {summary(self.run.result)}"
            except (OSError, ValueError) as e:
                self.status, self.message = 1, f"refused: cannot write {self.output}: {e}"
        self.context.try_shutdown()   # ends run_node's spin loop; the exit status is set in main()


def main(args=None) -> int:
    made: list[CalibrateNode] = []

    def factory() -> CalibrateNode:
        made.append(CalibrateNode())
        return made[-1]

    status = run_node(factory, NAME, (ParameterError, ValueError), args,
                      params_file=("fullperc_fusion", f"{NAME}.yaml"))
    if status != 0 or not made:
        return status
    node = made[-1]
    if node.status is None:
        node.status, node.message = 1, "refused: stopped before the collection ended; nothing written"
    text = " ".join(node.message.split())
    if node.status == 0:
        print(f"[{NAME}] {text}", flush=True)
    else:
        print(f"[{NAME}] {text}", file=sys.stderr, flush=True)
    return node.status


if __name__ == "__main__":
    sys.exit(main())
