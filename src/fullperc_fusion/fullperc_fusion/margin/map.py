"""Margin map of a room grid (BVV / GVV / PVV everywhere) and a PNG heatmap slice for reports.

A 6 x 5 x 3 m room at 2 cm is ~11 M points x 66 camera pairs, so this does not call
:func:`.view_margin.compute_margin` (float64, ``arccos`` per pair: ~10 ns per element here). It runs the
same Algorithm 1 with a dedicated kernel:

  * the grid is processed in column blocks (bx x by x all z) on a thread pool (numpy releases the GIL);
  * per camera and block: range / field-of-view / line-of-sight test and unit view vectors, in float32;
  * per camera pair: one dot product, then ``180° − β`` is read from a 65 537-entry table indexed by cos β that already
    holds 0 outside the convergence band, so there is no ``arccos`` and no band comparison per element;
  * camera pairs (and cameras, occluders, the OTS test) that cannot matter for a block are skipped;
  * the BVV test (OTS frustum and the OTS's line of sight, :func:`.view_margin.in_bvv`) runs in float64
    on the blocks that overlap the frustum's bounding box, so the map's BVV is exactly that of ``label_points``.

Accuracy against the float64 path: a table bin is 2/65536 wide in cos β, i.e. at most ~0.0014° of β per pair inside
the 40°–140° band (|dβ/dcos β| <= 1/sin 40°), ~0.1° for a point with all 66 pairs valid; a pair whose β lies within
that distance of a band edge may be classified differently. ``test_margin_map.py`` checks both bounds.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fullperc_fusion.margin.layout import Layout
from fullperc_fusion.margin.view_margin import BVV, GVV, PVV, REGION_NAMES, in_bvv, labels_from

TABLE_BINS = 1 << 16
_SEGMENT_END32 = np.float32(1.0 - 1e-6)  # float32 cannot hold layout.SEGMENT_END (1 - 1e-9)


@dataclass
class MarginMap:
    """Values on a regular grid: ``x = origin[0] + i * resolution`` etc.; arrays are indexed [i, j, k]."""

    origin: np.ndarray
    resolution: float
    margin_deg: np.ndarray  # float32
    valid_pairs: np.ndarray  # uint8
    cameras_seeing: np.ndarray  # uint8
    labels: np.ndarray  # uint8: BVV=1, GVV=2, PVV=3
    threshold_deg: float
    frame_id: str = "omc"

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.margin_deg.shape)  # type: ignore[return-value]

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(self.origin[a] + np.arange(n) * self.resolution for a, n in enumerate(self.shape))  # type: ignore

    def points(self) -> np.ndarray:
        """All grid points (N, 3) in C order of the arrays (only sensible for small maps)."""
        xs, ys, zs = self.axes()
        return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)

    def fractions(self) -> dict[str, float]:
        n = self.labels.size
        return {name: float(np.count_nonzero(self.labels == v)) / n for name, v in (("BVV", BVV), ("GVV", GVV),
                                                                                    ("PVV", PVV))}


def grid_axis(lo: float, hi: float, resolution: float) -> np.ndarray:
    """lo, lo + r, ... up to hi inclusive (within 1e-6 of a step)."""
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be a positive number, got {resolution!r}")
    n = int(math.floor((hi - lo) / resolution + 1e-6)) + 1
    return lo + np.arange(max(n, 1)) * resolution


def margin_table(lo_deg: float, hi_deg: float, bins: int = TABLE_BINS) -> np.ndarray:
    """float32 table over cos β in [-1, 1]: entry b holds 180° − β at the bin centre, 0 outside [lo, hi]."""
    c = -1.0 + (np.arange(bins + 1) + 0.5) * (2.0 / bins)
    beta = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return np.where((beta >= lo_deg) & (beta <= hi_deg), 180.0 - beta, 0.0).astype(np.float32)


class _Kernel:
    """Per-layout constants of the float32 kernel."""

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        self.pos = layout.cam_pos.astype(np.float32)
        self.R = layout.cam_R.astype(np.float32)
        self.tan_h = layout.tan_h.astype(np.float32)
        self.tan_v = layout.tan_v.astype(np.float32)
        self.r2 = (layout.range_m ** 2).astype(np.float32)
        self.table = margin_table(*layout.convergence_deg)
        self.half_bins = np.float32(TABLE_BINS / 2)
        self.pairs = list(zip(layout.pair_i.tolist(), layout.pair_j.tolist(), strict=True))
        self.boxes = [(b.lo.astype(np.float32), b.hi.astype(np.float32), b.lo, b.hi) for b in layout.occluders]

    def run(self, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray):
        """Margin, valid pairs and seeing cameras for the block xs x ys x zs (C order, flattened)."""
        shape = (len(xs), len(ys), len(zs))
        X = np.broadcast_to(xs.astype(np.float32)[:, None, None], shape).ravel()
        Y = np.broadcast_to(ys.astype(np.float32)[None, :, None], shape).ravel()
        Z = np.broadcast_to(zs.astype(np.float32)[None, None, :], shape).ravel()
        blo = np.array([xs[0], ys[0], zs[0]])
        bhi = np.array([xs[-1], ys[-1], zs[-1]])
        n = X.size
        seeing = np.zeros(n, dtype=np.uint8)
        units: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None] = []
        for c in range(len(self.pos)):
            cx, cy, cz = self.pos[c]
            dx, dy, dz = X - cx, Y - cy, Z - cz
            R = self.R[c]
            zc = dx * R[0, 2] + dy * R[1, 2] + dz * R[2, 2]
            xc = dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0]
            yc = dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1]
            d2 = dx * dx + dy * dy + dz * dz
            see = (d2 <= self.r2[c]) & (zc > 0)
            see &= np.abs(xc) <= self.tan_h[c] * zc
            see &= np.abs(yc) <= self.tan_v[c] * zc
            if not see.any():
                units.append(None)
                continue
            cam64 = self.layout.cam_pos[c]
            for lo32, hi32, lo, hi in self.boxes:
                # The segments camera -> block points lie in the box hull of the camera and the block.
                if np.any(np.maximum(bhi, cam64) < lo) or np.any(np.minimum(blo, cam64) > hi):
                    continue
                see &= ~_slab_blocked(self.pos[c], dx, dy, dz, lo32, hi32)
            if not see.any():
                units.append(None)
                continue
            seeing += see
            inv = np.float32(1.0) / np.sqrt(np.maximum(d2, np.float32(1e-12)))  # finite even at a camera centre
            units.append((dx * inv, dy * inv, dz * inv, see))
        margin = np.zeros(n, dtype=np.float32)
        pairs = np.zeros(n, dtype=np.uint8)
        for i, j in self.pairs:
            ui, uj = units[i], units[j]
            if ui is None or uj is None:
                continue
            both = ui[3] & uj[3]
            if not both.any():
                continue
            cosb = ui[0] * uj[0]
            cosb += ui[1] * uj[1]
            cosb += ui[2] * uj[2]
            cosb += np.float32(1.0)
            cosb *= self.half_bins
            val = np.take(self.table, cosb.astype(np.int32), mode="clip")
            val *= both
            margin += val
            pairs += val > 0
        return margin, pairs, seeing


def _slab_blocked(c32: np.ndarray, dx, dy, dz, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """float32 slab test of the segments c -> c + d against one box, same formula as ``layout.Box.blocks``."""
    tmin = tmax = None
    for a, d in enumerate((dx, dy, dz)):
        inv = np.float32(1.0) / (d + np.float32(1e-30))  # finite at d == 0, like Box.blocks
        t1 = (lo[a] - c32[a]) * inv
        t2 = (hi[a] - c32[a]) * inv
        tl = np.minimum(t1, t2)
        th = np.maximum(t1, t2)
        tmin = tl if tmin is None else np.maximum(tmin, tl)
        tmax = th if tmax is None else np.minimum(tmax, th)
    return np.maximum(tmin, np.float32(0.0)) <= np.minimum(tmax, _SEGMENT_END32)


def compute_margin_map(layout: Layout, resolution: float = 0.1, lo=None, hi=None, block: int = 16,
                       threads: int | None = None) -> MarginMap:
    """Margin, valid pairs, seeing cameras and region label on the grid lo..hi (default: the layout's room)."""
    lo = np.asarray(layout.room_min if lo is None else lo, dtype=float)
    hi = np.asarray(layout.room_max if hi is None else hi, dtype=float)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi < lo):
        raise ValueError(f"map bounds must be two 3-vectors with hi >= lo, got {lo} {hi}")
    xs, ys, zs = (grid_axis(lo[a], hi[a], resolution) for a in range(3))
    shape = (len(xs), len(ys), len(zs))
    margin = np.empty(shape, dtype=np.float32)
    pairs = np.empty(shape, dtype=np.uint8)
    seeing = np.empty(shape, dtype=np.uint8)
    inside = np.zeros(shape, dtype=bool)
    kernel = _Kernel(layout)
    ots_box = _ots_aabb(layout)

    def work(ij: tuple[int, int]) -> None:
        i0, j0 = ij
        bx, by = xs[i0:i0 + block], ys[j0:j0 + block]
        m, p, s = kernel.run(bx, by, zs)
        sub = (slice(i0, i0 + len(bx)), slice(j0, j0 + len(by)), slice(None))
        margin[sub] = m.reshape(len(bx), len(by), len(zs))
        pairs[sub] = p.reshape(len(bx), len(by), len(zs))
        seeing[sub] = s.reshape(len(bx), len(by), len(zs))
        if ots_box is not None and not (np.any([bx[-1], by[-1], zs[-1]] < ots_box[0])
                                        or np.any([bx[0], by[0], zs[0]] > ots_box[1])):
            pts = np.stack(np.meshgrid(bx, by, zs, indexing="ij"), axis=-1).reshape(-1, 3)
            inside[sub] = in_bvv(layout, pts).reshape(len(bx), len(by), len(zs))  # frustum + line of sight

    jobs = [(i0, j0) for i0 in range(0, shape[0], block) for j0 in range(0, shape[1], block)]
    nthreads = threads or min(os.cpu_count() or 1, 8)
    if nthreads <= 1:
        for job in jobs:
            work(job)
    else:
        with ThreadPoolExecutor(nthreads) as ex:
            for _ in ex.map(work, jobs):
                pass
    labels = labels_from(margin, inside, layout.threshold_deg)
    return MarginMap(np.array([xs[0], ys[0], zs[0]]), float(resolution), margin, pairs, seeing, labels,
                     float(layout.threshold_deg), layout.frame_id)


def _ots_aabb(layout: Layout):
    """Axis-aligned bounds of the OTS frustum in the layout frame (to skip blocks that cannot be BVV)."""
    if layout.ots is None:
        return None
    corners = layout.ots.frustum.corners().reshape(-1, 3)
    T = layout.ots.T_omc_ots
    c = corners @ T[:3, :3].T + T[:3, 3]
    return c.min(axis=0), c.max(axis=0)


REGION_COLORS = {BVV: (0.10, 0.65, 0.20), GVV: (0.20, 0.45, 0.85), PVV: (0.85, 0.20, 0.15)}


def save_heatmap_png(mmap: MarginMap, path: str | os.PathLike, axis: str = "z", value: float | None = None,
                     layout: Layout | None = None, title: str | None = None) -> Path:
    """Write a two-panel PNG of one grid slice: the margin heatmap (with the threshold contour) and the regions.

    ``axis`` is the slice normal ('x', 'y' or 'z'); ``value`` the coordinate [m] (nearest grid plane; default the
    middle). With ``layout`` the cameras are drawn projected onto the slice.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    a = "xyz".index(axis)
    ax_vals = mmap.axes()[a]
    k = len(ax_vals) // 2 if value is None else int(np.argmin(np.abs(ax_vals - value)))
    sl = [slice(None)] * 3
    sl[a] = k
    marg = mmap.margin_deg[tuple(sl)]
    lab = mmap.labels[tuple(sl)]
    h_ax, v_ax = [b for b in range(3) if b != a]
    hv, vv = mmap.axes()[h_ax], mmap.axes()[v_ax]
    extent = (hv[0] - mmap.resolution / 2, hv[-1] + mmap.resolution / 2,
              vv[0] - mmap.resolution / 2, vv[-1] + mmap.resolution / 2)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), constrained_layout=True)
    im = axes[0].imshow(marg.T, origin="lower", extent=extent, cmap="viridis", aspect="equal")
    fig.colorbar(im, ax=axes[0], label="view margin [deg]")
    if np.nanmin(marg) < mmap.threshold_deg < np.nanmax(marg):
        axes[0].contour(hv, vv, marg.T, levels=[mmap.threshold_deg], colors="w", linewidths=1.0)
    cmap = ListedColormap([(0.9, 0.9, 0.9), REGION_COLORS[BVV], REGION_COLORS[GVV], REGION_COLORS[PVV]])
    axes[1].imshow(lab.T, origin="lower", extent=extent, cmap=cmap, vmin=-0.5, vmax=3.5, aspect="equal",
                   interpolation="nearest")
    handles = [plt.Rectangle((0, 0), 1, 1, color=REGION_COLORS[v]) for v in (BVV, GVV, PVV)]
    axes[1].legend(handles, [f"{REGION_NAMES[v]} {100 * np.mean(lab == v):.0f} % of slice" for v in (BVV, GVV, PVV)],
                   loc="upper right", fontsize=8)
    if layout is not None:
        for ax in axes:
            ax.plot(layout.cam_pos[:, h_ax], layout.cam_pos[:, v_ax], "k^", ms=6)
            if layout.ots is not None:
                p = layout.ots.T_omc_ots[:3, 3]
                ax.plot([p[h_ax]], [p[v_ax]], "ms", ms=7)
    names = "xyz"
    for ax in axes:
        ax.set_xlabel(f"{names[h_ax]} [m]")
        ax.set_ylabel(f"{names[v_ax]} [m]")
    fig.suptitle(title or f"view margin, {axis} = {ax_vals[k]:.2f} m ({mmap.frame_id}), threshold "
                          f"{mmap.threshold_deg:.0f} deg, grid {mmap.resolution:g} m")
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
