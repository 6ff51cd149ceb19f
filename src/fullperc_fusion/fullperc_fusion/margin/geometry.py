"""Geometry of the OR layout's devices: OMC cameras, the tracker's measurement volume and static occluders.

The parts a :class:`~.layout.Layout` is made of, without the file: the view-margin model (:mod:`.view_margin`) and
the simulator test points against them, and the simulator builds scenes from them directly.

Frames (docs/nodes.md "Frames, stamps and units"):
  * ``omc``: the mocap world, z up; every position and orientation in the file is expressed in it.
    "Ground" in eq. (17) is the omc x-y plane.
  * OMC camera frames follow OpenCV: z = optical axis (forward), x right, y down. ``orientation`` is the
    quaternion (x y z w) of ``R = omc_from_camera`` (its third column is the viewing direction).
  * ``ots`` is the NDI device frame as the Vega reports poses in it: the measurement volume lies along
    **-z** (NDI volumes are described with negative z, e.g. the pyramid's far plane at z = -2400 mm, and
    real replies have Tz ~ -1900 mm); ``depth_axis: "+z"`` is accepted for trackers that look along +z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fullperc_common.transforms import apply_T, inv_T

#: NDI Polaris Vega pyramid volume as used by third-party code (reference/ndi.md §3.5, marked UNCERTAIN there):
#: (depth from the sensor [m], half width along x [m], half height along y [m]) at the near, middle and far planes.
NDI_PYRAMID_PLANES = ((0.950, 0.224, 0.240), (1.532, 0.398, 0.572), (2.400, 0.656, 0.783))
#: Extended pyramid: same as the pyramid to 2.4 m, far plane at 3.0 m. The cross-section beyond 2.4 m is not in our
#: sources; we continue the last segment of the pyramid linearly (an assumption, documented here).
NDI_EXTENDED_PLANES = NDI_PYRAMID_PLANES + (
    (3.000,
     0.656 + (0.656 - 0.398) / (2.400 - 1.532) * 0.600,
     0.783 + (0.783 - 0.572) / (2.400 - 1.532) * 0.600),
)

#: A segment camera -> point counts as blocked when it meets a box at a parameter t <= SEGMENT_END (t = 1 is the point),
#: so a point lying on an occluder's surface (a marker on the table top) is not hidden by that occluder.
SEGMENT_END = 1.0 - 1e-9


# --------------------------------------------------------------------------------------------- geometry helpers
def look_at_R(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """omc_from_camera of an OpenCV camera (z forward, x right, y down) at ``position`` looking at ``target``."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at_R: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def look_at_R_ndi(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """omc_from_ots rotation of an NDI tracker looking at ``target`` along its -z axis (x right, y up, z back)."""
    R = look_at_R(position, target, up)
    return np.column_stack([R[:, 0], -R[:, 1], -R[:, 2]])


def eq17_theta_prime_deg(theta_deg: float, phi_deg: float) -> float:
    """Paper eq. (17): angle θ' between the view vectors of two neighbouring, evenly mounted cameras.

    θ is the angle between the two view vectors' projections on the ground (≈ 360°/N for N cameras evenly
    around the room); φ is the angle between each view vector (camera -> object) and the ground (the mounting
    tilt, 30°-45° in the paper). For unit vectors with equal depression φ and azimuth difference θ,
    cos θ' = cos²φ cos θ + sin²φ = 1 + cos θ cos²φ - cos²φ, which is eq. (17).
    """
    c2 = math.cos(math.radians(phi_deg)) ** 2
    arg = 1.0 + math.cos(math.radians(theta_deg)) * c2 - c2
    return math.degrees(math.acos(max(-1.0, min(1.0, arg))))


# ------------------------------------------------------------------------------------------------- data classes
@dataclass(frozen=True)
class Camera:
    """One OMC camera. ``R`` maps camera-frame vectors into ``omc`` (omc_from_camera)."""

    name: str
    position: np.ndarray
    R: np.ndarray
    fov_h_deg: float
    fov_v_deg: float
    range_m: float
    resolution: tuple[int, int]

    @property
    def forward(self) -> np.ndarray:
        return self.R[:, 2]

    @property
    def quat_xyzw(self) -> np.ndarray:
        # imported here: margin_node's start does not need scipy.spatial
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(self.R).as_quat()

    @property
    def tilt_deg(self) -> float:
        """Angle of the optical axis below the ground plane (positive = looking down)."""
        return math.degrees(math.asin(max(-1.0, min(1.0, -float(self.forward[2])))))


@dataclass(frozen=True)
class Frustum:
    """Measurement volume of a tracker in its own frame: a stack of rectangular cross-sections.

    ``planes`` rows are (depth [m], half width along x [m], half height along y [m]) with strictly increasing depth;
    between rows the half sizes are interpolated linearly (the NDI pyramid is two such segments). ``depth_axis``
    says along which axis depth grows: "-z" for NDI trackers.
    """

    planes: np.ndarray
    depth_axis: str = "-z"
    _rows: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # plain-Python copy of the planes for contains_one (tolist() per call costs more than the test itself)
        object.__setattr__(self, "_rows", tuple(tuple(r) for r in np.asarray(self.planes, float).tolist()))

    @property
    def near_m(self) -> float:
        return float(self.planes[0, 0])

    @property
    def far_m(self) -> float:
        return float(self.planes[-1, 0])

    def contains(self, points_ots) -> np.ndarray:
        """Bool (N,) for points (N, 3) given in the tracker frame; a single (3,) point gives a 0-d bool array."""
        p = np.asarray(points_ots, dtype=float)
        d = -p[..., 2] if self.depth_axis == "-z" else p[..., 2]
        hw = np.interp(d, self.planes[:, 0], self.planes[:, 1])
        hh = np.interp(d, self.planes[:, 0], self.planes[:, 2])
        return (d >= self.near_m) & (d <= self.far_m) & (np.abs(p[..., 0]) <= hw) & (np.abs(p[..., 1]) <= hh)

    def contains_one(self, x: float, y: float, z: float) -> bool:
        """:meth:`contains` for one point, in plain Python (a few µs instead of ~15 µs of small numpy calls)."""
        d = -z if self.depth_axis == "-z" else z
        rows = self._rows
        if not (rows[0][0] <= d <= rows[-1][0]):
            return False
        d0, w0, h0 = rows[0]
        for d1, w1, h1 in rows[1:]:
            if d <= d1:
                f = (d - d0) / (d1 - d0)
                return abs(x) <= w0 + f * (w1 - w0) and abs(y) <= h0 + f * (h1 - h0)
            d0, w0, h0 = d1, w1, h1
        return False

    def corners(self) -> np.ndarray:
        """(M, 4, 3) corners of every cross-section in the tracker frame (for drawing)."""
        s = -1.0 if self.depth_axis == "-z" else 1.0
        out = []
        for d, hw, hh in self.planes:
            out.append([[x, y, s * d] for x, y in ((-hw, -hh), (hw, -hh), (hw, hh), (-hw, hh))])
        return np.asarray(out)


@dataclass(frozen=True)
class Ots:
    """The local tracker: its pose in ``omc`` and its measurement volume."""

    name: str
    T_omc_ots: np.ndarray
    frustum: Frustum
    volume: str
    _pose: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # (tx, ty, tz, R00, R10, R20, R01, R11, R21, R02, R12, R22): origin and the columns of R as Python floats,
        # for contains_one_omc
        T = np.asarray(self.T_omc_ots, dtype=float)
        object.__setattr__(self, "_pose", tuple(T[:3, 3].tolist() + T[:3, :3].T.ravel().tolist()))

    @property
    def position(self) -> np.ndarray:
        """The OTS origin in ``omc`` (the device's reference point; lines of sight start here)."""
        return self.T_omc_ots[:3, 3]

    def contains(self, points_ots) -> np.ndarray:
        return self.frustum.contains(points_ots)

    def contains_one_omc(self, x: float, y: float, z: float) -> bool:
        """:meth:`contains_omc` for one point in plain Python: R^T (p - t), then the frustum test."""
        tx, ty, tz, a0, a1, a2, b0, b1, b2, c0, c1, c2 = self._pose
        dx, dy, dz = x - tx, y - ty, z - tz
        return self.frustum.contains_one(a0 * dx + a1 * dy + a2 * dz, b0 * dx + b1 * dy + b2 * dz,
                                         c0 * dx + c1 * dy + c2 * dz)

    def contains_omc(self, points_omc) -> np.ndarray:
        """Bool (N,) for points (N, 3) in ``omc``: inside the measurement volume (the BVV)."""
        return self.frustum.contains(apply_T(inv_T(self.T_omc_ots), points_omc))


def segments(origin, points) -> tuple[np.ndarray, np.ndarray]:
    """(origin, 1 / direction) of the segments origin -> points, as :meth:`Box.blocks` takes them: the part of its
    slab test that does not depend on the box (a third of it), for a caller testing the same segments against
    every occluder."""
    c = np.asarray(origin, dtype=float)
    d = np.asarray(points, dtype=float) - c
    return c, 1.0 / (d + 1e-300)  # d == 0 -> a huge finite slope instead of inf/NaN; no effect otherwise


@dataclass(frozen=True)
class Box:
    """A static axis-aligned occluder in ``omc``."""

    name: str
    lo: np.ndarray
    hi: np.ndarray

    def blocks(self, origin, points, seg: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Bool: the segment origin -> point passes through the box before reaching the point.

        ``origin`` and ``points`` broadcast against each other (e.g. one camera (3,) and points (N, 3), cameras
        (N, 3) and one point (3,), or (1, N, 3) against (M, 1, 3)). ``seg``: :func:`segments` of the same
        origin and points, when the caller tests them against several boxes (computed once: the same numbers).

        Slab method: the segment meets the box where [tmin, tmax] overlaps [0, SEGMENT_END]. A point lying on the box
        surface is not hidden by it; a point inside the box is.
        """
        c, inv = seg if seg is not None else segments(origin, points)
        t1 = (self.lo - c) * inv
        t2 = (self.hi - c) * inv
        a = np.minimum(t1, t2)
        b = np.maximum(t1, t2)
        # the max / min over the three axes, pairwise: a reduction along a last axis of 3 was half the evaluator's
        # margin time; the same values (a zero's sign aside, which no comparison below sees; NaN propagates alike)
        tmin = np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])
        tmax = np.minimum(np.minimum(b[..., 0], b[..., 1]), b[..., 2])
        return np.maximum(tmin, 0.0) <= np.minimum(tmax, SEGMENT_END)
