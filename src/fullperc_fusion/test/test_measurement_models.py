"""measurement_models: each equation pinned, and the first-order link propagation checked by Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import make_T
from fullperc_fusion.filters.api import check_covariance
from fullperc_fusion.filters.measurement_models import (
    LocalModelParams,
    OmcModelParams,
    link_covariance_at,
    local_covariance,
    margin_factor,
    omc_covariance,
    omc_systematic_var,
    rotate_cov,
    vega_covariance,
)


def test_margin_factor_is_the_inverse_margin_clamped():
    assert margin_factor(300.0) == pytest.approx(1.0)
    assert margin_factor(150.0) == pytest.approx(2.0)
    assert margin_factor(3000.0) == pytest.approx(0.1)
    assert margin_factor(0.0) == margin_factor(10.0) == pytest.approx(300.0 / 30.0)   # clamped at margin_min
    assert margin_factor(None) == margin_factor(float("nan")) == 1.0


def test_omc_covariance_equation():
    pr = OmcModelParams()
    e, M = 0.5e-3, 150.0
    C = omc_covariance(e, M, pr)
    vp = pr.white_std**2 + (pr.white_fit_gain * e) ** 2 + pr.white_margin_std**2 * 2.0
    sp, sr = omc_systematic_var(e, M, pr)
    assert sp == pytest.approx(pr.sys_floor**2 + (pr.fit_gain * e) ** 2 + pr.margin_std**2 * 2.0, rel=1e-12)
    assert sr == pytest.approx(pr.rot_sys_floor**2 + (pr.fit_gain * e / pr.marker_lever) ** 2
                               + pr.rot_margin_std**2 * 2.0, rel=1e-12)
    assert pr.sys_floor > 0 and pr.rot_sys_floor > 0   # the floors are in: a well-seen point is not error-free
    vr = vp / pr.marker_lever**2 + sr
    np.testing.assert_allclose(np.diag(C), [vp] * 3 + [vr] * 3, rtol=1e-12)
    assert np.count_nonzero(C - np.diag(np.diag(C))) == 0
    check_covariance(C)
    np.testing.assert_array_equal(omc_covariance(e, M, pr, (sp, sr)), C)   # the caller's sys_var, same result
    assert omc_covariance(e, M, pr, (sp, 4 * sr))[3, 3] == pytest.approx(vp / pr.marker_lever**2 + 4 * sr)


def test_omc_covariance_grows_with_fit_error_and_with_a_smaller_margin():
    base = omc_covariance(0.1e-3, 1000.0)
    assert np.all(np.diag(omc_covariance(1e-3, 1000.0)) > np.diag(base))
    assert np.all(np.diag(omc_covariance(0.1e-3, 100.0)) > np.diag(base))
    assert all(a > b for a, b in zip(omc_systematic_var(0.1e-3, 100.0), omc_systematic_var(0.1e-3, 1000.0),
                                     strict=True))
    # unknown fit error (the device says -1, or nothing): the default, never a zero or negative variance
    np.testing.assert_array_equal(omc_covariance(-1.0, 1000.0), omc_covariance(OmcModelParams().default_fit, 1000.0))
    np.testing.assert_array_equal(omc_covariance(None, None), omc_covariance(float("nan"), 300.0))
    check_covariance(omc_covariance(0.0, 1e9))


def test_vega_covariance_grows_with_the_square_of_the_distance():
    pr = LocalModelParams()
    C = vega_covariance(pr.d_ref, pr)
    np.testing.assert_allclose(np.diag(C)[:3], pr.std_ref**2)
    np.testing.assert_allclose(np.diag(C)[3:], pr.rot_std_ref**2)
    np.testing.assert_allclose(vega_covariance(2 * pr.d_ref, pr), 16 * C)       # (2)^(2*2)
    assert np.sqrt(3 * C[0, 0]) == pytest.approx(0.12e-3)                      # NDI: 0.12 mm RMS (3-D)
    check_covariance(vega_covariance(0.0, pr))


def _exp(w):
    return Rot.from_rotvec(w).as_matrix()


def _log(R):
    return Rot.from_matrix(R).as_rotvec()


def test_link_covariance_matches_monte_carlo_through_the_lever_arm():
    """T_a_c = T_a_b T_b_c with the link's error (tangent of calibration.py) drawn from C_link: the chained pose's
    error covariance equals J C_link J^T to first order (small errors: 1e-4 relative to the variance)."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(6, 6))
    C_link = A @ A.T * 1e-8 + np.diag([1e-9] * 3 + [4e-8] * 3)     # ~0.1 mm, ~0.2 mrad, correlated
    T_ab = make_T([0.3, -1.2, 0.8], Rot.from_euler("zyx", [40, -10, 5], degrees=True).as_quat())
    T_bc = make_T([0.2, 0.1, 1.6], Rot.from_euler("zyx", [-20, 30, 10], degrees=True).as_quat())
    T_ac = T_ab @ T_bc
    d = rng.multivariate_normal(np.zeros(6), C_link, size=40000)
    # every draw at once (stacks of 4x4 transforms): T = the perturbed T_ab, Tc = T @ T_bc and its error
    T = np.broadcast_to(T_ab, (len(d), 4, 4)).copy()
    T[:, :3, 3] += d[:, :3]
    T[:, :3, :3] = _exp(d[:, 3:]) @ T_ab[:3, :3]
    Tc = T @ T_bc
    errs = np.empty_like(d)
    errs[:, :3] = Tc[:, :3, 3] - T_ac[:3, 3]
    errs[:, 3:] = _log(Tc[:, :3, :3] @ T_ac[:3, :3].T)
    emp = errs.T @ errs / len(errs)
    C = link_covariance_at(C_link, T_ac[:3, 3] - T_ab[:3, 3])
    scale = np.sqrt(np.outer(np.diag(C), np.diag(C)))
    assert np.max(np.abs(emp - C) / scale) < 0.03      # sampling error of 40000 draws ~ 1/sqrt(N/2) = 0.7 %
    # the lever arm matters: without it the position variance would be far too small
    assert np.trace(C[:3, :3]) > 3 * np.trace(C_link[:3, :3])


def test_local_covariance_is_the_rotated_device_term_plus_the_link_term():
    T_bo = make_T([1.0, 0.0, 0.5], Rot.from_euler("z", 90, degrees=True).as_quat())
    T_ot = make_T([0.0, 0.0, 1.675], [0, 0, 0, 1])
    C_link = np.diag([1e-10] * 3 + [1e-8] * 3)
    C = local_covariance(T_bo, T_ot, None)
    np.testing.assert_allclose(C, rotate_cov(vega_covariance(1.675), T_bo[:3, :3]), atol=1e-20)
    C2 = local_covariance(T_bo, T_ot, C_link)
    np.testing.assert_allclose(C2 - C, link_covariance_at(C_link, T_bo[:3, :3] @ T_ot[:3, 3]), atol=1e-20)
    # the link's 0.1 mrad at a 1.675 m lever: ~0.17 mm across the lever arm, nothing along it (z of ots -> ...)
    lever = T_bo[:3, :3] @ T_ot[:3, 3]
    u = lever / np.linalg.norm(lever)
    assert u @ (C2 - C)[:3, :3] @ u == pytest.approx(1e-10, rel=1e-9)
    dev = np.diag([1e-8] * 3 + [1e-6] * 3)
    np.testing.assert_allclose(local_covariance(T_bo, T_ot, None, device_cov=dev), rotate_cov(dev, T_bo[:3, :3]))
    check_covariance(C2)
