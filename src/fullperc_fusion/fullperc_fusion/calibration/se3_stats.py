"""Calibration of the static links of the frame chain (issue 15 item 1): robust SE(3) means with covariance.

Links, named and oriented as in :mod:`fullperc_fusion.pipeline.frame_chain` (``T_a_b`` maps points from b into a):

* ``T_omc_base``  the OMC's sightings of the base body, averaged.
* ``T_base_ots``  eq. (2): the average of the *inverted* OTS sightings of the base tool, inv(T_ots_base_i)
                  (what ``StaticLinks`` does today), so T_base_tool = T_base_ots · T_ots_tool.
* ``T_rig_ots``   eq. (1): samples inv(T_omc_rig(t_i)) · T_omc_base · inv(T_ots_base(t_i)) from OMC rig and
                  OTS base sightings paired by stamp (mutual nearest, within ``pair_tol_ns``), averaged.

Tangent space (one convention everywhere; the one of ROS ``PoseWithCovariance``, "rotation about the fixed
axes"): a pose near the mean T̄ = (R̄, p̄) is written with δ = [dx dy dz, rx ry rz] (metres, radians), both
parts in the *parent* frame a of T_a_b:

    p = p̄ + δp,    R = Exp(δθ) · R̄,     i.e. the residual of a sample is  δ_i = [p_i - p̄, Log(R_i R̄^T)].

Robust mean (:func:`robust_se3_mean`):

1. start: coordinate-wise median of the positions; rotation = the medoid (the sample with the smallest
   median angle to the others, over at most 256 evenly spaced samples); per-component robust sigma
   s_j = max(1.4826 MAD_j, floor_j); a sample is kept when every |δ_ij - median_j| <= k1 s_j, k1^2 =
   chi^2_1(1 - alpha).
2. iterate: T̄ = ``mean_T`` of the kept samples (arithmetic mean of positions, chordal L2 mean of rotations);
   C = sample covariance (ddof 1) of the kept residuals; a sample is kept when both block Mahalanobis
   distances, δp^T (C_pp + f_p^2 I)^-1 δp and δθ^T (C_θθ + f_θ^2 I)^-1 δθ, are <= chi^2_3(1 - alpha);
   repeat until the kept set does not change. Every sample is re-tested each round, so one rejected by the
   start can come back. The gate floors f (``GATE_FLOOR``, 10 µm and 0.1 mrad: the order of the Vega's TX
   output resolution, 0.01 mm and quaternion 1e-4 ~ 0.2 mrad) keep noise-free or quantised streams from
   having ordinary samples rejected.
3. covariance of the MEAN: Σ = C / n_inliers + diag(f_p'^2, f_θ'^2) with the floors ``COV_FLOOR`` (1 µm,
   1 µrad, far below any real sensor) so that a calibration is always positive definite. This assumes
   independent samples; noise correlated in time (the OMC's camera-set hops) makes the true uncertainty of
   the mean larger than Σ. With alpha = 1e-3 the truncation of Gaussian samples shrinks C by ~0.5 %
   (P(chi^2_5 <= q) / P(chi^2_3 <= q) = 0.995); not corrected.

Static check (:func:`check_static`): the collection is cut into ``n_windows`` equal time windows; each window's
robust mean is compared with every other's. A pair of windows shows motion when the difference exceeds the
absolute limit (``max_drift_m`` / ``max_drift_rad``) *and* is significant against the noise (Hotelling T^2
with the noise covariance pooled within the windows). The first condition lets through the OMC's
sub-millimetre hops, which are significant but are noise of the sensor, not motion; the second keeps a short,
noisy collection from being refused for noise.

YAML reading and writing are in :mod:`fullperc_fusion.calibration.io`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import chdtri, fdtri  # the chi^2 and F quantiles: scipy.stats costs a node ~0.6 s of start-up

from fullperc_common.transforms import T_to_pq, inv_T, make_T, mean_T
from fullperc_fusion.calibration.poses import BadSample, pose_to_T

CALIBRATION_VERSION = 1
LINK_NAMES = ("T_omc_base", "T_base_ots", "T_rig_ots")
GATE_FLOOR = (1e-5, 1e-4)   # m, rad: sigma floors of the outlier gate
COV_FLOOR = (1e-6, 1e-6)    # m, rad: sigma floors added to the covariance of the mean
_MEDOID_MAX = 256


class CalibrationError(ValueError):
    """A calibration was refused or a calibration file is wrong; the message says which body/file and field."""


# ------------------------------------------------------------------------------------------ data

@dataclass(eq=False)
class LinkEstimate:
    """One static link T_parent_child: mean pose, covariance of the mean and how it was obtained.

    ``position`` [m] and ``quat_xyzw`` (ROS order, scalar last, w >= 0) are the stored form; ``T`` is derived.
    ``cov`` is the 6x6 covariance of the mean in the tangent space [dx dy dz rx ry rz] (parent frame; m^2,
    m rad, rad^2; module docstring). Residual statistics are over the inliers, per sample, in mm and mrad.
    """

    position: np.ndarray
    quat_xyzw: np.ndarray
    cov: np.ndarray
    n_samples: int
    n_inliers: int
    rms_trans_mm: float
    max_trans_mm: float
    rms_rot_mrad: float
    max_rot_mrad: float
    source: str = ""
    inliers: np.ndarray | None = field(default=None, repr=False)  # mask over the samples; not stored

    @property
    def T(self) -> np.ndarray:
        return make_T(self.position, self.quat_xyzw)


@dataclass(eq=False)
class Calibration:
    """The static links of one setup, as written to and read from a calibration YAML."""

    links: dict[str, LinkEstimate]
    stamp_ns: int               # end of the collection (sensor stamps)
    duration_s: float           # span of the collection that was used
    source: str = ""            # free text: what produced it (executable, node start-up, bag ...)
    version: int = CALIBRATION_VERSION

    def T(self, name: str) -> np.ndarray:
        if name not in self.links:
            raise CalibrationError(f"calibration has no link '{name}' (has {sorted(self.links)})")
        return self.links[name].T


@dataclass
class StaticThresholds:
    """When a body counts as moved during a collection (module docstring, static check)."""

    max_drift_m: float = 1.0e-3
    max_drift_rad: float = 3.0e-3
    n_windows: int = 4
    min_window_samples: int = 5
    alpha: float = 1e-4


@dataclass
class CalibrationSettings:
    min_samples: int = 30                 # per body (and per rig/OTS pair for T_rig_ots)
    min_inlier_fraction: float = 0.5      # fewer consistent samples -> refused
    alpha: float = 1e-3                   # outlier gate, per block
    pair_tol_ns: int = 20_000_000         # T_rig_ots: OMC rig and OTS base sightings this close in time
    static: StaticThresholds = field(default_factory=StaticThresholds)


@dataclass
class BumpThresholds:
    trans_m: float = 1.0e-3
    rot_rad: float = 3.0e-3


# ------------------------------------------------------------------------------------------ tangent space

def se3_residuals(T_ref: np.ndarray, Ts: np.ndarray) -> np.ndarray:
    """(N, 6) residuals [p_i - p_ref, Log(R_i R_ref^T)] of a stack of transforms (N, 4, 4)."""
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    dp = Ts[:, :3, 3] - T_ref[:3, 3]
    dth = Rotation.from_matrix(Ts[:, :3, :3] @ T_ref[:3, :3].T).as_rotvec()
    return np.hstack([dp, dth])


def se3_retract(T_ref: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The pose with residual ``delta`` about ``T_ref``: p = p_ref + δp, R = Exp(δθ) R_ref."""
    delta = np.asarray(delta, dtype=float)
    return make_T(T_ref[:3, 3] + delta[:3], R=Rotation.from_rotvec(delta[3:]).as_matrix() @ T_ref[:3, :3])


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def compose_jacobian(A: np.ndarray, X: np.ndarray, B: np.ndarray) -> np.ndarray:
    """d δ(A X B) / d δX, first order, for the parent-frame tangent convention.

    With R_X' = Exp(θ) R_X, p_X' = p_X + dp:  R = Exp(R_A θ) R_A R_X R_B and
    p = p̄ + R_A dp - R_A [R_X p_B]x θ, so J = [[R_A, -R_A [R_X p_B]x], [0, R_A]].
    """
    RA = A[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = RA
    J[:3, 3:] = -RA @ _skew(X[:3, :3] @ B[:3, 3])
    J[3:, 3:] = RA
    return J


# ------------------------------------------------------------------------------------------ robust mean

def as_pose_stack(poses, what: str = "poses") -> np.ndarray:
    """(N, 4, 4) from an (N, 4, 4) array or a (positions (N, 3), quats_xyzw (N, 4)) pair; checked."""
    if isinstance(poses, tuple | list) and len(poses) == 2 and np.ndim(poses[0]) == 2 \
            and np.shape(poses[0])[1] == 3:  # (positions, quaternions), not a list of two 4x4
        P = np.asarray(poses[0], dtype=float)
        Q = np.asarray(poses[1], dtype=float)
        if P.ndim != 2 or P.shape[1] != 3 or Q.shape != (len(P), 4):
            raise CalibrationError(f"{what}: positions {P.shape} and quaternions {Q.shape}; expected (N, 3), (N, 4)")
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(Q))):
            raise CalibrationError(f"{what}: non-finite position or quaternion")
        n = np.linalg.norm(Q, axis=1)
        if np.any(np.abs(n - 1.0) > 1e-2):
            raise CalibrationError(f"{what}: quaternion norm {n[np.argmax(np.abs(n - 1))]:.4g} is not 1 (x y z w)")
        Ts = np.tile(np.eye(4), (len(P), 1, 1))
        Ts[:, :3, :3] = Rotation.from_quat(Q / n[:, None]).as_matrix()
        Ts[:, :3, 3] = P
        return Ts
    Ts = np.asarray(poses, dtype=float)
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
        raise CalibrationError(f"{what}: shape {Ts.shape}; expected (N, 4, 4) or (positions, quaternions)")
    if not np.all(np.isfinite(Ts)):
        raise CalibrationError(f"{what}: non-finite transform")
    R = Ts[:, :3, :3]
    err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2)) if len(Ts) else np.zeros(0)
    if np.any(err > 1e-2) or np.any(np.linalg.det(R) < 0):
        raise CalibrationError(f"{what}: a rotation block is not a rotation")
    return Ts


def _rotation_medoid(Rs: np.ndarray) -> np.ndarray:
    idx = np.unique(np.linspace(0, len(Rs) - 1, min(len(Rs), _MEDOID_MAX)).round().astype(int))
    q = Rotation.from_matrix(Rs[idx]).as_quat()
    ang = 2.0 * np.arccos(np.clip(np.abs(q @ q.T), 0.0, 1.0))
    return Rs[idx[int(np.argmin(np.median(ang, axis=0)))]]


def _block_d2(r: np.ndarray, C: np.ndarray, floor: float) -> np.ndarray:
    Ci = np.linalg.inv(C + floor**2 * np.eye(3))
    return np.einsum("ni,ij,nj->n", r, Ci, r)


def robust_se3_mean(poses, *, alpha: float = 1e-3, max_iter: int = 50, source: str = "",
                    what: str = "poses") -> LinkEstimate:
    """Robust mean pose of N sightings of one static transform, with the 6x6 covariance of the mean.

    ``poses``: (N, 4, 4) transforms or (positions (N, 3) [m], quaternions (N, 4) x y z w). Algorithm, gate
    and covariance convention in the module docstring. Raises :class:`CalibrationError` with fewer than 2
    samples or fewer than 2 inliers. ``inliers`` of the result is the mask of kept samples.
    """
    Ts = as_pose_stack(poses, what)
    n = len(Ts)
    if n < 2:
        raise CalibrationError(f"{what}: {n} sample(s); a mean with covariance needs at least 2")
    q3 = chdtri(3, alpha)                    # chi^2_3 upper alpha quantile (= chi2.ppf(1 - alpha, 3))
    k1 = float(np.sqrt(chdtri(1, alpha)))
    T0 = make_T(np.median(Ts[:, :3, 3], axis=0), R=_rotation_medoid(Ts[:, :3, :3]))
    r = se3_residuals(T0, Ts)
    med = np.median(r, axis=0)
    floors = np.repeat(GATE_FLOOR, 3)
    s = np.maximum(1.4826 * np.median(np.abs(r - med), axis=0), floors)
    mask = np.all(np.abs(r - med) <= k1 * s, axis=1)
    for _ in range(max_iter):
        if mask.sum() < 2:
            break
        Tm = mean_T(list(Ts[mask]))
        r = se3_residuals(Tm, Ts)
        C = np.cov(r[mask], rowvar=False, ddof=1)
        new = (_block_d2(r[:, :3], C[:3, :3], GATE_FLOOR[0]) <= q3) & \
            (_block_d2(r[:, 3:], C[3:, 3:], GATE_FLOOR[1]) <= q3)
        if np.array_equal(new, mask):
            break
        mask = new
    n_in = int(mask.sum())
    if n_in < 2:
        raise CalibrationError(f"{what}: only {n_in} of {n} samples are mutually consistent")
    return _estimate(mean_T(list(Ts[mask])), Ts, mask, source)


def mean_estimate(poses, T_mean: np.ndarray | None = None, *, source: str = "", what: str = "poses") -> LinkEstimate:
    """The plain mean pose of N sightings (every sample kept: ``average`` mode and calibrate mode's bridge,
    :mod:`frame_chain`) with the covariance of the mean of :func:`robust_se3_mean` (module docstring, step 3).

    ``T_mean``: the mean the caller already uses (default ``mean_T`` of all samples); the covariance is taken about
    it. Why a covariance for the plain average: it is the link of every local sample until the calibrated one is
    done, and the pose a filter reports is no better than the link it is expressed through (``pipeline``'s frame
    covariance): 30 Vega sightings of the base tool leave a few tenths of a millimetre at the tool.
    """
    Ts = as_pose_stack(poses, what)
    if len(Ts) < 2:
        raise CalibrationError(f"{what}: {len(Ts)} sample(s); a mean with covariance needs at least 2")
    return _estimate(mean_T(list(Ts)) if T_mean is None else np.asarray(T_mean, dtype=float), Ts,
                     np.ones(len(Ts), dtype=bool), source)


def _estimate(Tm: np.ndarray, Ts: np.ndarray, mask: np.ndarray, source: str) -> LinkEstimate:
    """LinkEstimate of the mean Tm of the samples Ts[mask]: covariance of the mean (module docstring, step 3) and
    the residual statistics."""
    n_in = int(mask.sum())
    r = se3_residuals(Tm, Ts)[mask]
    cov = np.cov(r, rowvar=False, ddof=1) / n_in + np.diag(np.repeat(np.square(COV_FLOOR), 3))
    cov = 0.5 * (cov + cov.T)
    et = np.linalg.norm(r[:, :3], axis=1) * 1e3
    er = np.linalg.norm(r[:, 3:], axis=1) * 1e3
    p, q = T_to_pq(Tm)
    return LinkEstimate(p, q, cov, len(Ts), n_in, float(np.sqrt(np.mean(et**2))), float(et.max()),
                        float(np.sqrt(np.mean(er**2))), float(er.max()), source, mask)


# ------------------------------------------------------------------------------------------ static check

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
    Ts = as_pose_stack(poses, label)
    t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    if t.shape != (len(Ts),):
        raise CalibrationError(f"{label}: {t.shape[0]} stamps for {len(Ts)} poses")
    t0 = int(t.min()) if len(t) else 0
    span = int(t.max()) - t0 if len(t) else 0
    nw = int(th.n_windows)
    w = np.minimum((t - t0) * nw // max(span, 1), nw - 1) if span > 0 else np.zeros(len(t), dtype=int)
    wins, resid = [], []
    for k in range(nw):
        sel = w == k
        if sel.sum() >= max(th.min_window_samples, 2):
            try:
                e = robust_se3_mean(Ts[sel], alpha=alpha, what=label)
            except CalibrationError:
                continue
            r = se3_residuals(e.T, Ts[sel][e.inliers])
            resid.append(r - r.mean(axis=0))
            wins.append((k, e))
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
            (ka, a), (kb, b) = wins[i], wins[j]
            d = se3_residuals(a.T, b.T[None])[0]
            S = C * (1.0 / a.n_inliers + 1.0 / b.n_inliers)
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


# ------------------------------------------------------------------------------------------ links

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


def link_T_base_ots(T_ots_base_samples, settings: CalibrationSettings | None = None,
                    label: str = "OTS tool 'base'") -> LinkEstimate:
    """T_base_ots (eq. 2): the robust mean of the inverted OTS sightings inv(T_ots_base_i), as ``StaticLinks``."""
    s = settings or CalibrationSettings()
    Ts = as_pose_stack(T_ots_base_samples, label)
    inv = np.stack([inv_T(T) for T in Ts]) if len(Ts) else Ts
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


# ------------------------------------------------------------------------------------------ collector

@dataclass
class CalibrationBodies:
    """Body names on the driver topics; same fields and defaults as ``ChainConfig``."""

    omc_base: str = "base"
    ots_base: str = "base"
    omc_rig: str = "ots_rig"

    @classmethod
    def from_chain_config(cls, cfg) -> CalibrationBodies:
        return cls(cfg.omc_base, cfg.ots_base, cfg.omc_rig)


class Collector:
    """Accumulates timestamped sightings for ``duration_s`` and turns them into a :class:`Calibration`.

    Feed every pose with :meth:`add` (device 'omc' or 'ots'); sightings of other bodies are ignored. The
    window starts at ``start_ns`` or the first accepted stamp and holds stamps in [start, start + duration];
    :attr:`complete` turns true once a stamp at or beyond its end arrives. :meth:`finish` checks counts and
    stillness of every body it needs, then estimates ``links`` (T_rig_ots brings T_omc_base with it).
    """

    def __init__(self, links: Sequence[str] = ("T_omc_base", "T_base_ots"),
                 bodies: CalibrationBodies | None = None, duration_s: float = 10.0,
                 settings: CalibrationSettings | None = None, start_ns: int | None = None) -> None:
        bad = [x for x in links if x not in LINK_NAMES]
        if bad or not links:
            raise ValueError(f"links {list(links)}: each must be one of {LINK_NAMES}")
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        self.links = tuple(x for x in LINK_NAMES if x in links or (x == "T_omc_base" and "T_rig_ots" in links))
        self.bodies = bodies or CalibrationBodies()
        self.settings = settings or CalibrationSettings()
        self.duration_ns = int(round(duration_s * 1e9))
        self.start_ns = start_ns
        self.last_ns: int | None = None
        b = self.bodies
        need = {"T_omc_base": [("omc", b.omc_base)], "T_base_ots": [("ots", b.ots_base)],
                "T_rig_ots": [("omc", b.omc_rig), ("ots", b.ots_base)]}
        self._buf: dict[tuple[str, str], list[tuple[int, np.ndarray]]] = {}
        for ln in self.links:
            for key in need[ln]:
                self._buf.setdefault(key, [])
        self.n_bad: dict[tuple[str, str], int] = {k: 0 for k in self._buf}

    @staticmethod
    def label(device: str, body: str) -> str:
        return f"OMC body '{body}'" if device == "omc" else f"OTS tool '{body}'"

    @property
    def complete(self) -> bool:
        return self.start_ns is not None and self.last_ns is not None and \
            self.last_ns >= self.start_ns + self.duration_ns

    def counts(self) -> dict[str, int]:
        return {f"{d}:{b}": len(v) for (d, b), v in self._buf.items()}

    def add(self, device: str, body: str, stamp_ns: int, position, quat_xyzw=None) -> bool:
        """One sighting (position [m] + quaternion x y z w, or a 4x4 as ``position`` with ``quat_xyzw`` None);
        True when it was collected (a needed body, valid pose, inside the window)."""
        key = (device, body)
        if key not in self._buf:
            return False
        stamp_ns = int(stamp_ns)
        self.last_ns = stamp_ns if self.last_ns is None else max(self.last_ns, stamp_ns)
        try:
            T = pose_to_T(position if quat_xyzw is None else (position, quat_xyzw))
        except BadSample:
            self.n_bad[key] += 1
            return False
        if self.start_ns is None:
            self.start_ns = stamp_ns
        if not self.start_ns <= stamp_ns <= self.start_ns + self.duration_ns:
            return False
        self._buf[key].append((stamp_ns, T))
        return True

    def samples(self, device: str, body: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps [ns] (N,), poses (N, 4, 4)) collected of one body, in stamp order."""
        v = sorted(self._buf[(device, body)], key=lambda x: x[0])
        return np.array([s for s, _ in v], dtype=np.int64), np.array([T for _, T in v]).reshape(-1, 4, 4)

    def finish(self, stamp_ns: int | None = None, source: str = "") -> Calibration:
        """The calibration, or :class:`CalibrationError` listing every body that was too sparse or moved."""
        s = self.settings
        problems = []
        data = {}
        for key in self._buf:
            lab = self.label(*key)
            t, Ts = self.samples(*key)
            data[key] = (t, Ts)
            if len(t) < s.min_samples:
                bad = f", {self.n_bad[key]} invalid poses dropped" if self.n_bad[key] else ""
                problems.append(f"too few sightings of {lab}: {len(t)} in {self.duration_ns / 1e9:g} s{bad}, "
                                f"need >= {s.min_samples}")
                continue
            try:
                check_static(lab, t, Ts, s.static, s.alpha)
            except CalibrationError as e:
                problems.append(str(e))
        if problems:
            raise CalibrationError("calibration refused: " + "; ".join(problems))
        b = self.bodies
        out: dict[str, LinkEstimate] = {}
        try:
            if "T_omc_base" in self.links:
                out["T_omc_base"] = link_T_omc_base(data[("omc", b.omc_base)][1], s, self.label("omc", b.omc_base))
            if "T_base_ots" in self.links:
                out["T_base_ots"] = link_T_base_ots(data[("ots", b.ots_base)][1], s, self.label("ots", b.ots_base))
            if "T_rig_ots" in self.links:
                (tr, Tr), (to, To) = data[("omc", b.omc_rig)], data[("ots", b.ots_base)]
                out["T_rig_ots"] = link_T_rig_ots(tr, Tr, to, To, out["T_omc_base"], s,
                                                  self.label("omc", b.omc_rig), self.label("ots", b.ots_base))
        except CalibrationError as e:
            raise CalibrationError(f"calibration refused: {e}") from e
        first = min(int(t[0]) for t, _ in data.values())
        last = max(int(t[-1]) for t, _ in data.values())
        return Calibration(out, int(stamp_ns) if stamp_ns is not None else last, (last - first) / 1e9, source)
