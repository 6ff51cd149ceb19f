"""How fast the tracked tool turns and how fast its turn rate changes, from the ground truth of bags (README
"The `fullperc` filter", ``<target>.ang_accel_noise``). No sensor and no filter is looked at.

The Diana's forward kinematics (:class:`fullperc_eval.evaluation.ground_truth.GroundTruth`, with each bag's
calibration) is sampled at 50 Hz; the angular velocity is the rotation between consecutive samples over the step,
averaged over 0.2 s (joint-state quantisation would otherwise dominate the difference), and the angular
acceleration its difference over the step. Per bag: the largest |w| [rad/s], the median, 99th percentile and
largest |dw/dt| [rad/s^2]; at the end the largest of each over all bags.

Run: python scripts/truth_motion.py BAG [BAG ...]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_eval.bag.calibration import load_calibration
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.evaluation.ground_truth import GroundTruth
from fullperc_eval.evaluation.replay_data import _stamp_ns

DT = 0.02       # [s] sampling step
SMOOTH = 10     # steps averaged for the angular velocity (0.2 s)


def joint_states(bag: str) -> tuple[np.ndarray, np.ndarray]:
    reader = BagReader(bag)
    reader.open()
    t, q = [], []
    try:
        for m in reader.messages(["/diana/joint_states"]):
            msg = reader.deserialize(m.data, m.msgtype)
            t.append(_stamp_ns(msg.header))
            q.append(np.asarray(msg.position, dtype=float))
    finally:
        reader.close()
    return np.asarray(t, np.int64), np.asarray(q)


def turn_figures(bag: str) -> dict[str, float]:
    t, q = joint_states(bag)
    gt = GroundTruth(t, q, load_calibration(bag))
    ts = np.arange(gt.t_ns[0], gt.t_ns[-1], int(DT * 1e9))
    T, ok = gt.T_base_tool(ts)
    R = Rotation.from_matrix(T[ok, :3, :3])
    w = (R[1:] * R[:-1].inv()).as_rotvec() / DT
    kernel = np.ones(SMOOTH) / SMOOTH
    ws = np.stack([np.convolve(w[:, k], kernel, mode="valid") for k in range(3)], axis=1)
    a = np.linalg.norm(np.diff(ws, axis=0), axis=1) / DT
    return {"w_max": float(np.linalg.norm(ws, axis=1).max()), "a_median": float(np.median(a)),
            "a_p99": float(np.percentile(a, 99)), "a_max": float(a.max())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bags", nargs="+")
    args = ap.parse_args(argv)
    rows = []
    for bag in args.bags:
        f = turn_figures(bag)
        rows.append(f)
        print(f"{bag}: |w| max {f['w_max']:.3f} rad/s, |dw/dt| median {f['a_median']:.4f}, p99 {f['a_p99']:.4f}, "
              f"max {f['a_max']:.4f} rad/s^2")
    print(f"over {len(rows)} bags: |w| max {max(r['w_max'] for r in rows):.3f} rad/s, |dw/dt| max "
          f"{max(r['a_max'] for r in rows):.4f} rad/s^2")


if __name__ == "__main__":
    main()
