"""Physics of the simulated trackers, on small hand-built camera rigs (no shared layout needed).

Expected values come from geometry computed here independently (ray information matrix, scipy's
Kabsch), never from the simulator's own output.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_eval.sim.occluders import PlacedBox, points_in_boxes, rays_blocked_by_boxes, segment_segment_distance
from fullperc_eval.sim.omc_model import CameraSet, NoiseModel, Occluders, fit_body, kabsch, observe_markers
from fullperc_eval.sim.ots_model import OtsModel
from fullperc_fusion.margin.layout import NDI_PYRAMID_PLANES, Box, Frustum, look_at_R, look_at_R_ndi

TARGET = np.array([0.1, -0.05, 1.0])


def ring(n: int = 8, radius: float = 3.0, height: float = 2.5) -> CameraSet:
    az = np.radians(np.arange(n) * 360.0 / n + 10.0)
    pos = np.column_stack([radius * np.cos(az), radius * np.sin(az), np.full(n, height)])
    R = np.stack([look_at_R(p, [0.0, 0.0, 1.0]) for p in pos])
    return CameraSet.from_specs([f"c{i}" for i in range(n)], pos, R, [56.0] * n, [46.0] * n, [4.5] * n,
                                [(2048, 2048)] * n)


NO_NOISE = NoiseModel(0.0, 1.0, 0.0)


def observe(cams, X, noise=NO_NOISE, z=None, occ=None, **kw):
    F, M = X.shape[:2]
    z = np.zeros((F, M, cams.K, 2)) if z is None else z
    return observe_markers(cams, X, np.ones((F, M), bool), occ or Occluders.none(F), noise, z, **kw)


def test_perfect_calibration_and_no_noise_is_exact():
    cams = ring()
    rng = np.random.default_rng(1)
    X = TARGET + rng.uniform(-0.3, 0.3, size=(50, 5, 3))
    obs = observe(cams, X)
    assert obs.seen.all()
    np.testing.assert_allclose(obs.X, X, atol=1e-9)


def test_marker_seen_by_all_cameras_triangulates_within_noise():
    cams = ring()
    sigma_px = 0.1
    noise = NoiseModel(sigma_px, 1.0, 0.0)  # constant pixel noise: easy to predict
    F = 4000
    rng = np.random.default_rng(2)
    X = np.broadcast_to(TARGET, (F, 1, 3)).copy()
    obs = observe(cams, X, noise, z=rng.standard_normal((F, 1, cams.K, 2)))
    assert obs.seen.all() and np.all(obs.n_cams == cams.K)
    err = obs.X[:, 0] - TARGET
    # first-order prediction: each ray constrains the 2 directions across it with std d * sigma_px / f
    info = np.zeros((3, 3))
    for k in range(cams.K):
        v = TARGET - cams.C[k]
        d = np.linalg.norm(v)
        u = v / d
        sig = d * sigma_px / cams.fx[k]
        info += (np.eye(3) - np.outer(u, u)) / sig**2
    predicted_rms = np.sqrt(np.trace(np.linalg.inv(info)))
    measured_rms = np.sqrt(np.mean(np.sum(err**2, axis=1)))
    assert abs(np.mean(err, axis=0)).max() < 0.2 * predicted_rms  # unbiased
    assert 0.85 * predicted_rms < measured_rms < 1.15 * predicted_rms


def test_pixel_noise_grows_with_distance():
    nm = NoiseModel(0.05, 2.0, 0.5)
    assert nm.sigma_px(np.array([1.0]))[0] < nm.sigma_px(np.array([2.0]))[0] == pytest.approx(0.05)
    assert nm.sigma_px(np.array([4.0]))[0] > 0.05


def test_occluding_cameras_one_by_one_shifts_estimate_in_steps():
    cams = ring().miscalibrated(np.random.default_rng(3), 0.001, 0.02)
    X = np.broadcast_to(TARGET, (1, 1, 3)).copy()
    estimates = []
    for n_off in range(cams.K - 1):  # the last two cameras always stay on
        enabled = np.arange(cams.K) >= n_off
        obs = observe(cams, X, camera_enabled=enabled)
        assert obs.n_cams[0, 0] == cams.K - n_off
        estimates.append(obs.X[0, 0])
    estimates = np.array(estimates)
    steps = np.linalg.norm(np.diff(estimates, axis=0), axis=1)
    assert np.all(steps > 1e-5), steps  # every change of the seeing set moves the estimate (a hop)
    err = np.linalg.norm(estimates - TARGET, axis=1)
    assert err.max() > 5e-4  # distortion from the miscalibration reaches the sub-mm..mm scale
    # with perfect calibration the same occlusions change nothing
    ideal = ring()
    for n_off in range(ideal.K - 1):
        obs = observe(ideal, X, camera_enabled=np.arange(ideal.K) >= n_off)
        np.testing.assert_allclose(obs.X[0, 0], TARGET, atol=1e-9)


def test_moving_occluder_makes_piecewise_constant_hops():
    """A person (capsule) walks through the line of sight of some cameras: without noise the estimate of a still
    marker is constant while the seeing set is constant and jumps exactly when the set changes."""
    cams = ring().miscalibrated(np.random.default_rng(4), 0.001, 0.02)
    F = 200
    X = np.broadcast_to(TARGET, (F, 1, 3)).copy()
    xs = np.linspace(-2.0, 2.0, F)
    a = np.column_stack([xs, np.full(F, 1.2), np.full(F, 0.2)])[:, None, :]
    b = np.column_stack([xs, np.full(F, 1.2), np.full(F, 1.8)])[:, None, :]
    obs = observe(cams, X, occ=Occluders(a, b, np.array([0.3])))
    seen = obs.seen[:, 0, :]
    assert (~seen).any() and seen.sum(axis=1).min() >= 2  # it does block some cameras, never all
    est = obs.X[:, 0]
    same_set = np.all(seen[1:] == seen[:-1], axis=1)
    moved = np.linalg.norm(np.diff(est, axis=0), axis=1)
    assert np.all(moved[same_set] < 1e-12)
    assert np.all(moved[~same_set] > 1e-6)


def test_kabsch_matches_scipy_and_rejects_fewer_than_three_markers():
    rng = np.random.default_rng(5)
    model = rng.normal(size=(4, 3)) * 0.05
    R = Rotation.random(random_state=6)
    t = np.array([0.3, -0.2, 1.1])
    meas = (R.apply(model) + t + rng.normal(scale=1e-4, size=(4, 3)))[None]
    Rk, tk, _ = kabsch(model, meas, np.ones((1, 4), bool))
    ref, _ = Rotation.align_vectors(meas[0] - meas[0].mean(0), model - model.mean(0))
    np.testing.assert_allclose(Rk[0], ref.as_matrix(), atol=1e-9)
    Rk2, tk2, _ = kabsch(model, meas, np.array([[True, True, False, False]]))
    assert np.isnan(tk2).all()


def test_body_fit_is_exact_without_errors_and_untracked_below_three_markers():
    cams = ring()
    model = np.array([[0, 0, 0], [0, 28.59, 41.02], [0, 0, 88.0], [0, -44.32, 40.45]]) / 1000
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    X = (model @ R.T + TARGET)[None]
    fit = fit_body(model, observe(cams, X))
    assert fit.tracked[0] and fit.markers_used[0] == 4
    np.testing.assert_allclose(fit.position[0], TARGET, atol=1e-9)
    obs = observe(cams, X, camera_enabled=np.zeros(cams.K, bool))
    fit = fit_body(model, obs)
    assert not fit.tracked[0] and np.isnan(fit.position[0]).all()


def test_segment_distance_and_box_blocking():
    d = segment_segment_distance(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.5, 1, -1]),
                                 np.array([0.5, 1, 1]))
    assert d == pytest.approx(1.0)
    box = PlacedBox.of("b", np.zeros(3), np.eye(3), np.array([0.5, 0.5, 0.5]))
    a = np.array([[-2.0, 0, 0], [-2.0, 2, 0]])
    b = np.array([[2.0, 0, 0], [2.0, 2, 0]])
    assert rays_blocked_by_boxes(a, b, [box]).tolist() == [True, False]


def test_layout_box_placed_in_the_simulator_blocks_what_the_margin_model_blocks():
    """The simulator's occluders are the margin model's Box, placed: for generic rays (no point exactly on a face,
    where the simulator's segment includes its ends and Box.blocks does not) both say the same."""
    rng = np.random.default_rng(3)
    table = Box("table", np.array([-0.4, -1.0, 0.7]), np.array([0.4, 1.0, 0.8]))
    cams = rng.uniform(-3.0, 3.0, (2000, 3)) + [0.0, 0.0, 1.5]
    pts = rng.uniform(-1.0, 1.0, (2000, 3)) + [0.0, 0.0, 0.75]
    placed = PlacedBox.from_layout(table)
    sim = rays_blocked_by_boxes(pts, cams, [placed])
    assert sim.tolist() == table.blocks(cams, pts).tolist()
    assert 100 < sim.sum() < 1900  # both outcomes are exercised
    inside = np.all((pts >= table.lo) & (pts <= table.hi), axis=1)
    assert points_in_boxes(pts, [placed]).tolist() == inside.tolist() and inside.any()


# ---------------------------------------------------------------------------------------------------- OTS
def vega_pose():
    p = np.array([0.0, 1.8, 1.8])
    T = np.eye(4)
    T[:3, :3] = look_at_R_ndi(p, TARGET)
    T[:3, 3] = p
    return T


TOOL = np.array([[0, 0, 0], [0, 28.59, 41.02], [0, 0, 88.0], [0, -44.32, 40.45]]) / 1000


def tool_markers(center: np.ndarray, F: int) -> np.ndarray:
    return np.broadcast_to(TOOL + center, (F, 4, 3)).copy()


def test_ots_accurate_inside_its_frustum():
    ots = OtsModel(Frustum(np.array(NDI_PYRAMID_PLANES)))
    T = vega_pose()
    F = 500
    rng = np.random.default_rng(7)
    z = rng.standard_normal((F, 4, 2, 2))
    fit, part = ots.measure(T, TOOL, tool_markers(TARGET, F), None, Occluders.none(F), z)
    assert fit.tracked.all() and not part.any()
    truth_ots = (np.linalg.inv(T) @ np.append(TARGET, 1.0))[:3]
    err = np.linalg.norm(fit.position - truth_ots, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.3e-3  # Vega class: ~0.1 mm
    assert np.sqrt(np.mean(err**2)) > 1e-6  # there is noise
    fit0, _ = ots.measure(T, TOOL, tool_markers(TARGET, 1), None, Occluders.none(1), np.zeros((1, 4, 2, 2)))
    np.testing.assert_allclose(fit0.position[0], truth_ots, atol=1e-9)


def test_ots_missing_outside_frustum_and_when_blocked():
    ots = OtsModel(Frustum(np.array(NDI_PYRAMID_PLANES)))
    T = vega_pose()
    far = T[:3, 3] + (TARGET - T[:3, 3]) * 2.0  # ~3.7 m away: beyond the 2.4 m far plane
    near = T[:3, 3] + (TARGET - T[:3, 3]) * 0.3  # ~0.55 m: before the 0.95 m near plane
    for c in (far, near):
        fit, _ = ots.measure(T, TOOL, tool_markers(c, 1), None, Occluders.none(1), np.zeros((1, 4, 2, 2)))
        assert not fit.tracked[0] and np.isnan(fit.position[0]).all()
    mid = (T[:3, 3] + TARGET) / 2  # a person standing between the Vega and the tool
    occ = Occluders((mid - [0, 0, 1.0])[None, None], (mid + [0, 0, 1.0])[None, None], np.array([0.25]))
    fit, _ = ots.measure(T, TOOL, tool_markers(TARGET, 1), None, occ, np.zeros((1, 4, 2, 2)))
    assert not fit.tracked[0]
