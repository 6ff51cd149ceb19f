"""Ground truth of the target from the arm's joint states (paper §5.2: the robot's encoders are the reference).

    T_base_tool(t) = T_base_diana_base · FK(q(t)) · T_flange_tool

``FK`` is :class:`fullperc_drivers.diana_kinematics.DianaKinematics` (the same model the ``diana_state``
node publishes ``/diana/flange_pose`` with), ``q(t)`` the recorded ``/diana/joint_states`` interpolated
linearly in joint space to the evaluated stamp. Joint-space interpolation is exact for the paper's protocol
(one joint turning at a smoothly varying rate) up to the curvature of q(t) over one sample period: at 100 Hz
and the simulator's peak joint acceleration that is far below a micrometre.

The two static transforms are the *calibration*. They travel with the bag as ``calibration.yaml`` in the bag
directory (:func:`load_calibration`): for a simulated bag they are the simulator's true values; for a real
recording they are the user's robot-world / hand-eye calibration, and every error of that calibration shows up
1:1 in every method's error (a constant offset per task). We deliberately do **not** estimate them from the bag
being evaluated: fitting T_base_diana_base to the OMC data would pull the truth towards the OMC (hiding its
bias), fitting it to the OTS data would hand the OTS-using filters a head start. An optional ``T_omc_base``
(true pose of the base marker in ``omc``) is used only to place the truth in the layout frame for the region
labels; without it the evaluator takes the average of the recorded raw OMC base-marker poses, whose
millimetre-level error is irrelevant for labelling.

File format (metres, quaternions x y z w; ``source`` is free text saying where the numbers come from)::

    T_base_diana_base: [x, y, z, qx, qy, qz, qw]
    T_flange_tool:     [x, y, z, qx, qy, qz, qw]
    T_omc_base:        [x, y, z, qx, qy, qz, qw]   # optional
    source: "simulator truth (fullperc_eval.dataset, task G-B-P, seed 0)"
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from fullperc_common.transforms import T_to_pq, make_T

CALIBRATION_FILE = "calibration.yaml"
REQUIRED = ("T_base_diana_base", "T_flange_tool")
OPTIONAL = ("T_omc_base",)
DEFAULT_MAX_GAP_NS = 50_000_000   # joint states further apart than this are not interpolated across


class CalibrationError(ValueError):
    """The calibration file is missing or malformed; the message names the file and the field."""


@dataclass
class Calibration:
    T_base_diana_base: np.ndarray
    T_flange_tool: np.ndarray
    T_omc_base: np.ndarray | None = None
    source: str = ""

    def as_dict(self) -> dict:
        out: dict = {}
        for k in REQUIRED + OPTIONAL:
            T = getattr(self, k)
            if T is not None:
                p, q = T_to_pq(T)
                out[k] = [float(v) for v in (*p, *q)]
        out["source"] = self.source
        return out


def _pose7(value, name: str, where: str) -> np.ndarray:
    if not isinstance(value, list | tuple) or len(value) != 7:
        raise CalibrationError(f"{where}: '{name}' must be a list [x, y, z, qx, qy, qz, qw], got {value!r}")
    try:
        v = np.array([float(x) for x in value])
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: '{name}' has a non-numeric entry: {value!r}") from None
    if not np.all(np.isfinite(v)):
        raise CalibrationError(f"{where}: '{name}' contains NaN/inf")
    n = float(np.linalg.norm(v[3:]))
    if abs(n - 1.0) > 1e-3:
        raise CalibrationError(f"{where}: '{name}' quaternion has norm {n:.6f}, expected 1 (x y z w order)")
    return make_T(v[:3], v[3:] / n)


def parse_calibration(data, where: str = "<calibration>") -> Calibration:
    if not isinstance(data, dict):
        raise CalibrationError(f"{where}: expected a mapping with {', '.join(REQUIRED)}")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise CalibrationError(f"{where}: missing {', '.join(missing)} (needed to turn joint states into "
                               "ground truth in the base frame)")
    kw = {k: _pose7(data[k], k, where) for k in REQUIRED}
    for k in OPTIONAL:
        if data.get(k) is not None:
            kw[k] = _pose7(data[k], k, where)
    return Calibration(**kw, source=str(data.get("source", "")))


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration file, or ``<bag>/calibration.yaml`` when given a bag directory."""
    p = Path(path)
    if p.is_dir():
        p = p / CALIBRATION_FILE
    if not p.is_file():
        raise CalibrationError(
            f"no calibration file {str(p)!r}: the evaluator needs T_base_diana_base and T_flange_tool to compute "
            f"the ground truth (put a {CALIBRATION_FILE} into the bag directory or pass --calibration FILE)")
    try:
        data = yaml.safe_load(p.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise CalibrationError(f"{p}: not a readable YAML file ({type(e).__name__}: {e})") from None
    return parse_calibration(data, str(p))


def save_calibration(path: str | os.PathLike, cal: Calibration) -> Path:
    p = Path(path)
    if p.is_dir():
        p = p / CALIBRATION_FILE
    header = ("# Calibration linking the Diana's forward kinematics to the base marker (fullperc_eval.ground_truth).\n"
              "# Metres, quaternions x y z w. T_a_b maps points of frame b into frame a.\n")
    p.write_text(header + yaml.safe_dump(cal.as_dict(), sort_keys=False, default_flow_style=None))
    return p


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
