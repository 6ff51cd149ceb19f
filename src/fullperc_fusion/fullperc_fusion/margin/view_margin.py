"""View-margin model of the paper (§4.2, Algorithm 1) and the BVV / GVV / PVV labelling.

For a point p and every OMC camera pair (i, j) Algorithm 1 adds the pair's *view margin* 180° − β, where β is
the convergence angle between the two view vectors (camera -> p), provided that

  1. p is within the effective range of both cameras (resolution degradation; ``range_m``, default 4 m),
  2. p is inside both cameras' fields of view (here a rectangular pyramid: |x/z| <= tan(fov_h/2),
     |y/z| <= tan(fov_v/2), z > 0 in the OpenCV camera frame),
  3. β is in the acceptable convergence band (default 40°–140°, inclusive).

Our extension of Algorithm 1 (static occluders): when the layout lists ``occluders`` (boxes),

  * a camera also needs a clear line of sight to the point (checks 1-2 become "the camera sees p"), and
  * the BVV needs one too: the paper calls a point BVV when it is "inside the OTS measurement volume", which
    silently assumes that the OTS can look there. We label p BVV only when it is inside the OTS frustum **and**
    the segment from the OTS origin (``T_omc_ots`` translation, the device's reference point between its two
    lenses) to p passes through no occluder. Without this, a point below the table edge on the far side of the
    table from the OTS would be "BVV" although the table top hides it from the tracker, and a task planned
    through such a region would give the local tracker nothing to measure.

With no occluders both checks are always true and the model is exactly the paper's Algorithm 1. (One origin is a
simplification: the Vega's two lenses sit ~0.25 m either side of it, so right at an occluder's shadow edge one
lens may already be blocked while the origin still sees; the simulator models both lenses.)

Two implementations of the same arithmetic (float64):
  * :func:`compute_margin` — vectorized over many points (chunked, no Python loop over points);
  * :func:`margin_at` / :func:`label_point` — one point, small arrays only, for the node's per-pose path (tens of
    µs); the OTS line of sight is one more column in the cameras' slab test, so it costs almost nothing.
The room-scale map uses a faster float32 kernel in :mod:`fullperc_fusion.margin.map`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fullperc_fusion.margin.geometry import segments
from fullperc_fusion.margin.layout import SEGMENT_END, Layout

# Same values as fullperc_msgs/Region (pinned by test_margin.py); the core stays ROS-free.
UNKNOWN, BVV, GVV, PVV = 0, 1, 2, 3
REGION_NAMES = {UNKNOWN: "UNKNOWN", BVV: "BVV", GVV: "GVV", PVV: "PVV"}


@dataclass(frozen=True)
class MarginResult:
    """Per point: summed margin [deg], number of valid camera pairs, number of cameras that see the point."""

    margin_deg: np.ndarray
    valid_pairs: np.ndarray
    cameras_seeing: np.ndarray


def _as_points(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("points contain NaN or inf")
    return p


def camera_visibility(layout: Layout, points) -> tuple[np.ndarray, np.ndarray]:
    """Range, field-of-view and line-of-sight check for every (point, camera).

    Returns ``see`` (M, N) bool and the unit view vectors (M, N, 3), which point from the camera to the point.
    """
    p = _as_points(points)
    d = p[:, None, :] - layout.cam_pos[None, :, :]
    pc = np.einsum("mnk,nkj->mnj", d, layout.cam_R)  # R^T d: the point in each camera frame
    z = pc[..., 2]
    d2 = np.einsum("mnk,mnk->mn", pc, pc)
    see = ((d2 <= layout.range_m ** 2)
           & (np.abs(pc[..., 0]) <= layout.tan_h * z) & (np.abs(pc[..., 1]) <= layout.tan_v * z))
    if layout.occluders:
        seg = segments(layout.cam_pos[None, :, :], p[:, None, :])
        for box in layout.occluders:
            see &= ~box.blocks(None, None, seg)
    # |d| > 0 wherever see is True (the FOV test fails at a camera centre); the floor only avoids 0/0 elsewhere.
    u = d / np.sqrt(np.maximum(d2, 1e-300))[..., None]
    return see, u


def compute_margin(layout: Layout, points_omc, chunk: int = 4096) -> MarginResult:
    """Algorithm 1 for many points (N, 3) in the layout frame, vectorized over points and camera pairs."""
    p = _as_points(points_omc)
    n = len(p)
    pi, pj = layout.pair_i, layout.pair_j
    margin = np.zeros(n)
    pairs = np.zeros(n, dtype=np.int64)
    seeing = np.zeros(n, dtype=np.int64)
    for a in range(0, n, chunk):
        see, u = camera_visibility(layout, p[a:a + chunk])
        cosb = np.einsum("mpk,mpk->mp", u[:, pi, :], u[:, pj, :])
        valid = see[:, pi] & see[:, pj] & (cosb <= layout.cos_lo) & (cosb >= layout.cos_hi)
        beta = np.degrees(np.arccos(np.clip(cosb, -1.0, 1.0)))
        margin[a:a + chunk] = np.where(valid, 180.0 - beta, 0.0).sum(axis=1)
        pairs[a:a + chunk] = valid.sum(axis=1)
        seeing[a:a + chunk] = see.sum(axis=1)
    return MarginResult(margin, pairs, seeing)


_TRIU: dict[int, np.ndarray] = {}


def _single(layout: Layout, point) -> tuple[float, int, int, bool, bool]:
    """Algorithm 1 for one point plus the OTS tests: (margin, valid pairs, cameras seeing, in frustum, ots_los).

    Same tests as :func:`compute_margin` / :func:`ots_line_of_sight`, arranged for one point; numpy's per-call
    overhead dominates, so the work is packed into few calls on precomputed layout arrays: all camera-frame
    coordinates from one mat-vec, one slab test for every (line-of-sight origin, box) — the cameras and, as the
    last column, the OTS origin — and the pair angles from the Gram matrix of the seeing cameras' view vectors.
    """
    p = np.asarray(point, dtype=float)
    if p.shape != (3,):
        raise ValueError(f"point must be 3 finite numbers, got {point!r}")
    x, y, z = p.tolist()
    if not math.isfinite(x + y + z):
        raise ValueError(f"point must be 3 finite numbers, got {point!r}")
    n_cam = layout.fast_tan.shape[1]
    pc = (layout.fast_A @ p - layout.fast_b).reshape(3, n_cam)
    fov = np.abs(pc[:2]) <= layout.fast_tan * pc[2]
    d2 = (pc * pc).sum(0)
    see = fov[0] & fov[1] & (d2 <= layout.fast_r2)
    dT = p[:, None] - layout.fast_camT  # (3, N) or (3, N + 1): the last column is the OTS origin
    ots = layout.ots
    inside = los = ots is not None
    if ots is not None:
        inside = ots.contains_one_omc(x, y, z)
    K = layout.fast_K
    if K.size:
        # slab test as in Box.blocks: the segment meets the box iff max(t_enter, 0) <= min(t_exit, SEGMENT_END)
        t = K * np.reciprocal(dT + 1e-300)[:, :, None]
        a = np.minimum(t[0], t[1])
        b = np.maximum(t[0], t[1])
        free = (np.maximum(np.maximum(a[0], a[1]), np.maximum(a[2], 0.0))
                > np.minimum(np.minimum(b[0], b[1]), np.minimum(b[2], SEGMENT_END))).all(1)
        see &= free[:n_cam]
        if ots is not None:
            los = bool(free[n_cam])
    idx = see.nonzero()[0]
    m = len(idx)
    if m < 2:
        return 0.0, 0, m, inside, los
    u = dT[:, idx] / np.sqrt(d2[idx])
    flat = _TRIU.get(m)
    if flat is None:
        i, j = np.triu_indices(m, k=1)
        flat = _TRIU[m] = i * m + j  # upper-triangle pairs as flat indices into the m x m Gram matrix
    c = np.take(u.T @ u, flat)
    if layout.cos_lo == -layout.cos_hi:  # symmetric band (40-140 deg): one comparison
        cv = c[np.abs(c) <= layout.cos_lo]
    else:
        cv = c[(c <= layout.cos_lo) & (c >= layout.cos_hi)]
    if layout.cos_lo >= 1.0 or layout.cos_hi <= -1.0:  # a band reaching 0 or 180 deg: |c| may exceed 1 by an ulp
        cv = np.clip(cv, -1.0, 1.0)
    k = len(cv)
    return 180.0 * k - math.degrees(float(np.arccos(cv).sum())), k, m, inside, los


def margin_at(layout: Layout, point) -> tuple[float, int, int]:
    """Algorithm 1 for one point (3,): (margin [deg], valid pairs, cameras seeing). The node's per-pose path."""
    m, k, s, _, _ = _single(layout, point)
    return m, k, s


def in_local_volume(layout: Layout, points_omc) -> np.ndarray:
    """Bool (N,): inside the OTS measurement volume (the frustum only; False everywhere without an OTS)."""
    p = _as_points(points_omc)
    if layout.ots is None:
        return np.zeros(len(p), dtype=bool)
    return np.asarray(layout.ots.contains_omc(p), dtype=bool)


def ots_line_of_sight(layout: Layout, points_omc) -> np.ndarray:
    """Bool (N,): no occluder on the segment OTS origin -> point (False everywhere without an OTS)."""
    p = _as_points(points_omc)
    if layout.ots is None:
        return np.zeros(len(p), dtype=bool)
    clear = np.ones(len(p), dtype=bool)
    for box in layout.occluders:
        clear &= ~box.blocks(layout.ots.position, p)
    return clear


def in_bvv(layout: Layout, points_omc) -> np.ndarray:
    """Bool (N,): the BVV condition — inside the OTS frustum and in the OTS's line of sight."""
    inside = in_local_volume(layout, points_omc)
    if inside.any():
        inside[inside] = ots_line_of_sight(layout, _as_points(points_omc)[inside])
    return inside


def labels_from(margin_deg: np.ndarray, in_volume: np.ndarray, threshold_deg: float) -> np.ndarray:
    """BVV where ``in_volume`` (pass :func:`in_bvv`), else GVV where margin >= threshold, else PVV."""
    lab = np.where(np.asarray(margin_deg) >= threshold_deg, GVV, PVV).astype(np.uint8)
    lab[np.asarray(in_volume, dtype=bool)] = BVV
    return lab


def label_points(layout: Layout, points_omc) -> tuple[np.ndarray, MarginResult]:
    """Region labels (uint8, BVV=1 / GVV=2 / PVV=3) and the margin for points (N, 3) in the layout frame."""
    res = compute_margin(layout, points_omc)
    return labels_from(res.margin_deg, in_bvv(layout, points_omc), layout.threshold_deg), res


@dataclass(frozen=True)
class PointLabel:
    """One labelled point (the single-point path used by margin_node).

    ``in_local_volume``: inside the OTS frustum; ``ots_line_of_sight``: nothing blocks the OTS's view of the point.
    The label is BVV exactly when both hold.
    """

    label: int
    margin_deg: float
    valid_pairs: int
    cameras_seeing: int
    in_local_volume: bool
    ots_line_of_sight: bool = False


def label_point(layout: Layout, point_omc) -> PointLabel:
    """Label of one point (3,) in the layout frame, via the single-point path."""
    m, v, s, inside, los = _single(layout, point_omc)
    label = BVV if (inside and los) else (GVV if m >= layout.threshold_deg else PVV)
    return PointLabel(label, m, v, s, inside, los)
