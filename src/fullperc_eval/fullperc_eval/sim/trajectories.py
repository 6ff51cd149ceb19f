"""Diana 7 trajectories: single-joint arcs with smooth (minimum-jerk) velocity profiles.

The paper's protocol (§5.2) moves only one revolute joint at a time, so the target on the flange
follows a circular arc whose accuracy rests on the joint encoder. A :class:`JointArc` holds the
arm still for ``hold_start`` seconds, moves joint ``joint`` from ``start`` to ``end`` along a
minimum-jerk profile (zero velocity and acceleration at both ends, so no step in the commanded
motion can masquerade as a tracker hop), and holds again for ``hold_end`` seconds.

Kinematics come from the project's single Diana model, :class:`fullperc_drivers.diana_kinematics.
DianaKinematics` (no second DH table here); :func:`arm_geometry` evaluates it in batches and also
returns the joint origins, from which the arm's own links become occluding capsules.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from fullperc_drivers.diana_kinematics import N_JOINTS, DianaKinematics


def min_jerk(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-jerk position s(u) = 10u^3 - 15u^4 + 6u^5 and ds/du on u in [0, 1] (clipped outside)."""
    u = np.clip(u, 0.0, 1.0)
    s = u**3 * (10 - 15 * u + 6 * u**2)
    ds = 30 * u**2 * (1 - u) ** 2
    return s, ds


@dataclass(frozen=True)
class JointArc:
    """Hold, move one joint from ``start`` to ``end`` [rad] in ``move`` seconds, hold. Other joints fixed at q0."""

    q0: tuple[float, ...]
    joint: int  # 0-based joint index
    start: float
    end: float
    move: float
    hold_start: float = 2.0
    hold_end: float = 2.0

    def __post_init__(self) -> None:
        if len(self.q0) != N_JOINTS or not 0 <= self.joint < N_JOINTS:
            raise ValueError("JointArc needs 7 joint angles and a joint index 0..6")
        if self.move <= 0 or self.hold_start < 0 or self.hold_end < 0:
            raise ValueError("JointArc durations must be positive")

    @property
    def duration(self) -> float:
        return self.hold_start + self.move + self.hold_end

    @property
    def peak_velocity(self) -> float:
        """Peak joint speed [rad/s] of the minimum-jerk profile (1.875 x mean speed)."""
        return 1.875 * abs(self.end - self.start) / self.move

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions and velocities (N, 7) at times t [s] from the start of the task."""
        t = np.asarray(t, dtype=float)
        s, ds = min_jerk((t - self.hold_start) / self.move)
        Q = np.tile(np.asarray(self.q0, dtype=float), (t.size, 1))
        dQ = np.zeros_like(Q)
        Q[:, self.joint] = self.start + (self.end - self.start) * s
        dQ[:, self.joint] = (self.end - self.start) * ds / self.move
        return Q, dQ


def arm_geometry(dk: DianaKinematics, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batch FK: Q (N, 7) -> joint origins (N, 7, 3) and flange transforms (N, 4, 4), both in diana_base."""
    Q = np.asarray(Q, dtype=float)
    origins = np.empty((len(Q), N_JOINTS, 3))
    flange = np.empty((len(Q), 4, 4))
    fid = dk.model.getFrameId("diana_flange")
    for k, q in enumerate(Q):
        pin.framesForwardKinematics(dk.model, dk.data, q)
        for j in range(N_JOINTS):
            origins[k, j] = dk.data.oMi[j + 1].translation
        flange[k] = dk.data.oMf[fid].homogeneous
    return origins, flange


# Link capsules along the chain: (from, to) indices into [diana_base origin, joint origins 1..7], radius [m].
# Radii approximate the Diana 7 housings (≈ 0.16 m base, tapering to ≈ 0.09 m at the wrist).
LINKS: tuple[tuple[int, int, float], ...] = (
    (0, 1, 0.08),  # base column to shoulder
    (2, 3, 0.065),  # upper arm
    (3, 4, 0.06),  # elbow offset
    (4, 5, 0.055),  # forearm
    (5, 6, 0.05),  # wrist
    (6, 7, 0.045),  # wrist to flange
)


def link_capsules(origins: np.ndarray, T_omc_base: np.ndarray, flange_clearance: float = 0.03,
                  links: tuple[tuple[int, int, float], ...] = LINKS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arm links as capsules in omc: (N, L, 3) start, (N, L, 3) end, (L,) radius.

    The last link stops ``flange_clearance`` short of the flange so the capsule's round cap does not
    swallow a tool mounted on the flange face.
    """
    N = origins.shape[0]
    pts = np.concatenate([np.zeros((N, 1, 3)), origins], axis=1)
    pts = pts @ T_omc_base[:3, :3].T + T_omc_base[:3, 3]
    a = np.stack([pts[:, i] for i, _, _ in links], axis=1)
    b = np.stack([pts[:, j] for _, j, _ in links], axis=1)
    r = np.array([rad for _, _, rad in links])
    last = b[:, -1] - a[:, -1]
    ln = np.linalg.norm(last, axis=-1, keepdims=True)
    b[:, -1] = b[:, -1] - last / np.maximum(ln, 1e-9) * np.minimum(flange_clearance + r[-1], 0.5 * ln)
    return a, b, r
