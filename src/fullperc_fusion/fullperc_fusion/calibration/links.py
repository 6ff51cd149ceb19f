"""The three static links estimated from collected sightings (names and directions as in
:mod:`fullperc_fusion.pipeline.frame_chain`; the robust mean and its covariance: :mod:`.se3_stats`):

* ``T_omc_base``  the robust mean of the OMC's sightings of the base body;
* ``T_base_ots``  eq. (2): the robust mean of the *inverted* OTS sightings of the base tool, inv(T_ots_base_i);
* ``T_rig_ots``   eq. (1): the robust mean of inv(T_omc_rig(t_i)) · T_omc_base · inv(T_ots_base(t_i)) over OMC rig
                  and OTS base sightings paired by stamp, plus the shared T_omc_base's covariance carried through.

Each refuses (:class:`~.se3_stats.CalibrationError`) when fewer than ``min_inlier_fraction`` of the samples are
mutually consistent. :func:`link_bump` compares a live view of a link with its calibration (:mod:`.monitor`).
"""

from __future__ import annotations

import numpy as np

from fullperc_common.transforms import inv_T, mean_T
from fullperc_fusion.calibration.se3_stats import (
    BumpThresholds,
    CalibrationError,
    CalibrationSettings,
    LinkEstimate,
    as_pose_stack,
    compose_jacobian,
    robust_se3_mean,
    se3_residuals,
)


def _check_inliers(est: LinkEstimate, label: str, settings: CalibrationSettings) -> LinkEstimate:
    if est.n_inliers < settings.min_inlier_fraction * est.n_samples:
        raise CalibrationError(
            f"{label}: only {est.n_inliers} of {est.n_samples} samples are mutually consistent "
            f"(need {settings.min_inlier_fraction:.0%}); the body may have moved or the sensor is hopping")
    return est


def link_T_omc_base(T_omc_base_samples, settings: CalibrationSettings | None = None,
                    label: str = "OMC body 'base'") -> LinkEstimate:
    """T_omc_base: the robust mean of the OMC's sightings of the base body."""
    s = settings or CalibrationSettings()
    est = robust_se3_mean(T_omc_base_samples, alpha=s.alpha, source=label, what=label)
    return _check_inliers(est, label, s)


def inv_T_stack(Ts: np.ndarray) -> np.ndarray:
    """``np.stack([inv_T(T) for T in Ts])`` of a stack (N, 4, 4), N >= 1, the same numbers: inv_T's operations on every
    matrix at once (R^T; -R^T as numpy lays it out, times p in one stacked matmul, which multiplies each matrix by its
    vector as the single product does). ~3 us per sighting less (a calibration inverts hundreds)."""
    Rt = Ts[:, :3, :3].swapaxes(1, 2)
    Ti = np.tile(np.eye(4), (len(Ts), 1, 1))
    Ti[:, :3, :3] = Rt
    Ti[:, :3, 3] = (-Rt @ Ts[:, :3, 3:4])[:, :, 0]
    return Ti


def link_T_base_ots(T_ots_base_samples, settings: CalibrationSettings | None = None,
                    label: str = "OTS tool 'base'") -> LinkEstimate:
    """T_base_ots (eq. 2): the robust mean of the inverted OTS sightings inv(T_ots_base_i), as ``StaticLinks``."""
    s = settings or CalibrationSettings()
    Ts = as_pose_stack(T_ots_base_samples, label)
    inv = inv_T_stack(Ts) if len(Ts) else Ts
    est = robust_se3_mean(inv, alpha=s.alpha, source=f"inverse of {label} (eq. 2)", what=label)
    return _check_inliers(est, label, s)


def pair_by_stamp(t_a, t_b, tol_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of mutual-nearest pairs of two stamp lists with |t_a - t_b| <= tol_ns.

    Mutual nearest: each sample is used at most once, so the pairs' noise stays independent when one
    stream is faster than the other. Ties go to the earlier sample.
    """
    ta = np.asarray(t_a, dtype=np.int64)
    tb = np.asarray(t_b, dtype=np.int64)
    if len(ta) == 0 or len(tb) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    oa, ob = np.argsort(ta, kind="stable"), np.argsort(tb, kind="stable")
    sa, sb = ta[oa], tb[ob]

    def nearest(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(dst, src), 1, len(dst) - 1) if len(dst) > 1 else np.zeros(len(src), int)
        if len(dst) == 1:
            return i
        left = np.abs(src - dst[i - 1]) <= np.abs(dst[i] - src)
        return np.where(left, i - 1, i)

    a_of_b = nearest(sb, sa)
    b_of_a = nearest(sa, sb)
    jb = np.arange(len(sb))
    keep = (b_of_a[a_of_b] == jb) & (np.abs(sa[a_of_b] - sb) <= tol_ns)
    return oa[a_of_b[keep]], ob[jb[keep]]


def link_T_rig_ots(t_rig, T_omc_rig_samples, t_ots, T_ots_base_samples, T_omc_base: LinkEstimate,
                   settings: CalibrationSettings | None = None, rig_label: str = "OMC body 'ots_rig'",
                   ots_label: str = "OTS tool 'base'") -> LinkEstimate:
    """T_rig_ots (eq. 1) from stamp-paired rig and base sightings and the calibrated T_omc_base.

    Samples T_rig_ots_i = inv(T_omc_rig_i) · T_omc_base · inv(T_ots_base_i) over the pairs
    (:func:`pair_by_stamp`); robust mean. Covariance to first order: the pairs' own term (covariance of the
    mean of the samples) plus J Σ_omc_base J^T with J = :func:`compose_jacobian`(inv(T̄_omc_rig),
    T_omc_base, T̄_base_ots), since the one T_omc_base is shared by every sample and does not average out.
    The base and rig sightings are treated as independent (an error common to one OMC frame is not modelled).
    """
    s = settings or CalibrationSettings()
    R = as_pose_stack(T_omc_rig_samples, rig_label)
    O = as_pose_stack(T_ots_base_samples, ots_label)
    for lab, t, P in ((rig_label, t_rig, R), (ots_label, t_ots, O)):
        if np.shape(t) != (len(P),):
            raise CalibrationError(f"{lab}: {np.shape(t)} stamps for {len(P)} poses")
    ia, ib = pair_by_stamp(t_rig, t_ots, s.pair_tol_ns)
    label = f"{rig_label} x {ots_label} pairs"
    if len(ia) < s.min_samples:
        raise CalibrationError(
            f"{label}: {len(ia)} pairs within {s.pair_tol_ns / 1e6:g} ms ({len(R)} rig, {len(O)} OTS sightings), "
            f"need >= {s.min_samples}")
    X = T_omc_base.T
    Ob = np.stack([inv_T(T) for T in O[ib]])
    samples = np.stack([inv_T(Ra) @ X @ Bi for Ra, Bi in zip(R[ia], Ob, strict=True)])
    src = f"inv({rig_label}) T_omc_base inv({ots_label}), pairs within {s.pair_tol_ns / 1e6:g} ms (eq. 1)"
    est = _check_inliers(robust_se3_mean(samples, alpha=s.alpha, source=src, what=label), label, s)
    m = est.inliers
    J = compose_jacobian(inv_T(mean_T(list(R[ia][m]))), X, mean_T(list(Ob[m])))
    cov = est.cov + J @ T_omc_base.cov @ J.T
    est.cov = 0.5 * (cov + cov.T)
    return est


def link_bump(cal_link, live_T: np.ndarray, thresholds: BumpThresholds | None = None) -> tuple[bool, float, float]:
    """(bumped, dtrans_m, drot_rad) of a live pose of a link against its calibration.

    ``cal_link``: a :class:`LinkEstimate` or a 4x4; ``live_T`` the same link (same direction) measured now.
    dtrans = |p_live - p_cal|, drot = |Log(R_live R_cal^T)|; bumped when either is strictly beyond its
    threshold. One frame of a Vega's view of the base carries ~0.2 mm and a few mrad of noise, so feed a
    short-window mean (:func:`robust_se3_mean`), and compare in the direction where the noise is small:
    the OTS's view T_ots_base = inv(T_base_ots), not T_base_ots, whose translation carries rotation noise
    times the 2 m lever.
    """
    th = thresholds or BumpThresholds()
    Tc = cal_link.T if isinstance(cal_link, LinkEstimate) else np.asarray(cal_link, dtype=float)
    d = se3_residuals(Tc, np.asarray(live_T, dtype=float)[None])[0]
    dt, dr = float(np.linalg.norm(d[:3])), float(np.linalg.norm(d[3:]))
    return bool(dt > th.trans_m or dr > th.rot_rad), dt, dr
