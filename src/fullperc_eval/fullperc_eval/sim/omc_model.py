"""Physics of the optical motion-capture measurement: projection, triangulation, rigid-body fit.

Per marker and camera: the marker is imaged when it lies in the camera's field of view and range,
faces the camera (the body's plate hides spheres seen from behind), and the straight line to the
camera is not blocked by any capsule or box. Its image point gets centroid noise whose standard
deviation grows with distance (a farther sphere covers fewer pixels, so its centroid is less
certain). The system then triangulates each marker by least squares from the rays of all cameras
that see it, using the extrinsics it *believes* (the true ones plus a seeded calibration error),
and fits each rigid body by Kabsch to its ≥ 3 triangulated markers.

Nothing is injected: when the set of seeing cameras changes, the rays that enter the least-squares
solution change, and with miscalibrated extrinsics the solution moves (a *hop*); with a fixed
set, the error varies smoothly with position (*distortion*). A lens residual common to all cameras
(:mod:`.omc_lens`: the focal length and radial distortion an incomplete calibration gets wrong)
bends every camera's ray the same way, which distorts the reconstructed volume smoothly with little
hop. With perfect calibration and zero noise every ray passes exactly through the marker and the
estimate is exact.

Everything is vectorised over a chunk of frames x markers x cameras.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .occluders import PlacedBox, rays_blocked_by_boxes, rays_blocked_by_capsules
from .omc_lens import LensResidual


@dataclass
class CameraSet:
    """K pinhole cameras. ``R`` maps camera to omc (columns: camera x right, y down, z forward).

    ``C``/``R`` are the true extrinsics, ``Cb``/``Rb`` what the system believes after calibration; ``lens`` is
    what the believed intrinsics (pinhole ``fx``..``cy``, taken as exact when back-projecting) miss of the real
    lenses (:class:`~.omc_lens.LensResidual`), common to all cameras.
    """

    names: list[str]
    C: np.ndarray  # (K, 3)
    R: np.ndarray  # (K, 3, 3)
    fx: np.ndarray  # (K,) [px]
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    tan_h: np.ndarray  # tan(half horizontal FOV)
    tan_v: np.ndarray
    range_m: np.ndarray
    Cb: np.ndarray = field(default=None)  # type: ignore[assignment]
    Rb: np.ndarray = field(default=None)  # type: ignore[assignment]
    lens: LensResidual | None = None  # what the believed lens model misses of the real lenses (None: exact)

    def __post_init__(self) -> None:
        if self.Cb is None:
            self.Cb = self.C.copy()
        if self.Rb is None:
            self.Rb = self.R.copy()

    @property
    def K(self) -> int:
        return len(self.names)

    @classmethod
    def from_specs(cls, names: Sequence[str], positions, rotations, fov_h_deg, fov_v_deg, range_m,
                   resolution) -> CameraSet:
        """Build from per-camera position (3,), rotation (3x3 omc_from_camera), FOV [deg], range [m], (w, h)."""
        res = np.asarray(resolution, dtype=float).reshape(-1, 2)
        tan_h = np.tan(np.radians(np.asarray(fov_h_deg, dtype=float)) / 2)
        tan_v = np.tan(np.radians(np.asarray(fov_v_deg, dtype=float)) / 2)
        return cls(names=list(names), C=np.asarray(positions, dtype=float).reshape(-1, 3),
                   R=np.asarray(rotations, dtype=float).reshape(-1, 3, 3),
                   fx=res[:, 0] / 2 / tan_h, fy=res[:, 1] / 2 / tan_v, cx=res[:, 0] / 2, cy=res[:, 1] / 2,
                   tan_h=tan_h, tan_v=tan_v, range_m=np.asarray(range_m, dtype=float).reshape(-1))

    def miscalibrated(self, rng: np.random.Generator, sigma_t_m: float, sigma_rot_deg: float) -> CameraSet:
        """Copy whose believed extrinsics differ from the truth by seeded Gaussian errors."""
        dt = rng.normal(0.0, sigma_t_m, size=(self.K, 3))
        drot = Rotation.from_rotvec(np.radians(rng.normal(0.0, sigma_rot_deg, size=(self.K, 3)))).as_matrix()
        return replace(self, Cb=self.C + dt, Rb=np.einsum("kij,kjl->kil", drot, self.R))


@dataclass(frozen=True)
class NoiseModel:
    """Image-point centroid noise: sigma_px(d) = sigma_px_ref * (d / d_ref) ** exponent."""

    sigma_px_ref: float = 0.05
    d_ref_m: float = 2.0
    exponent: float = 0.5

    def sigma_px(self, d: np.ndarray) -> np.ndarray:
        return self.sigma_px_ref * (np.asarray(d) / self.d_ref_m) ** self.exponent


@dataclass
class Occluders:
    """Occluders of a chunk of F frames: moving capsules (F, K, 3) x2 + radii (K,), static boxes."""

    cap_a: np.ndarray
    cap_b: np.ndarray
    cap_r: np.ndarray
    boxes: list[PlacedBox] = field(default_factory=list)

    @classmethod
    def none(cls, F: int) -> Occluders:
        return cls(np.zeros((F, 0, 3)), np.zeros((F, 0, 3)), np.zeros(0), [])


@dataclass
class MarkerObs:
    """Result of :func:`observe_markers` for F frames, M markers, K cameras."""

    seen: np.ndarray  # (F, M, K) bool: camera k detected marker m
    X: np.ndarray  # (F, M, 3) triangulated position (NaN when < min_cams)
    n_cams: np.ndarray  # (F, M) cameras used


def visible(cams: CameraSet, X: np.ndarray, normals: np.ndarray | None = None,
            max_view_angle_deg: float = 90.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static visibility of markers X (F, M, 3): FOV, range, facing. Returns (mask, p_cam, dist)."""
    v = X[:, :, None, :] - cams.C[None, None, :, :]  # (F, M, K, 3) camera -> marker
    pc = np.einsum("kji,fmkj->fmki", cams.R, v)  # R^T v : marker in camera coordinates
    dist = np.linalg.norm(v, axis=-1)
    z = pc[..., 2]
    mask = (z > 0) & (np.abs(pc[..., 0]) <= cams.tan_h * z) & (np.abs(pc[..., 1]) <= cams.tan_v * z)
    mask &= dist <= cams.range_m
    if normals is not None:  # a zero normal means "no plate": visible from every side
        cosang = -np.einsum("fmkj,fmj->fmk", v, normals) / np.maximum(dist, 1e-12)
        has = np.einsum("fmj,fmj->fm", normals, normals) > 0
        mask &= (cosang >= np.cos(np.radians(max_view_angle_deg))) | ~has[:, :, None]
    return mask, pc, dist


def line_of_sight(cams: CameraSet, X: np.ndarray, occ: Occluders, start_offset_m: float = 0.01) -> np.ndarray:
    """(F, M, K) True where the segment marker -> camera centre is free of capsules and boxes.

    The segment starts ``start_offset_m`` from the marker towards the camera so the sphere's own
    mount never counts as an occluder.
    """
    F, M = X.shape[:2]
    Kc = cams.K
    a = np.broadcast_to(X[:, :, None, :], (F, M, Kc, 3))
    b = np.broadcast_to(cams.C[None, None], (F, M, Kc, 3))
    u = b - a
    u = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-12)
    a = a + start_offset_m * u
    blocked = rays_blocked_by_capsules(a.reshape(F, M * Kc, 3), b.reshape(F, M * Kc, 3), occ.cap_a, occ.cap_b,
                                       occ.cap_r).reshape(F, M, Kc)
    if occ.boxes:
        blocked |= rays_blocked_by_boxes(a, b, occ.boxes)
    return ~blocked


def triangulate(origins: np.ndarray, dirs: np.ndarray, use: np.ndarray, weights: np.ndarray | None = None,
                min_cams: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection of rays: minimise sum_k w_k |(I - d_k d_k^T)(X - o_k)|^2.

    origins (K, 3); dirs (..., K, 3) unit; use (..., K) bool. Returns X (..., 3) (NaN where fewer than
    ``min_cams`` rays) and the ray count (...,).
    """
    w = use.astype(float) if weights is None else np.where(use, weights, 0.0)
    P = np.eye(3) - dirs[..., :, None] * dirs[..., None, :]  # (..., K, 3, 3)
    A = np.einsum("...k,...kij->...ij", w, P)
    b = np.einsum("...k,...kij,kj->...i", w, P, origins)
    n = use.sum(axis=-1)
    ok = n >= min_cams
    A = np.where(ok[..., None, None], A, np.eye(3))
    X = np.linalg.solve(A, b[..., None])[..., 0]
    X[~ok] = np.nan
    return X, n


def observe_markers(cams: CameraSet, X_true: np.ndarray, exists: np.ndarray, occ: Occluders,
                    noise: NoiseModel, std_normals: np.ndarray, normals: np.ndarray | None = None,
                    max_view_angle_deg: float = 90.0, camera_enabled: np.ndarray | None = None,
                    min_cams: int = 2) -> MarkerObs:
    """Detect, project with noise, back-project with believed extrinsics and triangulate.

    X_true (F, M, 3) true marker centres in omc; exists (F, M); std_normals (F, M, K, 2) standard
    normal draws (drawn for every ray whether seen or not, so occluding one camera leaves every other
    camera's noise unchanged); camera_enabled (K,) switches whole cameras off.
    """
    mask, pc, dist = visible(cams, X_true, normals, max_view_angle_deg)
    mask &= exists[:, :, None]
    if camera_enabled is not None:
        mask &= np.asarray(camera_enabled, dtype=bool)[None, None, :]
    if mask.any():
        mask &= line_of_sight(cams, X_true, occ)
    z = np.where(pc[..., 2] > 1e-9, pc[..., 2], 1.0)
    sig = noise.sigma_px(dist)
    xn, yn = pc[..., 0] / z, pc[..., 1] / z
    if cams.lens is not None:  # the real lens images the point where the believed lens model does not expect it
        xn, yn = cams.lens.distort(xn, yn)
    u = cams.fx * xn + cams.cx + sig * std_normals[..., 0]
    v = cams.fy * yn + cams.cy + sig * std_normals[..., 1]
    # back-projection through the believed intrinsics (taken as exact) and believed extrinsics
    dc = np.stack([(u - cams.cx) / cams.fx, (v - cams.cy) / cams.fy, np.ones_like(u)], axis=-1)
    dw = np.einsum("kij,fmkj->fmki", cams.Rb, dc)
    dw /= np.linalg.norm(dw, axis=-1, keepdims=True)
    # two passes: plain ray least squares, then weights 1/d^2 (= equal angular error per ray)
    X1, n = triangulate(cams.Cb, dw, mask, min_cams=min_cams)
    d_est = np.linalg.norm(np.nan_to_num(X1)[:, :, None, :] - cams.Cb[None, None], axis=-1)
    X2, _ = triangulate(cams.Cb, dw, mask, weights=1.0 / np.maximum(d_est, 0.1) ** 2, min_cams=min_cams)
    return MarkerObs(seen=mask, X=X2, n_cams=n)


def kabsch(model: np.ndarray, meas: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched weighted Kabsch (Arun 1987): R, t with meas ~ R model + t, using markers where ``use``.

    model (M, 3) body-frame marker positions; meas (F, M, 3); use (F, M). Returns R (F, 3, 3),
    t (F, 3), residual distances (F, M) (NaN for unused markers). Frames with < 3 markers get NaN.
    """
    w = use.astype(float)
    n = w.sum(axis=1)
    ok = n >= 3
    ns = np.where(ok, n, 1.0)
    measz = np.where(use[..., None], meas, 0.0)
    pbar = (w @ model) / ns[:, None]
    qbar = np.einsum("fm,fmi->fi", w, measz) / ns[:, None]
    P = model[None] - pbar[:, None]
    Q = measz - qbar[:, None]
    H = np.einsum("fm,fmi,fmj->fij", w, P, Q)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", Vt, U)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("fji,fjk,flk->fil", Vt, D, U)  # V D U^T
    t = qbar - np.einsum("fij,fj->fi", R, pbar)
    fitted = np.einsum("fij,mj->fmi", R, model) + t[:, None]
    resid = np.where(use, np.linalg.norm(fitted - measz, axis=-1), np.nan)
    R[~ok] = np.nan
    t[~ok] = np.nan
    return R, t, resid


@dataclass
class BodyFit:
    """Per-body rigid fit over F frames (positions in metres, quaternion x y z w)."""

    tracked: np.ndarray  # (F,) bool
    position: np.ndarray  # (F, 3), NaN when not tracked
    quat_xyzw: np.ndarray  # (F, 4), NaN when not tracked
    mean_error: np.ndarray  # (F,) mean marker residual [m], NaN when not tracked
    markers_used: np.ndarray  # (F,) int
    cameras_seeing: np.ndarray  # (F,) int: distinct cameras that saw >= 1 used marker
    rays: np.ndarray  # (F,) int: total rays used
    rms_error: np.ndarray  # (F,) RMS marker residual [m] (what NDI reports), NaN when not tracked


def fit_body(model: np.ndarray, obs: MarkerObs, min_markers: int = 3) -> BodyFit:
    """Kabsch fit of one body's observed markers to its geometry; tracked when >= ``min_markers``."""
    use = np.isfinite(obs.X[..., 0])
    R, t, resid = kabsch(model, obs.X, use)
    nused = use.sum(axis=1)
    tracked = (nused >= max(3, min_markers)) & np.isfinite(t[:, 0])
    F = len(tracked)
    q = np.full((F, 4), np.nan)
    if tracked.any():
        q[tracked] = Rotation.from_matrix(R[tracked]).as_quat(canonical=True)
    pos = np.where(tracked[:, None], t, np.nan)
    r0 = np.where(use, resid, 0.0)
    me = np.where(tracked, r0.sum(axis=1) / np.maximum(nused, 1), np.nan)
    rms = np.where(tracked, np.sqrt((r0**2).sum(axis=1) / np.maximum(nused, 1)), np.nan)
    seen_used = obs.seen & use[..., None]
    return BodyFit(tracked=tracked, position=pos, quat_xyzw=q, mean_error=me, markers_used=nused.astype(np.int32),
                   cameras_seeing=seen_used.any(axis=1).sum(axis=1).astype(np.int32),
                   rays=np.where(use, obs.n_cams, 0).sum(axis=1).astype(np.int32), rms_error=rms)
