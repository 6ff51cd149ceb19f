"""Physics of the local tracker (NDI Polaris Vega): a factory-calibrated stereo pair with a frustum.

The Vega is two cameras a fixed baseline apart. A tool marker is measured only when it lies inside
the characterised measurement volume (the frustum of the layout, 950-2400 mm nominal), faces the
bar, and both lenses have a free line of sight to it; it is then triangulated from the two rays
with sub-pixel centroid noise (growing with distance like the OMC's). The factory calibration is
taken as exact, so the only error is that noise: about 0.1 mm per marker near the middle of the
volume, with the depth direction the worst, as for any short-baseline stereo pair. A tool is
reported (pose = Kabsch fit of the ROM geometry, RMS fit error like the device's) when >= 3 of its
markers are measured, else MISSING.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullperc_common.transforms import apply_T, inv_T

from .omc_model import BodyFit, CameraSet, MarkerObs, NoiseModel, Occluders, fit_body, observe_markers


def _look_rotation(axis: np.ndarray, right_hint: np.ndarray) -> np.ndarray:
    """Rotation (columns x right, y down, z forward) whose z is ``axis`` and x is close to ``right_hint``."""
    z = axis / np.linalg.norm(axis)
    x = right_hint - z * (right_hint @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


@dataclass
class OtsModel:
    """Vega stereo model in its own ``ots`` frame; ``frustum.contains(points_ots (N,3)) -> (N,) bool``."""

    frustum: object
    baseline_m: float = 0.5
    axis_ots: tuple[float, float, float] | None = None  # viewing direction; None: from frustum.depth_axis
    right_ots: tuple[float, float, float] = (1.0, 0.0, 0.0)
    noise: NoiseModel = NoiseModel(sigma_px_ref=0.02, d_ref_m=1.5, exponent=0.5)
    fov_deg: float = 80.0
    resolution: tuple[int, int] = (1280, 1024)
    max_view_angle_deg: float = 90.0

    def lenses_ots(self) -> tuple[np.ndarray, np.ndarray]:
        """Lens centres (2, 3) and rotations (2, 3, 3) in the ots frame (origin midway between them)."""
        right = np.asarray(self.right_ots, dtype=float)
        axis = self.axis_ots
        if axis is None:
            axis = (0.0, 0.0, 1.0) if getattr(self.frustum, "depth_axis", "-z") == "+z" else (0.0, 0.0, -1.0)
        R = _look_rotation(np.asarray(axis, dtype=float), right)
        x = R[:, 0]
        C = np.stack([-0.5 * self.baseline_m * x, 0.5 * self.baseline_m * x])
        return C, np.stack([R, R])

    def cameras(self, T_omc_ots: np.ndarray) -> CameraSet:
        """The two lenses as a perfectly calibrated :class:`CameraSet` in the omc frame."""
        C, R = self.lenses_ots()
        w, h = self.resolution
        fov_v = np.degrees(2 * np.arctan(np.tan(np.radians(self.fov_deg) / 2) * h / w))
        return CameraSet.from_specs(["vega_left", "vega_right"], apply_T(T_omc_ots, C),
                                    np.einsum("ij,kjl->kil", T_omc_ots[:3, :3], R), [self.fov_deg] * 2, [fov_v] * 2,
                                    [10.0, 10.0], [self.resolution] * 2)

    def measure(self, T_omc_ots: np.ndarray, model: np.ndarray, markers_omc: np.ndarray, normals_omc: np.ndarray,
                occ: Occluders, std_normals: np.ndarray, min_markers: int = 3) -> tuple[BodyFit, np.ndarray]:
        """Measure one tool over F frames; returns the fit in the ots frame and (F,) "partially out of volume".

        model (M, 3) ROM marker geometry [m]; markers_omc (F, M, 3); normals_omc (F, 3) plate normals
        (None: no facing test); std_normals (F, M, 2, 2) standard normal draws.
        """
        F, M = markers_omc.shape[:2]
        T_ots_omc = inv_T(T_omc_ots)
        pts_ots = apply_T(T_ots_omc, markers_omc.reshape(-1, 3)).reshape(F, M, 3)
        inside = np.asarray(self.frustum.contains(pts_ots.reshape(-1, 3)), dtype=bool).reshape(F, M)
        cams = self.cameras(T_omc_ots)
        normals = None if normals_omc is None else np.broadcast_to(normals_omc[:, None, :], (F, M, 3))
        obs = observe_markers(cams, markers_omc, inside, occ, self.noise, std_normals, normals=normals,
                              max_view_angle_deg=self.max_view_angle_deg, min_cams=2)
        # express the triangulated markers in the ots frame and fit the ROM there
        X_ots = apply_T(T_ots_omc, obs.X.reshape(-1, 3)).reshape(F, M, 3)
        fit = fit_body(model, MarkerObs(seen=obs.seen, X=X_ots, n_cams=obs.n_cams), min_markers=min_markers)
        partially_out = fit.tracked & ~inside.all(axis=1)
        return fit, partially_out
