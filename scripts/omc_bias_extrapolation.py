"""Can a position-dependent OMC bias learnt in BVV be carried outside it? A raw-sensor check (issue 18).

``fullperc`` and CBKF learn the OMC's error while the Vega sees the tool (BVV) and carry it out of BVV as a constant
(CBKF) or fading (fullperc) bias. On the ``paper`` twin the OMC's error is a smooth function of position (the lens
residual, README "The twin's two profiles"), so a bias that is linear in position might carry further. This script
asks the sensor data, not a filter: per bag, the raw OMC position error (the node's own frame chain against the Diana
forward kinematics, as ``scripts/raw_sensor_stats.py``) on the samples stamped within the Vega's sightings is fitted
two ways -- a constant b, and b + J (x - x_mean) by least squares -- and each is used to predict the error of the OMC
samples before and after that span. Printed per bag and phase: the mean error norm [mm] raw, after subtracting the
constant, after subtracting the linear model, and the span of the fitting positions [mm].

Run: python scripts/omc_bias_extrapolation.py bags/paper
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fullperc_eval.bag.calibration import load_calibration
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.evaluation.config import replay_config
from fullperc_eval.evaluation.ground_truth import GroundTruth
from fullperc_fusion.frame_chain import pose_to_T
from fullperc_fusion.pipeline import TargetPipeline


def _stamp(h) -> int:
    return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)


def errors(bag: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float] | None]:
    """(OMC stamps [s], OMC error in base [m] (N, 3), true positions [m] (N, 3)) and the Vega's span [s]."""
    cfg, _ = replay_config()
    cfg.filters = ("omc",)
    pipe = TargetPipeline(cfg)
    c = cfg.chain
    reader = BagReader(bag)
    reader.open()
    jt, jq, omc, ots_t = [], [], [], []
    try:
        for m in reader.messages(list(reader.topics)):
            msg = reader.deserialize(m.data, m.msgtype)
            if m.topic == "/diana/joint_states":
                jt.append(_stamp(msg.header))
                jq.append(np.asarray(msg.position, dtype=float))
            elif m.topic.endswith("/pose") and m.topic.split("/")[1] in ("omc", "ots"):
                dev, body = m.topic.split("/")[1:3]
                t = _stamp(msg.header)
                pp, qq = msg.pose.position, msg.pose.orientation
                Td = pose_to_T((np.array([pp.x, pp.y, pp.z]), np.array([qq.x, qq.y, qq.z, qq.w])))
                if dev == "omc":
                    pipe.push_omc(body, t, Td)
                    if body == c.omc_target and pipe.chain.links.T_omc_base is not None:
                        omc.append((t, pipe.chain.global_T(Td)[:3, 3]))
                else:
                    pipe.push_ots(body, t, Td)
                    if body == c.ots_target:
                        ots_t.append(t)
                pipe.poll()
    finally:
        reader.close()
    gt = GroundTruth(np.array(jt), np.array(jq), load_calibration(bag))
    t = np.array([s[0] for s in omc], dtype=np.int64)
    T_true, ok = gt.T_base_tool(t)
    x = T_true[ok][:, :3, 3]
    e = np.array([s[1] for s in omc])[ok] - x
    span = (min(ots_t) * 1e-9, max(ots_t) * 1e-9) if ots_t else None
    return t[ok] * 1e-9, e, x, span


def _mae(err: np.ndarray) -> float:
    return float(np.linalg.norm(err, axis=1).mean() * 1e3)


def main(root: Path) -> None:
    print(f"{'bag':8s} {'phase':6s} {'raw':>5s} {'const':>6s} {'linear':>6s}  positions spanned in BVV [mm]")
    for bag in sorted(p for p in root.iterdir() if (p / "metadata.yaml").exists()):
        t, e, x, span = errors(bag)
        if span is None:
            continue
        inb = (t >= span[0]) & (t <= span[1])
        xm = x[inb].mean(axis=0)
        A = np.column_stack([np.ones(inb.sum()), x[inb] - xm])
        coef, *_ = np.linalg.lstsq(A, e[inb], rcond=None)
        b = e[inb].mean(axis=0)
        for phase, sel in (("before", t < span[0]), ("after", t > span[1])):
            if not sel.any():
                continue
            lin = np.column_stack([np.ones(sel.sum()), x[sel] - xm]) @ coef
            raw, const, linear = (_mae(e[sel] - pred) for pred in (0.0, b, lin))
            print(f"{bag.name:8s} {phase:6s} {raw:5.2f} {const:6.2f} {linear:6.2f}  "
                  f"{np.round(np.ptp(x[inb], axis=0) * 1e3).astype(int).tolist()}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "bags/paper"))
