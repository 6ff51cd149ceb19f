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

The static check of a collection (:mod:`.static_check`), the links estimated from the sightings (:mod:`.links`),
the collection itself (:mod:`.collector`) and YAML reading and writing (:mod:`.io`) build on this module; the robust
means of many windows of one stream at once (the static check's, the link monitor's) are :mod:`.se3_batch`'s, the
same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import chdtri  # the chi^2 quantile: scipy.stats costs a node ~0.6 s of start-up

from fullperc_common.so3 import skew
from fullperc_common.transforms import T_to_pq, make_T, mean_T
from fullperc_fusion.calibration.so3_stack import mean_rotation, near_quats, quats, rotvecs

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



@dataclass
class CalibrationBodies:
    """Body names on the driver topics that a :class:`~.collector.Collector` collects; same fields and defaults as
    ``ChainConfig``."""

    omc_base: str = "base"
    ots_base: str = "base"
    omc_rig: str = "ots_rig"

    @classmethod
    def from_chain_config(cls, cfg) -> CalibrationBodies:
        return cls(cfg.omc_base, cfg.ots_base, cfg.omc_rig)


# ------------------------------------------------------------------------------------------ tangent space

def se3_residuals(T_ref: np.ndarray, Ts: np.ndarray) -> np.ndarray:
    """(N, 6) residuals [p_i - p_ref, Log(R_i R_ref^T)] of a stack of transforms (N, 4, 4)."""
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    dp = Ts[:, :3, 3] - T_ref[:3, 3]
    dth = rotvecs(Ts[:, :3, :3] @ T_ref[:3, :3].T)   # Rotation.from_matrix(...).as_rotvec(), bit for bit
    return np.hstack([dp, dth])


def se3_retract(T_ref: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The pose with residual ``delta`` about ``T_ref``: p = p_ref + δp, R = Exp(δθ) R_ref."""
    delta = np.asarray(delta, dtype=float)
    return make_T(T_ref[:3, 3] + delta[:3], R=Rotation.from_rotvec(delta[3:]).as_matrix() @ T_ref[:3, :3])


def compose_jacobian(A: np.ndarray, X: np.ndarray, B: np.ndarray) -> np.ndarray:
    """d δ(A X B) / d δX, first order, for the parent-frame tangent convention.

    With R_X' = Exp(θ) R_X, p_X' = p_X + dp:  R = Exp(R_A θ) R_A R_X R_B and
    p = p̄ + R_A dp - R_A [R_X p_B]x θ, so J = [[R_A, -R_A [R_X p_B]x], [0, R_A]].
    """
    RA = A[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = RA
    J[:3, 3:] = -RA @ skew(X[:3, :3] @ B[:3, 3])
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


def stack_and_quats(poses, what: str = "poses") -> tuple[np.ndarray, np.ndarray | None]:
    """(``as_pose_stack(poses, what)``, :func:`.so3_stack.quats` of its rotations; None for fewer than 2 poses): the
    same stack, quaternions and errors, in the order as_pose_stack raises them. Why: for an (N, 4, 4) stack of
    rotations the quaternion conversion's own test (``near_quats``) already vouches for as_pose_stack's rotation test
    (a matmul, ``eye``, an LAPACK determinant per matrix: ~25 us for 60 sightings, ~0.3 ms for 1200), which then only
    runs where that test does not pass."""
    Ts = poses if isinstance(poses, np.ndarray) and poses.dtype == float else None
    if Ts is None or Ts.ndim != 3 or Ts.shape[1:] != (4, 4) or len(Ts) < 2 or not np.all(np.isfinite(Ts)):
        Ts = as_pose_stack(poses, what)   # every other input, its errors, and the stacks too short for a mean
        return Ts, (quats(Ts[:, :3, :3]) if len(Ts) >= 2 else None)
    q = near_quats(Ts[:, :3, :3])
    if q is None:
        Ts = as_pose_stack(Ts, what)      # its rotation test decides (and raises)
        q = quats(Ts[:, :3, :3])
    return Ts, q


def _median0(x: np.ndarray) -> np.ndarray:
    """``np.median(x, axis=0)`` of a 2-D array, the same values: the middle element of each sorted column, or the
    mean (a + b) / 2 of the two middle ones, as np.median takes them from its partition (a tie of -0.0 and 0.0 may
    come out as either sign in both); NaN columns through np.median itself. Why: np.median's wrapper cost ~15 us per
    call, four calls per robust mean, whose columns hold a few dozen values."""
    s = np.sort(x, axis=0)
    if not len(s) or np.isnan(s[-1]).any():
        return np.median(x, axis=0)
    return sorted_middle(s, 0)


def sorted_middle(s: np.ndarray, axis: int) -> np.ndarray:
    """The median along ``axis`` of ``s``, already sorted along it: its middle element, or the mean (a + b) / 2 of
    the two middle ones (np.median's values; the medians of :func:`_median0`, :func:`medoid_medians` and the
    windows of :mod:`.se3_batch`)."""
    n = s.shape[axis]
    h = n // 2
    if n % 2:
        return np.take(s, h, axis=axis)
    return (np.take(s, h - 1, axis=axis) + np.take(s, h, axis=axis)) / 2


def medoid_indices(n: int) -> np.ndarray:
    """The samples of n among which the medoid is sought: at most ``_MEDOID_MAX``, evenly spaced."""
    # up to _MEDOID_MAX samples the evenly spaced indices are every index (linspace's step is 1.0)
    return np.arange(n) if n <= _MEDOID_MAX else np.unique(np.linspace(0, n - 1, _MEDOID_MAX).round().astype(int))


def medoid_medians(q: np.ndarray) -> np.ndarray | None:
    """Each sample's median angle to the others, ``_median0(2 arccos(clip(|q q^T|, 0, 1)))``, for quaternions ``q``
    (m, 4), or per stack of them (W, m, 4); None where an angle is NaN (np.median's own path decides then).

    The same numbers by the same operations, cheaper (the medoid of 256 samples in ~3/4 of the time; it is the larger
    part of a robust mean of a calibration's hundreds of sightings): the clip in place as ``minimum(., 1)`` (its
    operand is an absolute value, so ``maximum(., 0)`` changes nothing, and NaN stays NaN in both), the doubling in
    place (x * 2.0 is 2.0 * x), and the columns sorted as the rows of the transposed copy, contiguous, which numpy
    sorts ~3x faster than a column in place -- a sort's result is its values in order, whichever way they are
    sorted."""
    G = q @ q.swapaxes(-1, -2)
    np.abs(G, out=G)
    np.minimum(G, 1.0, out=G)
    np.arccos(G, out=G)
    G *= 2.0
    s = np.ascontiguousarray(G.swapaxes(-1, -2))
    s.sort(axis=-1)
    if np.isnan(s[..., -1]).any():
        return None
    return sorted_middle(s, -1)


def _rotation_medoid(Rs: np.ndarray, q_all: np.ndarray | None = None) -> np.ndarray:
    """The sample with the smallest median angle to the others (over at most 256 evenly spaced samples);
    ``q_all``: the quaternions of ``Rs`` (:func:`.so3_stack.quats`) when the caller has them."""
    idx = medoid_indices(len(Rs))
    q = quats(Rs[idx]) if q_all is None else q_all[idx]
    med = medoid_medians(q)
    if med is None:   # a NaN angle: np.median's answer, as _median0 gives it
        med = _median0(2.0 * np.arccos(np.clip(np.abs(q @ q.T), 0.0, 1.0)))
    return Rs[idx[int(np.argmin(med))]]


def cov_rows(r: np.ndarray) -> np.ndarray:
    """``np.cov(r, rowvar=False, ddof=1)`` of a 2-D float array of at least 2 rows, the same numbers: np.cov's own
    steps for that case (its copy, the transposed view, the mean along it, the BLAS product of the view with its
    transpose, the scale 1 / (n - 1)) without its argument handling: ~7 us instead of ~16 per call; a robust mean
    takes one per round and one for its estimate."""
    X = np.array(r, ndmin=2, dtype=float).T
    X -= X.mean(axis=1)[:, None]
    c = np.dot(X, X.T)
    c *= np.true_divide(1, X.shape[1] - 1)
    return c


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
    # every sample's quaternion once: the medoid and each round's mean take rows of it (so3_stack: the same bits
    # as converting the subset; a mean of Ts[mask] is mean_T's, computed from these)
    Ts, q_all = stack_and_quats(poses, what)
    n = len(Ts)
    if n < 2 or q_all is None:
        raise CalibrationError(f"{what}: {n} sample(s); a mean with covariance needs at least 2")
    q3 = chdtri(3, alpha)                    # chi^2_3 upper alpha quantile (= chi2.ppf(1 - alpha, 3))
    k1 = float(np.sqrt(chdtri(1, alpha)))
    T0 = make_T(_median0(Ts[:, :3, 3]), R=_rotation_medoid(Ts[:, :3, :3], q_all))
    r = se3_residuals(T0, Ts)
    med = _median0(r)
    floors = np.repeat(GATE_FLOOR, 3)
    s = np.maximum(1.4826 * _median0(np.abs(r - med)), floors)
    mask = np.all(np.abs(r - med) <= k1 * s, axis=1)
    Tm = r_m = None   # the mean of the samples of ``mask`` and the residuals about it, once known
    for _ in range(max_iter):
        if mask.sum() < 2:
            break
        Tm = _mean_T_of(Ts, q_all, mask)
        r_m = r = se3_residuals(Tm, Ts)
        C = cov_rows(r[mask])
        new = (_block_d2(r[:, :3], C[:3, :3], GATE_FLOOR[0]) <= q3) & \
            (_block_d2(r[:, 3:], C[3:, 3:], GATE_FLOOR[1]) <= q3)
        if np.array_equal(new, mask):
            break   # converged: Tm and r_m are those of the final mask
        mask = new
        Tm = r_m = None
    n_in = int(mask.sum())
    if n_in < 2:
        raise CalibrationError(f"{what}: only {n_in} of {n} samples are mutually consistent")
    if Tm is None:   # the rounds ran out with a new mask
        Tm = _mean_T_of(Ts, q_all, mask)
    return _estimate(Tm, Ts, mask, source, r_m)


def _mean_T_of(Ts: np.ndarray, q_all: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``mean_T(list(Ts[mask]))`` bit for bit, from the quaternions ``q_all`` of every sample: the arithmetic mean
    of the positions (the same contiguous (n, 3) array mean_T stacks) and scipy's chordal mean of the rotations."""
    S = Ts[mask]
    return make_T(np.mean(np.ascontiguousarray(S[:, :3, 3]), axis=0), R=mean_rotation(S[:, :3, :3], q_all, mask))


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


def _estimate(Tm: np.ndarray, Ts: np.ndarray, mask: np.ndarray, source: str,
              r_all: np.ndarray | None = None) -> LinkEstimate:
    """LinkEstimate of the mean Tm of the samples Ts[mask]: covariance of the mean (module docstring, step 3) and
    the residual statistics; ``r_all``: ``se3_residuals(Tm, Ts)`` when the caller has them."""
    n_in = int(mask.sum())
    r = (se3_residuals(Tm, Ts) if r_all is None else r_all)[mask]
    cov = cov_rows(r) / n_in + np.diag(np.repeat(np.square(COV_FLOOR), 3))
    cov = 0.5 * (cov + cov.T)
    et = np.linalg.norm(r[:, :3], axis=1) * 1e3
    er = np.linalg.norm(r[:, 3:], axis=1) * 1e3
    p, q = T_to_pq(Tm)
    return LinkEstimate(p, q, cov, len(Ts), n_in, float(np.sqrt(np.mean(et**2))), float(et.max()),
                        float(np.sqrt(np.mean(er**2))), float(er.max()), source, mask)
