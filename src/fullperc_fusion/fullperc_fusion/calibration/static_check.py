"""Static check of a collection: did a body move while its sightings were collected?

Static check (:func:`check_static`): the collection is cut into ``n_windows`` equal time windows; each window's
robust mean is compared with every other's. A pair of windows shows motion when the difference exceeds the
absolute limit (``max_drift_m`` / ``max_drift_rad``) *and* is significant against the noise (Hotelling T^2
with the noise covariance pooled within the windows). The first condition lets through the OMC's
sub-millimetre hops, which are significant but are noise of the sensor, not motion; the second keeps a short,
noisy collection from being refused for noise.

Used by :class:`~.collector.Collector` before any link is estimated: a mean over a body that moved is no link.
"""

from __future__ import annotations

import numpy as np
from scipy.special import fdtri  # the F quantile: scipy.stats costs a node ~0.6 s of start-up

from fullperc_fusion.calibration.se3_batch import robust_se3_means_of
from fullperc_fusion.calibration.se3_stats import (
    COV_FLOOR,
    CalibrationError,
    StaticThresholds,
    se3_residuals,
    stack_and_quats,
)


def hotelling_threshold(alpha: float, dof: int, p: int = 3) -> float:
    """Upper 1 - alpha quantile of Hotelling's T^2 (p dims, covariance estimated with ``dof`` degrees of freedom).

    T^2 = p dof / (dof - p + 1) F(p, dof - p + 1); tends to chi^2_p(1 - alpha) as dof grows. With a covariance
    estimated from few samples, chi^2 would be far too small: E[S^-1] = Sigma^-1 dof / (dof - p - 1).
    """
    if dof < p:
        return float("inf")
    return float(p * dof / (dof - p + 1) * fdtri(p, dof - p + 1, 1.0 - alpha))


def check_static(label: str, stamps_ns, poses, thresholds: StaticThresholds | None = None,
                 alpha: float = 1e-3) -> None:
    """Raise :class:`CalibrationError` naming ``label`` when the body moved during the collection.

    ``poses`` are the raw sightings (sensor frame, e.g. T_omc_base_i or T_ots_base_i) at ``stamps_ns``;
    ``alpha`` is the outlier gate of the windows' robust means. Each window k (``n_windows`` equal spans of
    the stamps, at least ``min_window_samples`` sightings) gives a robust mean T_k over n_k inliers. The noise
    covariance C is pooled over the windows (inlier residuals about their own window's mean, dof
    nu = sum n_k - K), so motion between windows does not count as noise. Windows a and b differ by
    Δ = residual of T_b about T_a; per block, with S = C (1/n_a + 1/n_b), the difference is significant when
    Δ^T S^-1 Δ exceeds :func:`hotelling_threshold` (thresholds.alpha, nu). Moved = |Δp| > max_drift_m and
    significant, or |Δθ| > max_drift_rad and significant. Also refuses when fewer than two windows are
    usable: then nothing tells whether the body stayed still.
    """
    th = thresholds or StaticThresholds()
    Ts, _ = stack_and_quats(poses, label)   # as_pose_stack's stack and errors
    t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    if t.shape != (len(Ts),):
        raise CalibrationError(f"{label}: {t.shape[0]} stamps for {len(Ts)} poses")
    t0 = int(t.min()) if len(t) else 0
    span = int(t.max()) - t0 if len(t) else 0
    nw = int(th.n_windows)
    w = np.minimum((t - t0) * nw // max(span, 1), nw - 1) if span > 0 else np.zeros(len(t), dtype=int)
    # each window's robust mean (robust_se3_mean of its samples; a window it refuses is not used), the windows of
    # one size together (se3_batch: the same numbers)
    sels = [np.flatnonzero(w == k) for k in range(nw)]
    used = [k for k in range(nw) if len(sels[k]) >= max(th.min_window_samples, 2)]
    wins, resid = [], []
    for k, m in zip(used, robust_se3_means_of(Ts, [sels[k] for k in used], alpha=alpha), strict=True):
        if m is None:
            continue
        T_k, inliers = m
        r = se3_residuals(T_k, Ts[sels[k]][inliers])
        resid.append(r - r.mean(axis=0))
        wins.append((k, T_k, int(inliers.sum())))
    if len(wins) < 2:
        raise CalibrationError(
            f"{label}: sightings fill only {len(wins)} of {nw} time windows of the {span / 1e9:.1f} s collection "
            f"(need >= {th.min_window_samples} in at least 2) - cannot tell whether it stayed still")
    R = np.vstack(resid)
    dof = len(R) - len(wins)
    C = R.T @ R / dof + np.diag(np.repeat(np.square(COV_FLOOR), 3))
    q = hotelling_threshold(th.alpha, dof)
    worst = None
    for i in range(len(wins)):
        for j in range(i + 1, len(wins)):
            (ka, Ta, na), (kb, Tb, nb) = wins[i], wins[j]
            d = se3_residuals(Ta, Tb[None])[0]
            S = C * (1.0 / na + 1.0 / nb)
            dt, dr = float(np.linalg.norm(d[:3])), float(np.linalg.norm(d[3:]))
            sig_t = d[:3] @ np.linalg.solve(S[:3, :3], d[:3]) > q
            sig_r = d[3:] @ np.linalg.solve(S[3:, 3:], d[3:]) > q
            moved = (dt > th.max_drift_m and sig_t) or (dr > th.max_drift_rad and sig_r)
            score = max(dt / th.max_drift_m, dr / th.max_drift_rad)
            if moved and (worst is None or score > worst[0]):
                worst = (score, ka, kb, dt, dr)
    if worst is not None:
        _, ka, kb, dt, dr = worst
        ws = span / 1e9 / nw
        raise CalibrationError(
            f"{label} moved during the collection: {dt * 1e3:.2f} mm / {dr * 1e3:.2f} mrad between its mean over "
            f"{ka * ws:.1f}-{(ka + 1) * ws:.1f} s and over {kb * ws:.1f}-{(kb + 1) * ws:.1f} s of the "
            f"{span / 1e9:.1f} s collection (allowed {th.max_drift_m * 1e3:.2f} mm / "
            f"{th.max_drift_rad * 1e3:.2f} mrad); keep the setup still and calibrate again")
