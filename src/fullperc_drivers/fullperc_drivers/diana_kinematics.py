"""The one Diana 7 kinematic model (modified / Craig DH in pinocchio), shared by the driver and the simulator.

Why one module: the simulator generates the arm's "truth" and the ``diana_state`` driver turns joint
angles back into flange poses. If they used two copies of the DH table, a typo in one would look like
a tracker error in every evaluation. Both import :class:`DianaKinematics` from here.

Convention (reference/diana_eval.md §1.1, checked there against three public URDFs):
``T_{i-1,i} = RotX(alpha_{i-1}) · TransX(a_{i-1}) · RotZ(theta_i + q_i) · TransZ(d_i)``.
Because RotZ and TransZ commute, the fixed part of each joint is the placement
``RotX(alpha) · TransX(a) · RotZ(theta) · TransZ(d)`` followed by a revolute joint about its z axis.
The flange frame is the frame of joint 7 (the vendor's default TCP is the flange centre).
At q = 0 the arm points straight up and the flange is at (-0.087, 0, 1.3165) m.

A real controller may carry a calibrated table: the vendor SDK's ``getDH(a[7], alpha[7], d[7], theta[7])``
returns it (metres, radians, that array order); :meth:`DianaKinematics.from_getdh` builds the model from
those arrays. That ``getDH`` uses exactly this modified-DH convention is UNCERTAIN (the manuals do not say)
— compare its output with :data:`DIANA7_MDH` on the real robot before trusting it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from fullperc_common.transforms import make_T

N_JOINTS = 7
JOINT_NAMES = tuple(f"joint{i}" for i in range(1, N_JOINTS + 1))

# Rows i = 1..7: alpha_{i-1} [rad], a_{i-1} [m], d_i [m], theta offset_i [rad]  (reference/diana_eval.md §1.1)
DIANA7_MDH = np.array([
    [np.pi, 0.0, -0.2856, 0.0],
    [np.pi / 2, 0.0, 0.0, 0.0],
    [-np.pi / 2, 0.0, -0.4586, 0.0],
    [np.pi / 2, 0.065, 0.0, 0.0],
    [-np.pi / 2, -0.0528, -0.4554, 0.0],
    [-np.pi / 2, -0.0122, 0.0, np.pi],
    [-np.pi / 2, 0.087, -0.1169, 0.0],
])
DH_COLUMNS = ("alpha", "a", "d", "theta")

_DEG179 = np.deg2rad(179.0)
# Joint limits [rad] (Yeeman-Z xacro / joint_limits.yaml; catalogue agrees in degrees).
DIANA7_LOWER = np.array([-_DEG179, -np.pi / 2, -_DEG179, 0.0, -_DEG179, -_DEG179, -_DEG179])
DIANA7_UPPER = np.array([_DEG179, np.pi / 2, _DEG179, np.deg2rad(175.0), _DEG179, _DEG179, _DEG179])
DIANA7_VEL_LIMIT = np.array([2.967, 2.618, 2.618, 2.618, 3.1416, 3.1416, 3.840])  # rad/s
DIANA7_EFFORT = np.array([235.0, 235.0, 111.0, 111.0, 54.0, 54.0, 54.0])  # N m


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _as_tool_T(tool_offset) -> np.ndarray:
    """Tool offset as 4x4: accepts a 4x4 matrix or 7 numbers (x y z [m], qx qy qz qw)."""
    if tool_offset is None:
        return np.eye(4)
    arr = np.asarray(tool_offset, dtype=float)
    if arr.shape == (4, 4):
        T = arr.copy()
    elif arr.shape == (7,):
        T = make_T(arr[:3], arr[3:] / np.linalg.norm(arr[3:]))
    else:
        raise ValueError(f"tool_offset must be a 4x4 matrix or [x y z qx qy qz qw], got shape {arr.shape}")
    if not np.all(np.isfinite(T)) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) \
            or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError("tool_offset is not a finite rigid transform")
    return T


def _as_dh(dh) -> np.ndarray:
    if dh is None:
        return DIANA7_MDH.copy()
    arr = np.asarray(dh, dtype=float)
    if arr.shape != (N_JOINTS, 4):
        raise ValueError(f"DH table must be 7 rows of (alpha, a, d, theta), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("DH table contains NaN/inf")
    return arr


class DianaKinematics:
    """Forward kinematics of the Diana 7: ``fk(q)`` = T_diana_base_flange (4x4, metres)."""

    def __init__(self, dh=None, tool_offset=None, lower: Sequence[float] | None = None,
                 upper: Sequence[float] | None = None) -> None:
        self.dh = _as_dh(dh)
        self.tool_offset = _as_tool_T(tool_offset)
        self.lower = np.array(DIANA7_LOWER if lower is None else lower, dtype=float)
        self.upper = np.array(DIANA7_UPPER if upper is None else upper, dtype=float)
        if self.lower.shape != (N_JOINTS,) or self.upper.shape != (N_JOINTS,) or np.any(self.lower > self.upper):
            raise ValueError("joint limits must be two arrays of 7 with lower <= upper")
        self.model = self._build_model()
        self.data = self.model.createData()
        self._flange_id = self.model.getFrameId("diana_flange")
        self._tool_id = self.model.getFrameId("tool")

    @classmethod
    def from_getdh(cls, a: Sequence[float], alpha: Sequence[float], d: Sequence[float], theta: Sequence[float],
                   tool_offset=None) -> DianaKinematics:
        """Model from the vendor ``getDH`` arrays (order a, alpha, d, theta; metres and radians)."""
        cols = [np.asarray(v, dtype=float) for v in (alpha, a, d, theta)]
        if any(c.shape != (N_JOINTS,) for c in cols):
            raise ValueError("getDH arrays a, alpha, d, theta must each have 7 entries")
        return cls(dh=np.stack(cols, axis=1), tool_offset=tool_offset)

    @property
    def joint_limits(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lower.copy(), self.upper.copy()

    def _build_model(self) -> pin.Model:
        m = pin.Model()
        m.name = "diana7"
        parent = 0
        for i, (alpha, a, d, theta) in enumerate(self.dh):
            R = _rot_x(alpha) @ _rot_z(theta)
            p = np.array([a, 0.0, 0.0]) + _rot_x(alpha) @ np.array([0.0, 0.0, d])
            jid = m.addJoint(parent, pin.JointModelRZ(), pin.SE3(R, p), JOINT_NAMES[i],
                             np.array([DIANA7_EFFORT[i]]), np.array([DIANA7_VEL_LIMIT[i]]),
                             np.array([self.lower[i]]), np.array([self.upper[i]]))
            # Nominal inertia only so the model is well formed; no dynamics are computed with it.
            m.appendBodyToJoint(jid, pin.Inertia.FromSphere(1.0, 0.05), pin.SE3.Identity())
            m.addJointFrame(jid)
            parent = jid
        fl = m.addFrame(pin.Frame("diana_flange", parent, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
        m.addFrame(pin.Frame("tool", parent, fl, pin.SE3(self.tool_offset[:3, :3].copy(),
                                                         self.tool_offset[:3, 3].copy()), pin.FrameType.OP_FRAME))
        return m

    def _q(self, q) -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (N_JOINTS,):
            raise ValueError(f"q must have 7 joint angles, got {q.shape[0]}")
        if not np.all(np.isfinite(q)):
            raise ValueError("q contains NaN/inf")
        return q

    def fk(self, q) -> np.ndarray:
        """T_diana_base_flange (4x4, metres) for joint angles q [rad]."""
        pin.framesForwardKinematics(self.model, self.data, self._q(q))
        return self.data.oMf[self._flange_id].homogeneous.copy()

    def fk_tool(self, q) -> np.ndarray:
        """T_diana_base_tool = T_diana_base_flange · tool_offset."""
        pin.framesForwardKinematics(self.model, self.data, self._q(q))
        return self.data.oMf[self._tool_id].homogeneous.copy()

    def fk_many(self, Q, tool: bool = False) -> np.ndarray:
        """Batch FK: Q (N, 7) -> (N, 4, 4) flange (or tool) transforms."""
        Q = np.asarray(Q, dtype=float)
        if Q.ndim != 2 or Q.shape[1] != N_JOINTS:
            raise ValueError(f"Q must have shape (N, 7), got {Q.shape}")
        if not np.all(np.isfinite(Q)):   # _q's test, once for the batch (the evaluator's ground truth: ~7k rows)
            raise ValueError("q contains NaN/inf")
        fid = self._tool_id if tool else self._flange_id
        out = np.empty((Q.shape[0], 4, 4))
        # the joints' forward kinematics, then the one frame asked for (framesForwardKinematics places every frame
        # by the same product oMi[parent] * placement): the same matrix, a third less time per row (the ground
        # truth of an evaluation: ~11k rows) -- test_diana_kinematics.py pins it to fk / fk_tool bit for bit
        model, data, fk, place = self.model, self.data, pin.forwardKinematics, pin.updateFramePlacement
        for k, q in enumerate(Q):
            fk(model, data, q)
            out[k] = place(model, data, fid).homogeneous
        return out

    def joint_origins(self, q) -> np.ndarray:
        """Origins of the 7 joint frames in diana_base (7, 3) — for reach checks and drawing the arm."""
        pin.forwardKinematics(self.model, self.data, self._q(q))
        return np.array([self.data.oMi[j].translation for j in range(1, N_JOINTS + 1)])

    def link_transforms(self, q, root: str = "diana_base", tool: bool = False) -> list[tuple[str, str, np.ndarray]]:
        """The arm's TF tree for joint angles q: (parent, child, T_parent_child) for ``diana_link1..7`` (each in
        its parent link, ``diana_link1`` in ``root``), ``diana_flange`` (in ``diana_link7``) and, with ``tool``,
        ``diana_tool`` (the tool offset, in ``diana_flange``). Chained, they give :meth:`fk` / :meth:`fk_tool`."""
        pin.forwardKinematics(self.model, self.data, self._q(q))
        out, parent = [], root
        for j in range(1, N_JOINTS + 1):
            child = f"diana_link{j}"
            out.append((parent, child, self.data.liMi[j].homogeneous.copy()))
            parent = child
        out.append((parent, "diana_flange", self.model.frames[self._flange_id].placement.homogeneous.copy()))
        if tool:
            out.append(("diana_flange", "diana_tool", self.tool_offset.copy()))
        return out

    def within_limits(self, q) -> bool:
        q = self._q(q)
        return bool(np.all(q >= self.lower) and np.all(q <= self.upper))
