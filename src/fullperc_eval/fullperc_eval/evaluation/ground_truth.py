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
"""

from __future__ import annotations

import numpy as np

from fullperc_eval.bag.calibration import Calibration

DEFAULT_MAX_GAP_NS = 50_000_000   # joint states further apart than this are not interpolated across


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
