"""How fast a tracked target moves and turns, and how fast that changes, from the ground truth of bags (docs/targets.md
"A hand-held target needs its own motion model": ``<target>.accel_noise`` and ``<target>.ang_accel_noise``).
No sensor and no filter is looked at.

The truth -- the Diana's forward kinematics for the arm-held ``tool`` (:class:`GroundTruth`, with each bag's
calibration), the simulator's ``/sim/truth/<target>`` for any other target -- is sampled at 50 Hz and averaged over
0.2 s (joint-state quantisation, and a hand's 8-12 Hz tremor of a fifth of a millimetre, would otherwise dominate the
differences). Turning: the angular velocity is the rotation between consecutive samples over the step, the angular
acceleration its difference over the step. Moving: the same for the position. Per bag: the largest |w| [rad/s],
the median, 99th percentile and largest |dw/dt| [rad/s^2], the largest speed [m/s] and acceleration [m/s^2], and
v_max * a_max [m^2/s^3]: the white-acceleration density a constant-velocity model needs for that motion (over a time
T the model lets the velocity change by ~sqrt(q T) (Bar-Shalom, Li, Kirubarajan 2001, sec. 6.2.2); the target
reaches v_max from rest at a_max in T = v_max / a_max, so q ~ v_max^2 / T = v_max a_max), and by the same argument
|w| max * |dw/dt| max [rad^2/s^3] for the constant-angular-velocity model (``<target>.ang_accel_noise``). At the end:
the largest of each over all bags.

Run: python scripts/truth_motion.py [--target NAME] BAG [BAG ...]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from fullperc_eval.bag.calibration import load_calibration
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.evaluation.ground_truth import GroundTruth, target_truth
from fullperc_eval.evaluation.replay_data import _stamp_ns

DT = 0.02       # [s] sampling step
SMOOTH = 10     # steps averaged for the velocities (0.2 s)


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


def _truth(bag: str, target: str):
    track = target_truth(bag, target)
    if track is None:
        t, q = joint_states(bag)
        track = GroundTruth(t, q, load_calibration(bag))
    return track


def _smooth(x: np.ndarray) -> np.ndarray:
    kernel = np.ones(SMOOTH) / SMOOTH
    return np.stack([np.convolve(x[:, k], kernel, mode="valid") for k in range(x.shape[1])], axis=1)


def motion_figures(bag: str, target: str = "tool") -> dict[str, float]:
    """Turn and move figures of ``target`` in ``bag`` (module docstring)."""
    gt = _truth(bag, target)
    ts = np.arange(gt.t_ns[0], gt.t_ns[-1], int(DT * 1e9))
    T, ok = gt.T_base_tool(ts)
    R = Rotation.from_matrix(T[ok, :3, :3])
    ws = _smooth((R[1:] * R[:-1].inv()).as_rotvec() / DT)
    a = np.linalg.norm(np.diff(ws, axis=0), axis=1) / DT
    vs = _smooth(np.diff(T[ok, :3, 3], axis=0) / DT)
    acc = np.linalg.norm(np.diff(vs, axis=0), axis=1) / DT
    v_max, acc_max = float(np.linalg.norm(vs, axis=1).max()), float(acc.max())
    w_max, a_max = float(np.linalg.norm(ws, axis=1).max()), float(a.max())
    return {"w_max": w_max, "a_median": float(np.median(a)), "a_p99": float(np.percentile(a, 99)), "a_max": a_max,
            "v_max": v_max, "acc_max": acc_max, "q_cv": v_max * acc_max, "q_turn": w_max * a_max}


def turn_figures(bag: str) -> dict[str, float]:
    """The arm-held tool's figures (:func:`motion_figures`)."""
    return motion_figures(bag, "tool")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--target", default="tool", help="tracked target (default tool: the Diana's joints)")
    ap.add_argument("bags", nargs="+")
    args = ap.parse_args(argv)
    rows = []
    for bag in args.bags:
        f = motion_figures(bag, args.target)
        rows.append(f)
        print(f"{bag}: |w| max {f['w_max']:.3f} rad/s, |dw/dt| median {f['a_median']:.4f}, p99 {f['a_p99']:.4f}, "
              f"max {f['a_max']:.4f} rad/s^2; |v| max {f['v_max']:.3f} m/s, |dv/dt| max {f['acc_max']:.3f} m/s^2, "
              f"v_max*a_max {f['q_cv']:.4g} m^2/s^3, w_max*(dw/dt)_max {f['q_turn']:.4g} rad^2/s^3")
    top = {k: max(r[k] for r in rows) for k in rows[0]}
    print(f"over {len(rows)} bags ({args.target}): |w| max {top['w_max']:.3f} rad/s, |dw/dt| max {top['a_max']:.4f} "
          f"rad/s^2, |v| max {top['v_max']:.3f} m/s, |dv/dt| max {top['acc_max']:.3f} m/s^2, v_max*a_max "
          f"{top['q_cv']:.4g} m^2/s^3, w_max*(dw/dt)_max {top['q_turn']:.4g} rad^2/s^3")


if __name__ == "__main__":
    main()
