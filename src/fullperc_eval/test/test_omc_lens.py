"""The OMC lens residual (sim.omc_lens): a focal-length/radial-distortion error common to all cameras distorts the
reconstructed volume smoothly; it moves the estimate much less when a camera drops out than per-camera extrinsic
errors of the same size do, and it is off for the ideal system."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_eval.sim.omc_lens import LensResidual
from fullperc_eval.sim.omc_model import CameraSet, NoiseModel, Occluders, observe_markers
from fullperc_eval.sim.scene import SceneError, build_scene, load_scene_config

NO_NOISE = NoiseModel(0.0, 1.0, 0.0)


def ring(n: int = 8, radius: float = 3.0, height: float = 2.5) -> CameraSet:
    """n cameras on a circle, all aimed at the origin (as the OR's ceiling ring aims at the table)."""
    ang = np.arange(n) * 2 * np.pi / n
    pos = np.column_stack([radius * np.cos(ang), radius * np.sin(ang), np.full(n, height)])
    R = []
    for p in pos:
        z = -p / np.linalg.norm(p)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R.append(np.column_stack([x, np.cross(z, x), z]))
    return CameraSet.from_specs([f"c{i}" for i in range(n)], pos, R, [56.0] * n, [46.0] * n, [6.0] * n,
                                [(2048, 2048)] * n)


def estimate(cams: CameraSet, X: np.ndarray, enabled: np.ndarray | None = None) -> np.ndarray:
    F, M = X.shape[:2]
    obs = observe_markers(cams, X, np.ones((F, M), bool), Occluders.none(F), NO_NOISE,
                          np.zeros((F, M, cams.K, 2)), camera_enabled=enabled)
    return obs.X


def test_distort_is_radial_and_zero_on_the_axis():
    lens = LensResidual(focal_scale=0.005, k1=-0.02)
    x, y = np.array([0.0, 0.3, -0.2]), np.array([0.0, 0.1, 0.4])
    xd, yd = lens.distort(x, y)
    assert xd[0] == 0.0 and yd[0] == 0.0
    np.testing.assert_allclose(xd[1:] * y[1:], yd[1:] * x[1:], atol=1e-15)  # same direction from the centre
    r2 = x**2 + y**2
    np.testing.assert_allclose(xd, x * 1.005 * (1 - 0.02 * r2))
    np.testing.assert_array_equal(LensResidual().distort(x, y)[0], x)


def test_from_config_reads_checks_and_drops_a_zero_residual():
    assert LensResidual.from_config(None) is None
    assert LensResidual.from_config({"focal_scale": 0.0, "k1": 0.0}) is None
    assert LensResidual.from_config({"focal_scale": 0.004}) == LensResidual(0.004, 0.0)
    with pytest.raises(ValueError, match="omc.lens_residual.k1"):
        LensResidual.from_config({"k1": "big"})
    with pytest.raises(ValueError, match="focal_scale"):
        LensResidual.from_config({"focal_scale": 0.5})


def test_common_residual_distorts_smoothly_and_hops_little():
    """Off the aim point the residual moves the estimate by ~mm; dropping one camera changes it by a small share of
    that, while per-camera extrinsic errors that give the same displacement hop by a large share of it."""
    X = np.array([[[0.4, -0.3, 0.5]]])
    lens_cams = ring()
    lens_cams.lens = LensResidual(focal_scale=0.006, k1=-0.02)
    err = np.linalg.norm(estimate(lens_cams, X)[0, 0] - X[0, 0])
    assert 5e-4 < err < 1e-2
    # the aim point is on every optical axis: no displacement there
    np.testing.assert_allclose(estimate(lens_cams, np.zeros((1, 1, 3)))[0, 0], 0.0, atol=1e-12)
    # the field is smooth: 1 mm of motion changes the error by far less than 1 mm
    X2 = X + np.array([0.001, 0.0, 0.0])
    d_err = (estimate(lens_cams, X2) - X2) - (estimate(lens_cams, X) - X)
    assert np.linalg.norm(d_err) < 0.02 * err

    def hops(cams: CameraSet) -> float:
        full = estimate(cams, X)[0, 0]
        return max(np.linalg.norm(estimate(cams, X, np.arange(cams.K) != k)[0, 0] - full) for k in range(cams.K))

    ext = ring().miscalibrated(np.random.default_rng(1), 0.0, 0.05)
    ext_err = np.linalg.norm(estimate(ext, X)[0, 0] - X[0, 0])
    assert ext_err > 0.3 * err  # comparable displacement ...
    assert hops(lens_cams) / err < 0.5 * hops(ext) / ext_err  # ... but the common residual hops far less


def test_profiles_and_the_ideal_system():
    """paper carries a residual, spec (a complete calibration) none, and miscalibration=False switches it off."""
    assert build_scene(0, profile="paper").omc_cams.lens is not None
    assert build_scene(0, profile="spec").omc_cams.lens is None
    assert build_scene(0, profile="paper", miscalibration=False).omc_cams.lens is None
    cfg = load_scene_config(profile="paper")
    cfg["omc"]["lens_residual"] = {"k1": 1.0}
    with pytest.raises(SceneError, match="lens_residual"):
        build_scene(0, config=cfg)
