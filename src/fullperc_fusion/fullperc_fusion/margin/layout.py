"""Camera layout of the operating room: OMC cameras, the OTS (NDI Vega) and the view-margin settings.

The layout is the static geometry that the view-margin model (paper §4, Algorithm 1, eq. 17) works on.
It is one YAML file (metres and degrees) shared by ``margin_node`` and the simulator, so the region
labels the node publishes and the camera geometry the simulated OMC triangulates with agree.

Frames, and the cameras', the tracker's and the occluders' geometry: :mod:`.geometry`. This module is the file:
its format, the checks that name the file and the field, and the :class:`Layout` with the arrays the margin model
precomputes from it.

File format (every field is checked; an error names the file and the field)::

    frame_id: omc
    room: {min: [-3.0, -2.5, 0.0], max: [3.0, 2.5, 3.0]}      # optional: map bounds [m]
    camera_defaults: {fov_h_deg: 56, fov_v_deg: 46, range_m: 4.0, resolution: [2048, 2048]}
    cameras:
      - {name: cam01, position: [x, y, z], orientation: [qx, qy, qz, qw]}   # may override any default
    ots:                                                       # optional (no OTS -> never BVV)
      name: vega
      position: [x, y, z]
      orientation: [qx, qy, qz, qw]                            # omc_from_ots
      volume: pyramid                                          # pyramid | extended | custom
      depth_axis: "-z"
      planes: [[depth_m, half_width_m, half_height_m], ...]    # only with volume: custom
    convergence_deg: [40, 140]
    threshold: {mode: eq17, theta_deg: 30, phi_deg: 35, k: 6}  # or {mode: explicit, deg: 300}
    occluders:                                                 # optional: static boxes that block lines of sight
      - {name: table_top, min: [x, y, z], max: [x, y, z]}      # axis-aligned in omc [m]
    scene: {...}                                               # optional, free-form (simulator props)

Occluders are our extension of Algorithm 1 (the paper's model is occlusion-free): a camera only counts for a point
when the segment camera -> point does not pass through a static box (the OR table, a patient, an anaesthesia cart),
and a point is BVV only when the segment from the OTS origin to it is clear as well (see :mod:`.margin`).
Without ``occluders`` the model is exactly the paper's.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fullperc_common.share import share_path
from fullperc_common.transforms import make_T, quat_to_R_rows
from fullperc_common.yaml_file import load_yaml_file
from fullperc_fusion.margin.geometry import (
    NDI_EXTENDED_PLANES,
    NDI_PYRAMID_PLANES,
    SEGMENT_END,
    Box,
    Camera,
    Frustum,
    Ots,
    eq17_theta_prime_deg,
    look_at_R,
    look_at_R_ndi,
)

# the geometry's names stay importable from here, where the margin model, the simulator and the emulators take them
__all__ = ["NDI_EXTENDED_PLANES", "NDI_PYRAMID_PLANES", "SEGMENT_END", "Box", "Camera", "Frustum", "Layout",
           "LayoutError", "Ots", "Threshold", "default_layout_path", "eq17_theta_prime_deg", "load_layout",
           "look_at_R", "look_at_R_ndi", "parse_layout"]

_DEFAULT_CAMERA = {"fov_h_deg": 56.0, "fov_v_deg": 46.0, "range_m": 4.0, "resolution": [2048, 2048]}
_CAMERA_KEYS = {"name", "position", "orientation", "fov_h_deg", "fov_v_deg", "range_m", "resolution"}
_OTS_KEYS = {"name", "position", "orientation", "volume", "depth_axis", "planes"}
_TOP_KEYS = {"frame_id", "room", "camera_defaults", "cameras", "ots", "convergence_deg", "threshold", "occluders",
             "scene"}


class LayoutError(ValueError):
    """The layout file is wrong; the message names the file and the field."""


@dataclass(frozen=True)
class Threshold:
    """GVV/PVV threshold on the summed margin [deg]: ``k·θ'`` of eq. (17) or an explicit value."""

    mode: str
    deg: float
    theta_deg: float | None = None
    phi_deg: float | None = None
    k: float | None = None
    theta_prime_deg: float | None = None


@dataclass(frozen=True)
class Layout:
    """Everything the view-margin model needs, plus precomputed arrays for the vectorized paths."""

    frame_id: str
    cameras: tuple[Camera, ...]
    ots: Ots | None
    convergence_deg: tuple[float, float]
    threshold: Threshold
    room_min: np.ndarray
    room_max: np.ndarray
    source: str = "<memory>"
    occluders: tuple[Box, ...] = ()
    scene: dict = field(default_factory=dict)
    # Precomputed stacks (filled in __post_init__): positions (N,3), rotations (N,3,3), tan of half FOVs, ranges.
    cam_pos: np.ndarray = field(init=False, repr=False)
    cam_R: np.ndarray = field(init=False, repr=False)
    tan_h: np.ndarray = field(init=False, repr=False)
    tan_v: np.ndarray = field(init=False, repr=False)
    range_m: np.ndarray = field(init=False, repr=False)
    pair_i: np.ndarray = field(init=False, repr=False)
    pair_j: np.ndarray = field(init=False, repr=False)
    # Single-point path (margin.margin_at), arranged so that one point costs ~25 small numpy calls:
    # camera-frame coordinates of p for all cameras as one mat-vec, pc = (fast_A @ p - fast_b).reshape(3, N);
    # tan of the half FOVs (2, N); squared ranges (N,); line-of-sight origins (3, N + 1): the N cameras, then the
    # OTS origin when there is an OTS (its column gives the BVV line of sight in the same slab test); occluder slab
    # offsets (lo - c, hi - c) for every origin c as (2, 3, N + 1, B).
    fast_A: np.ndarray = field(init=False, repr=False)
    fast_b: np.ndarray = field(init=False, repr=False)
    fast_tan: np.ndarray = field(init=False, repr=False)
    fast_r2: np.ndarray = field(init=False, repr=False)
    fast_camT: np.ndarray = field(init=False, repr=False)
    fast_K: np.ndarray = field(init=False, repr=False)
    fast_pairs: np.ndarray = field(init=False, repr=False)
    cos_lo: float = field(init=False, repr=False)
    cos_hi: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        cams = self.cameras
        set_ = object.__setattr__
        set_(self, "cam_pos", np.array([c.position for c in cams], dtype=float).reshape(-1, 3))
        set_(self, "cam_R", np.array([c.R for c in cams], dtype=float).reshape(-1, 3, 3))
        set_(self, "tan_h", np.tan(np.radians([c.fov_h_deg / 2.0 for c in cams])))
        set_(self, "tan_v", np.tan(np.radians([c.fov_v_deg / 2.0 for c in cams])))
        set_(self, "range_m", np.array([c.range_m for c in cams], dtype=float))
        i, j = np.triu_indices(len(cams), k=1)
        set_(self, "pair_i", i)
        set_(self, "pair_j", j)
        A = np.transpose(self.cam_R, (2, 0, 1)).reshape(-1, 3)  # row k*N + n = k-th axis of camera n, in omc
        set_(self, "fast_A", np.ascontiguousarray(A))
        set_(self, "fast_b", np.einsum("rk,rk->r", A, np.tile(self.cam_pos, (3, 1))))
        set_(self, "fast_tan", np.stack([self.tan_h, self.tan_v]))
        set_(self, "fast_r2", self.range_m ** 2)
        origins = self.cam_pos if self.ots is None else np.vstack([self.cam_pos, self.ots.position[None, :]])
        set_(self, "fast_camT", np.ascontiguousarray(origins.T))
        lo = np.array([b.lo for b in self.occluders], dtype=float).reshape(-1, 3)
        hi = np.array([b.hi for b in self.occluders], dtype=float).reshape(-1, 3)
        rel = np.stack([lo[None, :, :] - origins[:, None, :], hi[None, :, :] - origins[:, None, :]])
        set_(self, "fast_K", np.ascontiguousarray(np.transpose(rel, (0, 3, 1, 2))))  # (2, 3, N (+1), B)
        set_(self, "fast_pairs", i * len(cams) + j)  # camera pairs as flat indices into an N x N matrix
        # Convergence band in cosine space: lo <= beta <= hi  <=>  cos(hi) <= cos(beta) <= cos(lo).
        set_(self, "cos_lo", math.cos(math.radians(self.convergence_deg[0])))
        lo_deg, hi_deg = self.convergence_deg
        # a band symmetric about 90 deg gets exactly symmetric cosines, so margin_at can test |cos| <= cos_lo
        set_(self, "cos_hi", -self.cos_lo if lo_deg + hi_deg == 180.0 else math.cos(math.radians(hi_deg)))

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @property
    def threshold_deg(self) -> float:
        return self.threshold.deg

    @property
    def T_omc_ots(self) -> np.ndarray | None:
        return None if self.ots is None else self.ots.T_omc_ots

    @property
    def frustum(self) -> Frustum | None:
        return None if self.ots is None else self.ots.frustum

    def with_threshold(self, deg: float) -> Layout:
        """Copy with an explicit threshold (e.g. a node parameter overriding the file)."""
        if not (math.isfinite(deg) and deg >= 0):
            raise LayoutError(f"{self.source}: threshold.deg: must be a finite number >= 0, got {deg!r}")
        return Layout(self.frame_id, self.cameras, self.ots, self.convergence_deg, Threshold("explicit", float(deg)),
                      self.room_min, self.room_max, self.source, self.occluders, self.scene)


# ------------------------------------------------------------------------------------------------------ parsing
class _Ctx:
    """Carries the file name so every error says where it is."""

    def __init__(self, source: str) -> None:
        self.source = source

    def err(self, where: str, what: str) -> LayoutError:
        return LayoutError(f"layout file {self.source}: field '{where}': {what}")

    def get(self, m: Mapping, key: str, where: str, default: Any = ...) -> Any:
        if not isinstance(m, Mapping):
            raise self.err(where, f"expected a mapping, got {type(m).__name__}")
        if key not in m or m[key] is None:
            if default is ...:
                raise self.err(f"{where}.{key}" if where else key, "missing")
            return default
        return m[key]

    def unknown(self, m: Mapping, allowed: set[str], where: str) -> None:
        extra = sorted(set(m) - allowed)
        if extra:
            raise self.err(where or "<top level>", f"unknown key(s) {extra}; allowed: {sorted(allowed)}")

    def number(self, v: Any, where: str, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(where, f"expected a number, got {v!r}")
        x = float(v)
        if not math.isfinite(x):
            raise self.err(where, f"must be finite, got {v!r}")
        if lo is not None and (x <= lo if lo_open else x < lo):
            raise self.err(where, f"must be {'>' if lo_open else '>='} {lo:g}, got {v!r}")
        if hi is not None and x > hi:
            raise self.err(where, f"must be <= {hi:g}, got {v!r}")
        return x

    def vector(self, v: Any, n: int, where: str) -> np.ndarray:
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise self.err(where, f"expected a list of {n} numbers, got {v!r}")
        return np.array([self.number(x, f"{where}[{i}]") for i, x in enumerate(v)])

    def rotation(self, v: Any, where: str) -> np.ndarray:
        q = self.vector(v, 4, where)
        n = float(np.linalg.norm(q))
        if n < 1e-9:
            raise self.err(where, "zero-length quaternion (x y z w); an orientation needs a unit quaternion")
        if abs(n - 1.0) > 1e-2:
            raise self.err(where, f"quaternion (x y z w) is not unit length (norm {n:.4f}); typo?")
        return np.array(quat_to_R_rows(*(q / n).tolist()))   # scipy's from_quat().as_matrix(), bit for bit


def _parse_camera(ctx: _Ctx, m: Any, defaults: dict, where: str) -> Camera:
    if not isinstance(m, Mapping):
        raise ctx.err(where, f"expected a mapping, got {m!r}")
    ctx.unknown(m, _CAMERA_KEYS, where)
    name = ctx.get(m, "name", where)
    if not isinstance(name, str) or not name:
        raise ctx.err(f"{where}.name", f"expected a non-empty string, got {name!r}")
    merged = {**defaults, **{k: v for k, v in m.items() if v is not None}}
    res = ctx.get(merged, "resolution", where)
    if (not isinstance(res, (list, tuple)) or len(res) != 2
            or not all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in res)):
        raise ctx.err(f"{where}.resolution", f"expected [width, height] positive integers, got {res!r}")
    return Camera(
        name=name,
        position=ctx.vector(ctx.get(m, "position", where), 3, f"{where}.position"),
        R=ctx.rotation(ctx.get(m, "orientation", where), f"{where}.orientation"),
        fov_h_deg=ctx.number(ctx.get(merged, "fov_h_deg", where), f"{where}.fov_h_deg", 0, 179, lo_open=True),
        fov_v_deg=ctx.number(ctx.get(merged, "fov_v_deg", where), f"{where}.fov_v_deg", 0, 179, lo_open=True),
        range_m=ctx.number(ctx.get(merged, "range_m", where), f"{where}.range_m", 0, lo_open=True),
        resolution=(int(res[0]), int(res[1])),
    )


def _parse_ots(ctx: _Ctx, m: Any) -> Ots:
    where = "ots"
    if not isinstance(m, Mapping):
        raise ctx.err(where, f"expected a mapping, got {m!r}")
    ctx.unknown(m, _OTS_KEYS, where)
    pos = ctx.vector(ctx.get(m, "position", where), 3, "ots.position")
    R = ctx.rotation(ctx.get(m, "orientation", where), "ots.orientation")
    volume = ctx.get(m, "volume", where, "pyramid")
    axis = ctx.get(m, "depth_axis", where, "-z")
    if axis not in ("-z", "+z"):
        raise ctx.err("ots.depth_axis", f"must be \"-z\" or \"+z\", got {axis!r}")
    if volume == "pyramid":
        planes = np.array(NDI_PYRAMID_PLANES)
    elif volume == "extended":
        planes = np.array(NDI_EXTENDED_PLANES)
    elif volume == "custom":
        raw = ctx.get(m, "planes", where)
        if not isinstance(raw, (list, tuple)) or len(raw) < 2:
            raise ctx.err("ots.planes", "expected at least two [depth_m, half_width_m, half_height_m] rows")
        planes = np.array([ctx.vector(r, 3, f"ots.planes[{i}]") for i, r in enumerate(raw)])
        if np.any(planes <= 0):
            raise ctx.err("ots.planes", "depths and half sizes must be > 0")
        if np.any(np.diff(planes[:, 0]) <= 0):
            raise ctx.err("ots.planes", "depths must increase strictly from row to row")
    else:
        raise ctx.err("ots.volume", f"must be pyramid, extended or custom, got {volume!r}")
    if volume != "custom" and m.get("planes") is not None:
        raise ctx.err("ots.planes", "only allowed with volume: custom")
    name = ctx.get(m, "name", where, "vega")
    return Ots(name=str(name), T_omc_ots=make_T(pos, R=R), frustum=Frustum(planes, axis), volume=str(volume))


def _parse_threshold(ctx: _Ctx, m: Any, cameras: tuple[Camera, ...]) -> Threshold:
    where = "threshold"
    if m is None:
        m = {"mode": "eq17"}
    if not isinstance(m, Mapping):
        raise ctx.err(where, f"expected a mapping, got {m!r}")
    mode = ctx.get(m, "mode", where)
    if mode == "explicit":
        ctx.unknown(m, {"mode", "deg"}, where)
        return Threshold("explicit", ctx.number(ctx.get(m, "deg", where), "threshold.deg", 0))
    if mode != "eq17":
        raise ctx.err("threshold.mode", f"must be eq17 or explicit, got {mode!r}")
    ctx.unknown(m, {"mode", "theta_deg", "phi_deg", "k"}, where)
    theta = m.get("theta_deg")
    theta = 360.0 / len(cameras) if theta is None else ctx.number(theta, "threshold.theta_deg", 0, 180, lo_open=True)
    phi = m.get("phi_deg")
    phi = float(np.mean([c.tilt_deg for c in cameras])) if phi is None else ctx.number(phi, "threshold.phi_deg", 0, 90)
    k = m.get("k")
    k = 6.0 if k is None else ctx.number(k, "threshold.k", 0, lo_open=True)
    tp = eq17_theta_prime_deg(theta, phi)
    return Threshold("eq17", k * tp, theta_deg=theta, phi_deg=phi, k=k, theta_prime_deg=tp)


def parse_layout(data: Any, source: str = "<memory>") -> Layout:
    """Build a :class:`Layout` from the parsed YAML mapping; raises :class:`LayoutError` naming the field."""
    ctx = _Ctx(source)
    if not isinstance(data, Mapping):
        raise ctx.err("<top level>", f"expected a mapping, got {type(data).__name__}")
    ctx.unknown(data, _TOP_KEYS, "")
    frame_id = ctx.get(data, "frame_id", "", "omc")
    if not isinstance(frame_id, str) or not frame_id:
        raise ctx.err("frame_id", f"expected a non-empty string, got {frame_id!r}")

    defaults_in = ctx.get(data, "camera_defaults", "", {})
    if not isinstance(defaults_in, Mapping):
        raise ctx.err("camera_defaults", "expected a mapping")
    ctx.unknown(defaults_in, _CAMERA_KEYS - {"name", "position", "orientation"}, "camera_defaults")
    defaults = {**_DEFAULT_CAMERA, **{k: v for k, v in defaults_in.items() if v is not None}}

    raw_cams = ctx.get(data, "cameras", "")
    if not isinstance(raw_cams, (list, tuple)) or len(raw_cams) < 2:
        raise ctx.err("cameras", "expected a list of at least two cameras (a margin needs a camera pair)")
    cameras = tuple(_parse_camera(ctx, c, defaults, f"cameras[{i}]") for i, c in enumerate(raw_cams))
    names = [c.name for c in cameras]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ctx.err("cameras", f"duplicate camera names {dup}")

    conv = ctx.vector(ctx.get(data, "convergence_deg", "", [40.0, 140.0]), 2, "convergence_deg")
    if not (0.0 <= conv[0] < conv[1] <= 180.0):
        raise ctx.err("convergence_deg", f"need 0 <= lo < hi <= 180, got {conv.tolist()}")

    ots_raw = data.get("ots")
    ots = None if ots_raw is None else _parse_ots(ctx, ots_raw)
    threshold = _parse_threshold(ctx, data.get("threshold"), cameras)

    room = data.get("room")
    if room is None:
        lo, hi = np.min([c.position for c in cameras], axis=0), np.max([c.position for c in cameras], axis=0)
        lo[2] = 0.0
    else:
        if not isinstance(room, Mapping):
            raise ctx.err("room", "expected a mapping {min: [x,y,z], max: [x,y,z]}")
        ctx.unknown(room, {"min", "max"}, "room")
        lo = ctx.vector(ctx.get(room, "min", "room"), 3, "room.min")
        hi = ctx.vector(ctx.get(room, "max", "room"), 3, "room.max")
        if np.any(hi <= lo):
            raise ctx.err("room", f"max must exceed min on every axis, got min={lo.tolist()} max={hi.tolist()}")
    occ_raw = data.get("occluders") or []
    if not isinstance(occ_raw, (list, tuple)):
        raise ctx.err("occluders", "expected a list of {name, min, max} boxes")
    occluders = []
    for i, b in enumerate(occ_raw):
        w = f"occluders[{i}]"
        if not isinstance(b, Mapping):
            raise ctx.err(w, f"expected a mapping, got {b!r}")
        ctx.unknown(b, {"name", "min", "max"}, w)
        blo = ctx.vector(ctx.get(b, "min", w), 3, f"{w}.min")
        bhi = ctx.vector(ctx.get(b, "max", w), 3, f"{w}.max")
        if np.any(bhi <= blo):
            raise ctx.err(w, f"max must exceed min on every axis, got min={blo.tolist()} max={bhi.tolist()}")
        occluders.append(Box(str(ctx.get(b, "name", w, f"box{i}")), blo, bhi))
    scene = data.get("scene") or {}
    if not isinstance(scene, Mapping):
        raise ctx.err("scene", "expected a mapping")
    return Layout(frame_id, cameras, ots, (float(conv[0]), float(conv[1])), threshold, np.asarray(lo, float),
                  np.asarray(hi, float), source, tuple(occluders), dict(scene))


def load_layout(path: str | os.PathLike) -> Layout:
    """Read and check a layout YAML file; raises :class:`LayoutError` naming the file and the bad field."""
    return parse_layout(load_yaml_file(path, "layout file", LayoutError), str(Path(path)))


def default_layout_path() -> Path:
    """The installed ``share/fullperc_fusion/config/or_layout.yaml``, else the source copy
    (:func:`fullperc_common.share.share_path`); FileNotFoundError naming every place tried."""
    return share_path("fullperc_fusion", "config", "or_layout.yaml")
