"""Occluder geometry: capsules (staff, the arm's own links) and boxes (table, equipment).

Line of sight is decided by pure geometry, vectorised over many rays and occluders at once, so
the OMC/OTS models can test every marker x camera ray of a whole chunk of frames in one call.
A ray is a segment from a marker to a camera centre; it is blocked when it passes within a
capsule's radius of the capsule's axis segment, or through a box.

A box is the margin model's :class:`fullperc_fusion.margin.layout.Box` (axis-aligned, ``lo``/``hi``) given in its own
frame and placed in ``omc`` by a rotation and a centre (:class:`PlacedBox`): the layout's occluders unrotated,
scene.yaml's obstacles and the robot's cart turned about z. The segment test here is the simulator's own: a ray
counts as blocked when it touches the box anywhere on [marker, camera], both ends included, where the margin
model's :meth:`~fullperc_fusion.margin.layout.Box.blocks` spares a point lying on the box's surface.

Staff walk seeded paths (:class:`StaffWalker`): each person moves through random waypoints
inside a rectangular floor zone with a smooth (raised-cosine) speed profile between waypoints,
so occlusion starts and ends gradually, as when a person steps into a camera's line of sight.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from fullperc_fusion.margin.layout import Box

_EPS = 1e-12


def segment_segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Minimum distance between segments [p1, q1] and [p2, q2] (broadcast over leading axes, last axis 3).

    Closest-point algorithm of Ericson, *Real-Time Collision Detection* §5.1.9, vectorised; both
    degenerate cases (zero-length segments) are handled.
    """
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    a, e, f, c, b = np.broadcast_arrays(a, e, f, c, b)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > _EPS, np.clip((b * f - c * e) / np.where(denom > _EPS, denom, 1.0), 0.0, 1.0), 0.0)
        t = np.where(e > _EPS, (b * s + f) / np.where(e > _EPS, e, 1.0), 0.0)
        a_safe = np.where(a > _EPS, a, 1.0)
        s_lo = np.where(a > _EPS, np.clip(-c / a_safe, 0.0, 1.0), 0.0)
        s_hi = np.where(a > _EPS, np.clip((b - c) / a_safe, 0.0, 1.0), 0.0)
    s = np.where(t < 0.0, s_lo, np.where(t > 1.0, s_hi, s))
    t = np.clip(t, 0.0, 1.0)
    c1 = p1 + d1 * s[..., None]
    c2 = p2 + d2 * t[..., None]
    return np.linalg.norm(c1 - c2, axis=-1)


# A (ray, occluder) pair is decided by the exact test only where a cheap bound cannot rule it out (most pairs of a
# frame are far apart: ~3 % of the ray x capsule pairs and ~20 % of the ray x box pairs of a task remain). The bound
# keeps this margin [m]: many orders above the rounding of either computation on room-sized coordinates, so a pair it
# rules out is one the exact test does not block either, and the exact test itself runs unchanged on the pairs kept
# (the same operations per element: the same result; test_twin_profiles.py pins both forms equal).
_CULL_M = 1e-6


def rays_blocked_by_capsules(ray_a: np.ndarray, ray_b: np.ndarray, cap_a: np.ndarray, cap_b: np.ndarray,
                             cap_r: np.ndarray, *, cull: bool = True) -> np.ndarray:
    """Which rays pass through any capsule.

    ray_a, ray_b: (F, R, 3) ray end points per frame; cap_a, cap_b: (F, K, 3) capsule axis end
    points; cap_r: (K,) radii. Returns (F, R) bool. ``cull``: the exact distance only for the (ray, capsule) pairs
    within reach of each other (:data:`_CULL_M`: a capsule lies in the ball about its axis' midpoint of radius half
    its length plus its radius); False: for every pair (the plain form, same result).
    """
    if cap_a.shape[1] == 0:
        return np.zeros(ray_a.shape[:2], dtype=bool)
    if not cull:
        d = segment_segment_distance(ray_a[:, :, None, :], ray_b[:, :, None, :], cap_a[:, None, :, :],
                                     cap_b[:, None, :, :])
        return np.any(d < cap_r[None, None, :], axis=-1)
    mid = 0.5 * (cap_a + cap_b)                                                  # (F, K, 3)
    reach = 0.5 * np.sqrt(np.einsum("fki,fki->fk", cap_b - cap_a, cap_b - cap_a)) + cap_r + _CULL_M
    d = ray_b - ray_a                                                            # (F, R, 3)
    w = mid[:, None, :, :] - ray_a[:, :, None, :]                                # (F, R, K, 3): ray start -> midpoint
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(np.einsum("frki,fri->frk", w, d) / np.einsum("fri,fri->fr", d, d)[:, :, None], 0.0, 1.0)
    w -= d[:, :, None, :] * s[..., None]                                         # closest point of the ray -> midpoint
    near = ~(np.einsum("frki,frki->frk", w, w) > (reach * reach)[:, None, :])   # NaN (e.g. a zero-length ray): kept
    f, r, k = np.nonzero(near)
    out = np.zeros(ray_a.shape[:2], dtype=bool)
    if f.size:
        hit = segment_segment_distance(ray_a[f, r], ray_b[f, r], cap_a[f, k], cap_b[f, k]) < cap_r[k]
        out[f[hit], r[hit]] = True
    return out


@dataclass(frozen=True)
class PlacedBox:
    """An oriented box: the margin model's :class:`~fullperc_fusion.margin.layout.Box` centred in its own frame
    (``lo = -half``, ``hi = half``), placed in omc by ``center`` and ``R`` (omc_from_box)."""

    box: Box
    center: np.ndarray
    R: np.ndarray

    @classmethod
    def of(cls, name: str, center: np.ndarray, R: np.ndarray, half: np.ndarray) -> PlacedBox:
        """A box of half extents ``half`` [m] centred at ``center`` with rotation ``R`` (omc_from_box)."""
        half = np.asarray(half, dtype=float)
        return cls(Box(name, -half, half), np.asarray(center, dtype=float), np.asarray(R, dtype=float))

    @classmethod
    def from_layout(cls, b: Box) -> PlacedBox:
        """One of the layout's axis-aligned occluders (``lo``/``hi`` in omc)."""
        lo, hi = np.asarray(b.lo), np.asarray(b.hi)
        return cls.of(b.name, (lo + hi) / 2, np.eye(3), (hi - lo) / 2)

    @property
    def name(self) -> str:
        return self.box.name

    @functools.cached_property
    def upright(self) -> bool:
        """R is exactly the identity (axis-aligned in omc)."""
        return bool(np.array_equal(self.R, np.eye(3)))

    @property
    def half(self) -> np.ndarray:
        """Half extents along the box's own axes [m]."""
        return self.box.hi


def rays_blocked_by_boxes(ray_a: np.ndarray, ray_b: np.ndarray, boxes: list[PlacedBox], *,
                          cull: bool = True) -> np.ndarray:
    """Which segments [ray_a, ray_b] (shape (..., 3)) cross any of the static boxes (slab test). ``cull``: the slab
    test only for the segments whose bounding box (in the box's frame) reaches the box (:data:`_CULL_M`), an upright
    box's frame without the product (:func:`_into`); False: for every segment (the plain form, same result)."""
    blocked = np.zeros(ray_a.shape[:-1], dtype=bool)
    for box in boxes:
        if not cull or blocked.ndim == 0:
            a = (ray_a - box.center) @ box.R  # into the box frame (R^T x, row-vector form)
            b = (ray_b - box.center) @ box.R
            blocked |= _slab(a, b, box.half)
            continue
        a, b = _into(ray_a, box), _into(ray_b, box)
        # both ends beyond one face (by the margin): the segment cannot meet the box
        apart = ((np.minimum(a, b) > box.half + _CULL_M) | (np.maximum(a, b) < -box.half - _CULL_M)).any(axis=-1)
        near = np.nonzero(~apart)
        blocked[near] |= _slab(a[near], b[near], box.half)
    return blocked


def _into(x: np.ndarray, box: PlacedBox) -> np.ndarray:
    """Points ``x`` (..., 3) in ``box``'s frame: (x - centre) @ R (R^T x, row-vector form). An upright box (R the
    identity, as every layout box): the difference alone, which is what the product gives for finite points (x * 1
    + 0 + 0, at most a zero's sign differs, which no test of :func:`_slab` sees) without its cost."""
    d = x - box.center
    if box.upright and np.isfinite(d).all():
        return d
    return d @ box.R


def _slab(a: np.ndarray, b: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Whether each segment [a, b] (..., 3), in a box's frame, meets the box [-half, half], both ends included."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - a) * inv
        t2 = (half - a) * inv
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    # a coordinate the segment is parallel to: inside the slab -> no constraint, else never hits
    par = np.abs(d) < _EPS
    inside = np.abs(a) <= half
    tmin = np.where(par, np.where(inside, -np.inf, np.inf), tmin)
    tmax = np.where(par, np.where(inside, np.inf, -np.inf), tmax)
    t_enter = np.max(tmin, axis=-1)
    t_exit = np.min(tmax, axis=-1)
    return (t_enter <= t_exit) & (t_exit >= 0.0) & (t_enter <= 1.0)


def points_in_boxes(points: np.ndarray, boxes: list[PlacedBox], margin: float = 0.0) -> np.ndarray:
    """(..., 3) points -> bool, True where a point lies inside any box grown by ``margin``."""
    out = np.zeros(points.shape[:-1], dtype=bool)
    for box in boxes:
        local = (points - box.center) @ box.R
        out |= np.all(np.abs(local) <= box.half + margin, axis=-1)
    return out


@dataclass
class StaffWalker:
    """One person as a vertical capsule walking seeded random waypoints inside a floor rectangle.

    zone: (xmin, xmax, ymin, ymax) in the omc frame (floor at z = floor_z). Between waypoints the
    person moves with a raised-cosine speed profile (smooth start and stop) at ``speed`` mean
    speed, then pauses ``pause`` seconds. The whole path is drawn from ``rng`` once, so the same
    seed gives the same walk.
    """

    name: str
    zone: tuple[float, float, float, float]
    radius: float
    height: float
    speed: float
    pause: float
    duration: float
    rng: np.random.Generator
    floor_z: float = 0.0
    _t: np.ndarray = field(init=False, repr=False)
    _xy: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        x0, x1, y0, y1 = self.zone
        pts = [np.array([self.rng.uniform(x0, x1), self.rng.uniform(y0, y1)])]
        times = [0.0]
        t = 0.0
        while t < self.duration + 1.0:
            nxt = np.array([self.rng.uniform(x0, x1), self.rng.uniform(y0, y1)])
            seg = float(np.linalg.norm(nxt - pts[-1])) / max(self.speed, 1e-6)
            t += max(seg, 0.1)
            pts.append(nxt)
            times.append(t)
            t += self.pause
            pts.append(nxt)
            times.append(t)
        self._t = np.asarray(times)
        self._xy = np.stack(pts)

    def xy(self, t: np.ndarray) -> np.ndarray:
        """Floor position (N, 2) at times t [s]."""
        t = np.clip(np.asarray(t, dtype=float), self._t[0], self._t[-1])
        i = np.clip(np.searchsorted(self._t, t, side="right") - 1, 0, len(self._t) - 2)
        span = self._t[i + 1] - self._t[i]
        u = np.where(span > 0, (t - self._t[i]) / np.where(span > 0, span, 1.0), 0.0)
        s = 0.5 - 0.5 * np.cos(np.pi * u)  # raised cosine: zero velocity at both ends
        return self._xy[i] + (self._xy[i + 1] - self._xy[i]) * s[:, None]

    def capsule(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Capsule axis end points (N, 3), (N, 3) at times t: from the knees' height to the head."""
        xy = self.xy(t)
        lo = np.column_stack([xy, np.full(len(xy), self.floor_z + self.radius)])
        hi = np.column_stack([xy, np.full(len(xy), self.floor_z + self.height - self.radius)])
        return lo, hi
