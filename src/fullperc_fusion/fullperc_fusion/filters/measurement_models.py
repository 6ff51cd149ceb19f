"""Measurement noise models (issue 18 item 2): the 6x6 pose covariance of an OMC and of a local (Vega) sample.

Only the ``fullperc`` filter uses these (its registry entry declares ``models``); the paper's four keep their fixed
noise. Every model is a small pure function with its equation in the docstring; the constants are device
specifications or statistics of the RAW sensors against the Diana ground truth (never of a filter's output), each
with its origin below.

Convention (:mod:`.api`): ROS order [x y z, rx ry rz]; position in metres in the parent frame, rotation a
small rotation vector about the parent's axes, R_true = Exp(dtheta) R_est.

Raw-sensor statistics used below ("raw stats"): the 6 ``bags/spec`` twin bags (device-specification noise),
every tracked /omc/tool and /ots/tool sample mapped into ``base`` by the node's frame chain, compared with the
Diana forward kinematics; the OMC's view margin from :func:`margin.margin_at` on ``config/or_layout.yaml``
(``fit_noise_model bags/spec bags/paper``, :mod:`fullperc_eval.evaluation.sensor_stats`, which also writes them as
a noise-model file for another installation: :mod:`noise_model_file`). Per-axis variance regressed on
[1, fit_error^2, 300/margin] (a term printed negative: the data show none):

* OMC total error (white + systematic): sqrt(a) = 0.121 mm (0.120 mm beyond the white floor), k_fit = 0.96,
  margin term 0.378 mm at 300 deg; rotation: floor 0.62 mrad, k_rot_fit = 17.2 rad/m, margin term 1.31 mrad at
  300 deg; median fit error 0.088 mm. The ``paper`` profile's bags (worse calibrated cameras): floor 1.46 mm, fit
  gain 0.72, margin term 4.4 mm, rotation margin term 13.5 mrad, median fit error 0.29 mm -- the margin term grows
  with the miscalibration, and it differs between installations (seeds);
* OMC white part (frame-to-frame: consecutive differences / sqrt 2, same regression): floor 0.020 mm, margin term
  0.076 mm at 300 deg, fit gain 0.25; robust (MAD) white jitter 0.033-0.038 mm per axis in both profiles;
* time structure of the OMC error (rms per-axis increment over a lag L): spec 0.071 / 0.175 / 0.301 mm at
  L = 8 ms / 1 s / 10 s, paper 0.091 / 0.79 / 2.11 mm; fitted as white + first-order Gauss-Markov,
  D(L) = 2 w^2 + 2 s^2 (1 - exp(-L / tau)): position tau = 3.06 s (spec) / 18 s (paper), s = 0.21 / 2.28 mm.
  The rotation error as white + two Gauss-Markov processes: paper 1.2 mrad white, 5.3 mrad / 0.33 s fast (reverts
  within frames: noise of the sample, here), 8.94 mrad / 3.38 s slow (``FullpercParams.rot_sys_std`` /
  ``rot_sys_time``); spec 1.15 mrad, 1.36 mrad / 0.40 s, 1.44 mrad / 2.8 s. Over the distance between two samples
  instead of their time lag (white + Gauss-Markov): paper 10.0 mrad with a length of 52.7 mm
  (``FullpercParams.rot_bias_length``), spec 2.1 mrad / 36 mm. Beyond the white
  jitter the error is systematic and decorrelates within seconds of motion (distortion along the path,
  camera-set changes). Each OMC sample's fit error is its own body's (``/omc/tool/quality``): before 2026-12-02 the
  statistics took, at each stamp, the fit error of whichever body's quality came last -- the instrument's -- and
  dropped the samples where the instrument was not tracked, so the constants then in force (k_fit 0.52, rotation
  5.8 rad/m, floor 1.64 mrad, margin term 4.35 mrad) were regressed on another body's fit error;
* ``test/test_model_constants.py`` recomputes these on the committed bags and fails when a constant below (or one
  of ``FullpercParams``) is no longer what they give;
* Vega tool (chain included) per axis 0.13 mm mid-volume, 0.17-0.19 mm at the ends of the 0.95-2.4 m volume;
  orientation ~2.2 mrad per axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# The paper's GVV threshold (§5: theta ~ 50 deg, k = 6 -> ~300 deg): the margin at which the OMC's margin
# term has its reference value.
MARGIN_REF_DEG = 300.0
# The 6x6 templates the matrices below start from: a copy with the non-zero entries written in (ndarray.put for
# scattered ones: one call instead of np.diag or a 36-entry array literal, which cost more per sample).
_ZERO6 = np.zeros((6, 6))
_EYE6 = np.eye(6)
_DIAG6 = np.arange(0, 36, 7)                                               # the diagonal, in C.ravel()
_SKEW6 = np.array([4, 5, 9, 11, 15, 16])                                    # [0:3, 3:6] without its diagonal


@dataclass(frozen=True)
class OmcModelParams:
    """Constants of :func:`omc_covariance` and :func:`omc_systematic_var`; origin of each in the module docstring
    ("raw stats"). The systematic error's correlation time (~3 s, Gauss-Markov fit of the structure function) is
    the filter's ``FullpercParams.sys_time``.

    white_std        [m]      per-axis white floor
    white_fit_gain   [-]      per-axis white std per metre of the device's RMS marker fit error
    white_margin_std [m]      per-axis white std of the view-margin term at ``margin_ref`` degrees
    sys_floor        [m]      per-axis systematic std everywhere (the total's floor beyond the white one:
                              sqrt(0.121^2 - 0.020^2) mm; the miscalibration every point has)
    fit_gain         [-]      per-axis systematic std per metre of fit error
    margin_std       [m]      per-axis systematic std of the view-margin term at ``margin_ref``
    margin_ref       [deg]    reference margin (the paper's GVV threshold)
    margin_min       [deg]    margins below this count as this (a point one camera pair barely sees)
    marker_lever     [m]      rotation std = position std / lever: k_fit / k_rot_fit = 0.956 / 17.2 rad/m = 56 mm,
                              so the fit-error term of the rotation is the regression's (a ~9 cm tool)
    rot_sys_floor    [rad]    per-axis systematic rotation std everywhere (the rotation total's floor beyond
                              the white position floor over the lever: 0.51 mrad)
    rot_margin_std   [rad]    per-axis systematic rotation std of the margin term at ``margin_ref``
    default_fit      [m]      fit error assumed when the device reports none (-1): the spec bags' median
    """

    white_std: float = 0.0197e-3
    white_fit_gain: float = 0.248
    white_margin_std: float = 0.0759e-3
    sys_floor: float = 0.120e-3
    fit_gain: float = 0.956
    margin_std: float = 0.378e-3
    margin_ref: float = MARGIN_REF_DEG
    margin_min: float = 30.0
    marker_lever: float = 0.956 / 17.2
    rot_sys_floor: float = 0.506e-3
    rot_margin_std: float = 1.31e-3
    default_fit: float = 0.0882e-3


@dataclass(frozen=True)
class LocalModelParams:
    """Constants of :func:`vega_covariance`.

    std_ref      [m]    per-axis std at ``d_ref``: NDI Polaris Vega 0.12 mm RMS (3-D) volumetric -> 0.12/sqrt(3)
    d_ref        [m]    middle of the Vega's characterised volume (0.95-2.4 m)
    exponent     [-]    stereo triangulation: depth error ~ d^2 / (baseline f) at constant pixel noise
    rot_std_ref  [rad]  per-axis orientation std at ``d_ref`` (raw stats, ~2.2 mrad; a ~30 mm tool)
    """

    std_ref: float = 0.12e-3 / np.sqrt(3.0)
    d_ref: float = 1.675
    exponent: float = 2.0
    rot_std_ref: float = 2.2e-3


def margin_factor(margin_deg: float | None, ref_deg: float = MARGIN_REF_DEG, min_deg: float = 30.0) -> float:
    """f(M) = M_ref / max(M, M_min): the margin term's variance scale; 1 without a margin (None or non-finite).

    The paper's model (§4): a point seen by fewer camera pairs, at worse convergence angles, has a smaller summed
    margin M and is triangulated from fewer rays, so its error is larger. The summed margin grows roughly with
    the number of valid pairs; a least-squares solution over k rays has a variance ~1/k: variance ~ 1/M.
    """
    if margin_deg is None or not math.isfinite(margin_deg):   # math's test: np.isfinite's answer, without its call
        return 1.0
    return float(ref_deg / max(float(margin_deg), min_deg))


def _fit(fit_error: float | None, params: OmcModelParams) -> float:
    if fit_error is None or not math.isfinite(fit_error) or fit_error < 0:
        return params.default_fit
    return float(fit_error)


def omc_covariance(fit_error: float | None, margin_deg: float | None,
                   params: OmcModelParams = OmcModelParams(),
                   sys_var: tuple[float, float] | None = None) -> np.ndarray:
    """6x6 measurement covariance R of one OMC body pose (isotropic, so the same in any frame).

        position, the WHITE (frame-to-frame) part:   sigma_p^2 = w^2 + (k_w e)^2 + m_w^2 f(M)
        rotation, white + systematic:                sigma_r^2 = sigma_p^2 / lever^2 + s_r^2   (omc_systematic_var)
        C = diag(sigma_p^2 I3, sigma_r^2 I3)

    e the device's RMS marker fit error [m] (``default_fit`` when unknown: None or < 0), M the view margin at the
    point [deg] (:func:`margin_factor`). Fewer, worse-placed cameras and rays that disagree (large fit error) make
    every frame's triangulation noisier; a rotation error of a rigid body is its marker error over the lever.

    Why the position gets its white part only: the rest of the OMC's position error is systematic (the same for
    about a second along the path, module docstring); a filter given it as white R would average it away, which
    it cannot be. ``fullperc`` models it as a bias state (Gauss-Markov, variance :func:`omc_systematic_var`).
    Why the rotation gets both: its systematic part decorrelates within ~1 s (Gauss-Markov fit, module
    docstring) and jumps (one marker's camera set changes: a step of ~0.3 mm over a 90 mm lever is 3 mrad) and
    reverts within frames (the filter's single-frame innovations of 4-8 mrad at a modelled white level of
    0.7 mrad, spec bags); a bias state cannot follow that, so it counts as noise of the sample.

    ``sys_var``: :func:`omc_systematic_var` of the same arguments when the caller has it already (the pipeline
    needs it for the sample's bias model too); computed here otherwise.
    """
    vp, vr, _ = omc_variances(fit_error, margin_deg, params, sys_var)
    return _diag6(vp, vr)


def omc_variances(fit_error: float | None, margin_deg: float | None, params: OmcModelParams = OmcModelParams(),
                  sys_var: tuple[float, float] | None = None) -> tuple[float, float, tuple[float, float]]:
    """(sigma_p^2, sigma_r^2, sys_var): the diagonal of :func:`omc_covariance` and :func:`omc_systematic_var` (unless
    given), the fit error and margin factor taken once for both (the pipeline needs all three per OMC sample)."""
    e = _fit(fit_error, params)
    f = margin_factor(margin_deg, params.margin_ref, params.margin_min)
    vp = params.white_std**2 + (params.white_fit_gain * e) ** 2 + params.white_margin_std**2 * f
    if sys_var is None:
        sys_var = _systematic_var(e, f, params)
    return vp, vp / params.marker_lever**2 + sys_var[1], sys_var


def omc_systematic_var(fit_error: float | None, margin_deg: float | None,
                       params: OmcModelParams = OmcModelParams()) -> tuple[float, float]:
    """Per-axis variance of the OMC's systematic error (position [m^2], rotation [rad^2]) at this sample.

        s_p^2 = s_0^2 + (k_fit e)^2 + m^2 f(M),   s_r^2 = r_0^2 + (k_fit e / lever)^2 + m_r^2 f(M)

    The stationary variance of the Gauss-Markov bias of ``fullperc`` (correlation time ``FullpercParams.sys_time``).
    Margin-adaptive: where few cameras see the body or their rays disagree, the OMC's systematic error is larger.
    """
    return _systematic_var(_fit(fit_error, params), margin_factor(margin_deg, params.margin_ref, params.margin_min),
                           params)


def _systematic_var(e: float, f: float, params: OmcModelParams) -> tuple[float, float]:
    """:func:`omc_systematic_var` of the fit error ``e`` (:func:`_fit`) and the margin factor ``f``."""
    vp = params.sys_floor**2 + (params.fit_gain * e) ** 2 + params.margin_std**2 * f
    vr = params.rot_sys_floor**2 + (params.fit_gain * e / params.marker_lever) ** 2 + params.rot_margin_std**2 * f
    return vp, vr


def vega_covariance(distance_m: float, params: LocalModelParams = LocalModelParams()) -> np.ndarray:
    """6x6 covariance of one Vega tool pose in the ``ots`` frame, from the tool's distance d to the Vega.

        s(d) = (d / d_ref)^exponent
        C = diag((std_ref s)^2 I3, (rot_std_ref s)^2 I3)

    Isotropic for simplicity (a stereo bar's depth axis is worse than its lateral ones; the NDI figure is an
    RMS over all three). d is floored at 0.1 m so a degenerate pose does not give a zero covariance.
    """
    return _diag6(*vega_variances(distance_m, params))


def vega_variances(distance_m: float, params: LocalModelParams = LocalModelParams()) -> tuple[float, float]:
    """(position, rotation) per-axis variance on the diagonal of :func:`vega_covariance`."""
    s = (max(float(distance_m), 0.1) / params.d_ref) ** params.exponent
    return (params.std_ref * s) ** 2, (params.rot_std_ref * s) ** 2


def _diag6(vp: float, vr: float) -> np.ndarray:
    """diag(vp, vp, vp, vr, vr, vr)."""
    C = _ZERO6.copy()
    C.put(_DIAG6, (vp, vp, vp, vr, vr, vr))
    return C


def rotate_cov(cov: np.ndarray, R: np.ndarray) -> np.ndarray:
    """C' = J C J^T, J = diag(R, R): a pose covariance expressed in a parent frame turned by R."""
    J = np.zeros((6, 6))
    J[0:3, 0:3] = J[3:6, 3:6] = R
    out = J @ cov @ J.T
    return 0.5 * (out + out.T)


def rotate_diag_cov(vp: float, vr: float, R: np.ndarray) -> np.ndarray:
    """:func:`rotate_cov` of diag(vp, vp, vp, vr, vr, vr) (the OMC's and the Vega's model covariances), bit for bit.

    J C of a diagonal C has one product per entry (J_ij C_jj; the other terms of its sum are exact zeros), so it is
    J times C's diagonal, element-wise, instead of a matrix product; (J C) J^T is the same matrix product as
    :func:`rotate_cov`'s (``test_imm_fast.py`` holds the two equal)."""
    J = _ZERO6.copy()
    J[0:3, 0:3] = J[3:6, 3:6] = R
    out = (J * np.array((vp, vp, vp, vr, vr, vr))) @ J.T
    return 0.5 * (out + out.T)


def link_covariance_at(link_cov: np.ndarray, lever_arm) -> np.ndarray:
    """Covariance a static link T_a_b (6x6, tangent of :mod:`calibration`) adds to a pose T_a_b · T_b_c.

    With the link's error p_ab = p̄_ab + dp, R_ab = Exp(dphi) R̄_ab (parent frame a), the chained pose is, to
    first order,

        p_ac = p̄_ac + dp + dphi x l,   l = p_ac - p_ab (the lever arm: from the link's origin to the point),
        R_ac = Exp(dphi) R̄_ac,

    so the chained pose's error is J [dp; dphi] with J = [[I, -[l]x], [0, I]] and C = J C_link J^T. The link's
    rotation error times the lever arm is what dominates a Vega 1.5 m from the tool.
    """
    if isinstance(lever_arm, np.ndarray) and lever_arm.shape == (3,):
        x, y, z = lever_arm.tolist()   # the floats float() gives, in one call
    else:
        x, y, z = (float(v) for v in lever_arm)
    J = _EYE6.copy()   # I with -[l]x written into its [0:3, 3:6] block
    J.put(_SKEW6, (z, -y, -z, x, y, -x))
    out = J @ np.asarray(link_cov, dtype=float) @ J.T
    return 0.5 * (out + out.T)


def local_covariance(T_base_ots: np.ndarray, T_ots_tool: np.ndarray, link_cov: np.ndarray | None,
                     params: LocalModelParams = LocalModelParams(), device_cov: np.ndarray | None = None) -> np.ndarray:
    """6x6 covariance in ``base`` of a local sample T_base_tool = T_base_ots · T_ots_tool.

        C = J_R C_dev J_R^T + J_l C_link J_l^T,   C_dev = C_vega(|p_ots_tool|) (or the device's own covariance)

    J_R = diag(R_base_ots, R_base_ots) (:func:`rotate_cov`), J_l of :func:`link_covariance_at` with the lever arm
    l = R_base_ots p_ots_tool. The two errors are independent (the Vega's noise now, the calibration's then).
    ``link_cov`` None (links given as parameters or averaged without a covariance): the device term alone.
    """
    R = T_base_ots[:3, :3]
    p = T_ots_tool[:3, 3]
    if device_cov is None:
        d = p.ravel(order="K")   # |p| as np.linalg.norm computes it (sqrt of the dot), without its wrapper
        C = rotate_diag_cov(*vega_variances(math.sqrt(d.dot(d)), params), R)
    else:
        C = rotate_cov(device_cov, R)
    if link_cov is not None:
        C = C + link_covariance_at(link_cov, R @ p)
    return 0.5 * (C + C.T)
