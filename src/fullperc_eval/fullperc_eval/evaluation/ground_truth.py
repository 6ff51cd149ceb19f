"""Ground truth of the target from the arm's joint states (paper §5.2: the robot's encoders are the reference).

    T_base_tool(t) = T_base_diana_base · FK(q(t)) · T_flange_tool

``FK`` is :class:`fullperc_drivers.diana_kinematics.DianaKinematics` (the same model the ``diana_state``
node publishes ``/diana/flange_pose`` with), ``q(t)`` the recorded ``/diana/joint_states`` interpolated
linearly in joint space to the evaluated stamp. Joint-space interpolation is exact for the paper's protocol
(one joint turning at a smoothly varying rate) up to the curvature of q(t) over one sample period: at 100 Hz
and the simulator's peak joint acceleration that is far below a micrometre.

The two static transforms are the *calibration*. They travel with the bag as ``calibration.yaml`` in the bag
directory (:mod:`fullperc_eval.bag.calibration`: file format, :func:`~fullperc_eval.bag.calibration.load_calibration`):
for a simulated bag they are the simulator's true values; for a real recording they are the user's robot-world /
hand-eye calibration, and every error of that calibration shows up 1:1 in every method's error (a constant offset
per task). We deliberately do **not** estimate them from the bag being evaluated: fitting T_base_diana_base to
the OMC data would pull the truth towards the OMC (hiding its bias), fitting it to the OTS data would hand the
OTS-using filters a head start. An optional ``T_omc_base`` (true pose of the base marker in ``omc``) is used only
to place the truth in the layout frame for the region labels; without it the evaluator takes the average of the
recorded raw OMC base-marker poses, whose millimetre-level error is irrelevant for labelling.

**Targets without a robot** (the twin's hand-held ``instrument``, :mod:`fullperc_eval.sim.walker`) have no encoders:
their truth is the simulator's, recorded in the bag as ``/sim/truth/<target>`` (PoseStamped in ``base``;
simulator-only, no real recording has it). :class:`TruthTrack` interpolates it like the joint states (position
linearly, orientation by slerp). :func:`target_truth` picks the source: the arm-held target (``tool``) always
uses the Diana's forward kinematics, as before; any other target needs its truth topic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fullperc_eval.bag.calibration import Calibration
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.reader import BagReader

DEFAULT_MAX_GAP_NS = 50_000_000   # joint states further apart than this are not interpolated across
ARM_TARGET = "tool"               # the target on the Diana's flange: truth from its joint states
TRUTH_PREFIX = "/sim/truth"       # /sim/truth/<target>: the simulator's truth of a target without a robot


class GroundTruth:
    """Target position in ``base`` at any stamp inside the recorded joint-state stream.

    ``t_ns`` (N,) joint-state stamps (acquisition times, strictly increasing after de-duplication),
    ``q`` (N, 7) joint angles [rad]. Stamps more than ``max_gap_ns`` from a joint sample on either side, or
    outside the recorded span, are invalid (NaN) rather than extrapolated.
    """

    def __init__(self, t_ns, q, calibration: Calibration, kinematics=None,
                 max_gap_ns: int = DEFAULT_MAX_GAP_NS) -> None:
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        Q = np.asarray(q, dtype=float)
        if Q.ndim != 2 or Q.shape[0] != t.shape[0] or Q.shape[1] != 7:
            raise ValueError(f"joint states: expected t (N,) and q (N, 7), got {t.shape} and {Q.shape}")
        if t.size < 2:
            raise ValueError(f"joint states: need at least 2 samples for ground truth, got {t.size}")
        order = np.argsort(t, kind="stable")
        t, Q = t[order], Q[order]
        keep = np.concatenate([[True], np.diff(t) > 0])      # duplicate stamps: the first sample wins
        self.t_ns, self.q = t[keep], Q[keep]
        if not np.all(np.isfinite(self.q)):
            raise ValueError("joint states contain NaN/inf")
        if kinematics is None:
            from fullperc_drivers.diana_kinematics import DianaKinematics

            kinematics = DianaKinematics()
        self.kin = kinematics
        self.cal = calibration
        self.max_gap_ns = int(max_gap_ns)

    def joints_at(self, t_ns) -> tuple[np.ndarray, np.ndarray]:
        """Linearly interpolated q (M, 7) and a validity mask (M,) at stamps ``t_ns``."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        ts = self.t_ns
        i = np.searchsorted(ts, t, side="right")          # ts[i-1] <= t < ts[i]
        valid = (i > 0) & (t <= ts[-1])
        i0 = np.clip(i - 1, 0, len(ts) - 1)
        i1 = np.clip(i, 0, len(ts) - 1)
        exact = valid & (ts[i0] == t)
        i1 = np.where(exact, i0, i1)
        gap = ts[i1] - ts[i0]
        valid &= exact | (gap <= self.max_gap_ns)
        w = np.where(gap > 0, (t - ts[i0]) / np.where(gap > 0, gap, 1), 0.0)
        Q = self.q[i0] + (self.q[i1] - self.q[i0]) * w[:, None]
        return Q, valid

    def T_base_tool(self, t_ns) -> tuple[np.ndarray, np.ndarray]:
        """(M, 4, 4) true target poses in ``base`` (NaN where invalid) and the validity mask."""
        Q, valid = self.joints_at(t_ns)
        out = np.full((len(Q), 4, 4), np.nan)
        if valid.any():
            F = self.kin.fk_many(Q[valid])
            out[valid] = self.cal.T_base_diana_base @ F @ self.cal.T_flange_tool
        return out, valid

    def position_base(self, t_ns) -> tuple[np.ndarray, np.ndarray]:
        T, valid = self.T_base_tool(t_ns)
        return T[:, :3, 3], valid


class TruthTrack:
    """A target's recorded true poses in ``base`` (``/sim/truth/<target>``), the same interface as :class:`GroundTruth`.

    ``t_ns`` (N,) stamps, ``T`` (N, 4, 4) poses. Between two samples at most ``max_gap_ns`` apart: position linearly,
    orientation by slerp (exact enough at the simulator's 120 Hz: a walking hand turns well under a degree between
    samples); elsewhere invalid (NaN).
    """

    def __init__(self, t_ns, T, max_gap_ns: int = DEFAULT_MAX_GAP_NS) -> None:
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        T = np.asarray(T, dtype=float)
        if T.shape != (len(t), 4, 4):
            raise ValueError(f"truth track: expected t (N,) and T (N, 4, 4), got {t.shape} and {T.shape}")
        if t.size < 2:
            raise ValueError(f"truth track: need at least 2 samples, got {t.size}")
        order = np.argsort(t, kind="stable")
        t, T = t[order], T[order]
        keep = np.concatenate([[True], np.diff(t) > 0])
        self.t_ns, self.T = t[keep], T[keep]
        if not np.all(np.isfinite(self.T)):
            raise ValueError("truth track contains NaN/inf")
        self.max_gap_ns = int(max_gap_ns)
        self._slerp = Slerp((self.t_ns - self.t_ns[0]).astype(float), Rotation.from_matrix(self.T[:, :3, :3]))

    def T_base_tool(self, t_ns) -> tuple[np.ndarray, np.ndarray]:
        """(M, 4, 4) true poses in ``base`` (NaN where invalid) and the validity mask."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        ts = self.t_ns
        i = np.clip(np.searchsorted(ts, t, side="right"), 1, len(ts) - 1)   # ts[i-1] <= t < ts[i] inside the span
        valid = (t >= ts[0]) & (t <= ts[-1]) & ((ts[i] - ts[i - 1] <= self.max_gap_ns) | (t == ts[i - 1]))
        out = np.full((len(t), 4, 4), np.nan)
        if valid.any():
            tv, iv = t[valid], i[valid]
            w = ((tv - ts[iv - 1]) / (ts[iv] - ts[iv - 1]))[:, None]
            T = np.tile(np.eye(4), (len(tv), 1, 1))
            T[:, :3, 3] = self.T[iv - 1, :3, 3] * (1 - w) + self.T[iv, :3, 3] * w
            T[:, :3, :3] = self._slerp((tv - ts[0]).astype(float)).as_matrix()
            out[valid] = T
        return out, valid

    def position_base(self, t_ns) -> tuple[np.ndarray, np.ndarray]:
        T, valid = self.T_base_tool(t_ns)
        return T[:, :3, 3], valid


def load_truth_track(bag: str | Path, target: str) -> TruthTrack:
    """``/sim/truth/<target>`` of ``bag`` as a :class:`TruthTrack`; ValueError when the bag has none."""
    topic = f"{TRUTH_PREFIX}/{target}"
    reader = BagReader(bag)
    if topic not in reader.topics or reader.topics[topic].count == 0:
        raise ValueError(f"bag {str(reader.path)!r} has no {topic}: target '{target}' has no robot, and its ground "
                         "truth is the simulator's (only bags of the twin have it)")
    t, T = [], []
    try:
        reader.open()
        for m in reader.messages([topic]):
            msg = reader.deserialize(m.data, m.msgtype)
            p, q = msg.pose.position, msg.pose.orientation
            Tk = np.eye(4)
            Tk[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            Tk[:3, 3] = (p.x, p.y, p.z)
            t.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            T.append(Tk)
    except BagError as e:
        raise ValueError(str(e)) from None
    finally:
        reader.close()
    return TruthTrack(t, np.asarray(T))


def target_truth(bag: str | Path, target: str) -> TruthTrack | None:
    """The truth of ``target`` when it is not the arm-held one (None: use the Diana's joints, :class:`GroundTruth`)."""
    return None if target == ARM_TARGET else load_truth_track(bag, target)
