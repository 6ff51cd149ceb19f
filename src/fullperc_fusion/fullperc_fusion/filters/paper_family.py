"""One Kalman filter, four configurations: KF, BKF, CKF, CBKF (paper §3.2, eq. 3-14).

This is the general (matrix) form and the reference, written independently of the closed form: the registry
(:mod:`.registry`) serves the same filters in closed form per axis (:mod:`.paper_fast`, one sample at a time, and
:mod:`.paper_batch`, a whole replay, both on the one per-axis kernel :mod:`.paper_kernel`), which the tests hold to
this form (test_fast_filter.py, 1e-12) and which falls back to it when a covariance couples the axes.

State per target (all in ``base``, metres): x = [p v b] (9 states) with the compensation (bias) term b
of the global source, or x = [p v] (6 states) without it.

=====  ==========  ===================  =====================================================
kind   bias state  biased estimator M   meaning
=====  ==========  ===================  =====================================================
kf     no          no                   plain constant-velocity KF, both sources measure p
bkf    no          yes                  biased KF of ref. [29]: x = M x'', P = M P M^T
ckf    yes         no                   compensated KF: global measures p + b, local measures p
cbkf   yes         yes                  the paper's method (default)
=====  ==========  ===================  =====================================================

Equations, with dt from the sample stamps:

* prediction (eq. 9, 10): x' = F x, P' = F P F^T + Q, F = [[I, dt I, 0], [0, I, 0], [0, 0, I]];
  Q is the white-acceleration constant-velocity model per axis, q_a [[dt^3/3, dt^2/2], [dt^2/2, dt]],
  plus a bias random walk q_b dt I.
* measurement (eq. 11): H_global = [I 0 I], H_local = [I 0 0] (without the bias state both are [I 0]);
  a synchronised (global, local) pair is one stacked update with H = [[H_global], [H_local]].
  When the two samples of a pair were taken at different stamps, the filter is predicted to the newer
  one and the older sample, taken ``lag`` seconds earlier, is modelled exactly under constant velocity
  as p(t - lag) = p(t) - lag v(t): its H row gets -lag I in the velocity block (lag = 0 gives eq. 11).
* R (block-diagonal, one 3x3 block per measurement): the position block ``cov[:3, :3]`` of the measurement's
  covariance (:class:`~.api.Measurement`), or the paper's fixed noise ``global_std^2 I`` / ``local_std^2 I``
  when it has none (the default; bit-identical to the filters before the seam).
* gain and update (eq. 12, 13): G = P' H^T (H P' H^T + R)^-1, x'' = x' + G (y - H x'), and
  P = (I - G H) P' (I - G H)^T + G R G^T (Joseph form: equal to eq. 12's (I - G H) P' for the optimal
  gain, but stays symmetric positive semi-definite in floating point).
* biased estimator (eq. 4-8, 14): M = diag(m_i), m_i = x_i^2 / (var_i + x_i^2) with the unknown x_i
  replaced by its unbiased estimate x''_i (plug-in, as in Thompson 1968 shrinkage) and var_i = P_ii;
  x = M x''. (Eq. 6 prints x^b_i = (m_i)^2 x_i; eq. 4 defines x^b = M x, which is what eq. 7 minimises.)

Decisions where the paper leaves room (each pinned by a test in test_filters.py):

* Eq. (14), second line, reads P_k = M_k P'_k M_k^T with the *predicted* P'_k. We use the *updated*
  P_k of eq. (12): P_k = M_k P_k M_k^T. Reasons: (a) with P'_k the information of every measurement is
  thrown away -- P never shrinks, P_pp grows by Q each step without bound, the gain tends to I and the
  filter degenerates into following the raw measurements; (b) eq. (12) computes P_k and nothing else
  would use it; (c) eq. (5) takes the MSE of x^b = M x'' whose unbiased part has covariance P_k
  (updated), so M P_k M^T is the covariance of the biased estimate. ``eq14_covariance='prior'``
  reproduces the literal reading for the test that shows the divergence.
* What M does to the gain: P = M P M^T scales row/column i of P by m_i, so the next prior P' and with
  it the gain for state i shrink too -- a state whose estimate is small compared with its uncertainty
  loses value *and* gain, step after step. Applied to every state as eq. (4) literally says, this
  breaks the filter in two ways (measured on the synthetic B->P stream of test_filters.py):
  - velocity: a target moving at a few cm/s has |v| comparable to sigma_v, so m_v ~ 0.03-0.5 at every
    step; the velocity and its gain collapse, the constant-velocity model degenerates into a random
    walk with tiny Q, and the estimate lags the moving target by several millimetres;
  - bias: b starts at 0, so m_b = 0 and the b rows of P are zeroed; b = 0 is absorbing, the
    compensation is never learned, and whatever was learned is multiplied by m_b < 1 at every
    global-only step -- exactly when the compensation is needed (the B->P case).
  Hence M acts on the position block only (``shrink_blocks``, default ("p",)). There, eq. (7) is a
  shrinkage towards the origin of ``base``: positions are tens of centimetres with var ~1e-8 m^2, so
  m = 1 - O(1e-7) and BKF stays within micrometres of KF, CBKF of CKF -- the same pattern as the
  paper's Table 1 (BKF within 0.02 mm of KF, CBKF within 0.01 mm of CKF), which a velocity or bias
  shrinkage could not produce. The other blocks stay selectable for experiments.
* Hops: the normalised innovation squared of the global rows, NIS_g = y_g^T S_gg^-1 y_g, is compared
  with a chi^2 gate (3 dof, 99.9 % -> 16.27). A hop is flagged for every kind. With a bias state and
  ``hop_to_bias`` the bias variance is raised by y_g^2 (per axis) before the gain is computed, so a
  step of the global source goes into b rather than p: hops come from the set of seeing cameras
  changing, i.e. from the sensor, while the target moves smoothly. This is how the compensated
  filters "counter hop errors when only global information is accessible" (paper §3.2).
* A gap longer than ``max_gap_s`` without any sample re-initialises p and v from the next sample
  (constant-velocity extrapolation over seconds is meaningless); b and its variance are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullperc_fusion.filters.api import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    Measurement,
    Step,
    StepCompat,
    predict_interval,
    split_update,
)

__all__ = ["FILTER_KINDS", "SOURCE_GLOBAL", "SOURCE_LOCAL", "FilterParams", "FusionFilter", "PassThrough", "Step",
           "biased_factors", "kalman_update", "measurement_matrix", "process_noise", "transition"]

FILTER_KINDS = ("kf", "bkf", "ckf", "cbkf")

_I3 = np.eye(3)


@dataclass
class FilterParams:
    """Noise and behaviour parameters; defaults are physical guesses for the simulated OR, not fits.

    accel_noise  q_a, white-acceleration spectral density [m^2/s^3]: 0.05 lets a hand-guided or
                 robot-carried tool change speed by ~0.2 m/s within a second.
    bias_walk    q_b, bias random-walk density [m^2/s]: 1e-7 -> the OMC error drifts ~0.3 mm per
                 sqrt(s) as the target moves through differently calibrated parts of the room.
    global_std   OMC white noise per axis [m] (sub-millimetre jitter; the systematic part is b).
    local_std    OTS chain noise per axis [m] (Vega ~0.1 mm RMS plus calibration of the chain).
    init_*_std   prior standard deviations of p [m], v [m/s], b [m] at initialization.
    hop_gate     chi^2 threshold on the 3-dof NIS of the global rows (99.9 % quantile).
    """

    accel_noise: float = 0.05
    bias_walk: float = 1e-7
    global_std: float = 0.3e-3
    local_std: float = 0.15e-3
    init_pos_std: float = 5e-3
    init_vel_std: float = 0.1
    init_bias_std: float = 5e-3
    hop_gate: float = 16.266
    hop_to_bias: bool = True
    max_gap_s: float = 0.5
    shrink_blocks: tuple[str, ...] = ("p",)
    eq14_covariance: str = "posterior"   # 'posterior' (ours) | 'prior' (literal eq. 14, diverges)

    def validate(self) -> FilterParams:
        for name in ("accel_noise", "bias_walk", "init_pos_std", "init_vel_std", "init_bias_std"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"filter parameter {name} must be finite and >= 0, got {v!r}")
        for name in ("global_std", "local_std", "hop_gate", "max_gap_s"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"filter parameter {name} must be finite and > 0, got {v!r}")
        if not set(self.shrink_blocks) <= {"p", "v", "b"}:
            raise ValueError(f"shrink_blocks must be a subset of ('p', 'v', 'b'), got {self.shrink_blocks!r}")
        if self.eq14_covariance not in ("posterior", "prior"):
            raise ValueError(f"eq14_covariance must be 'posterior' or 'prior', got {self.eq14_covariance!r}")
        return self


# ---------------------------------------------------------------------------------------------
# The equations as plain functions, so tests can check each step on its own.

def transition(dt: float, has_bias: bool) -> np.ndarray:
    """F of eq. (9): constant velocity for p, v; b constant."""
    n = 9 if has_bias else 6
    F = np.eye(n)
    F[0:3, 3:6] = dt * _I3
    return F


def process_noise(dt: float, accel_noise: float, bias_walk: float, has_bias: bool) -> np.ndarray:
    """Q of eq. (10): white-acceleration CV model per axis plus a bias random walk."""
    n = 9 if has_bias else 6
    Q = np.zeros((n, n))
    qa = accel_noise
    Q[0:3, 0:3] = qa * dt**3 / 3 * _I3
    Q[0:3, 3:6] = Q[3:6, 0:3] = qa * dt**2 / 2 * _I3
    Q[3:6, 3:6] = qa * dt * _I3
    if has_bias:
        Q[6:9, 6:9] = bias_walk * dt * _I3
    return Q


def measurement_matrix(source: int, has_bias: bool, lag_s: float = 0.0) -> np.ndarray:
    """H of eq. (11) for one source; ``lag_s`` > 0 for a sample older than the filter time."""
    n = 9 if has_bias else 6
    H = np.zeros((3, n))
    H[:, 0:3] = _I3
    H[:, 3:6] = -lag_s * _I3
    if has_bias and source == SOURCE_GLOBAL:
        H[:, 6:9] = _I3
    return H


def biased_factors(x: np.ndarray, var: np.ndarray) -> np.ndarray:
    """m_i = x_i^2 / (var_i + x_i^2) of eq. (7); 1 where var_i = 0 (nothing to trade)."""
    x = np.asarray(x, dtype=float)
    var = np.asarray(var, dtype=float)
    x2 = x * x
    den = var + x2
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(den > 0, x2 / np.where(den > 0, den, 1.0), 1.0)
    return np.where(var <= 0, 1.0, m)


def kalman_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray):
    """Eq. (12)-(13): returns x'', P (Joseph form), G, innovation y, S."""
    y = z - H @ x
    S = H @ P @ H.T + R
    G = np.linalg.solve(S, H @ P).T   # P H^T S^-1, S symmetric
    x_new = x + G @ y
    IKH = np.eye(len(x)) - G @ H
    P_new = IKH @ P @ IKH.T + G @ R @ G.T
    return x_new, 0.5 * (P_new + P_new.T), G, y, S


# ---------------------------------------------------------------------------------------------

class FusionFilter(StepCompat):
    """The configurable filter; ``kind`` is one of :data:`FILTER_KINDS`. Implements :class:`~.api.Filter`.

    :meth:`predict` moves the state to a stamp (eq. 9-10); :meth:`update` fuses one
    :class:`~.api.Measurement` or a synchronised (global, local) pair in one stacked update (eq. 11-14).
    R of a measurement is the position block ``cov[:3, :3]`` of its covariance, or ``global_std**2 I`` /
    ``local_std**2 I`` when it has none. ``step(z_global, t_global, z_local, t_local)`` is predict + update.
    Stamps must be non-decreasing; the synchronizer guarantees it, a direct caller gets ValueError otherwise.

    Before the first measurement, and after a gap longer than ``max_gap_s``, :meth:`predict` only records the
    stamp and the next :meth:`update` (re-)initialises the state there (see the module docstring). A refused
    update (ValueError, LinAlgError) leaves the state as predicted; a non-finite result resets the filter.
    """

    def __init__(self, kind: str = "cbkf", params: FilterParams | None = None) -> None:
        if kind not in FILTER_KINDS:
            raise ValueError(f"filter kind '{kind}' is not one of {FILTER_KINDS}")
        self.kind = kind
        self.params = (params or FilterParams()).validate()
        self.has_bias = kind in ("ckf", "cbkf")
        self.biased = kind in ("bkf", "cbkf")
        self.n = 9 if self.has_bias else 6
        blocks = {"p": range(0, 3), "v": range(3, 6), "b": range(6, 9)}
        self._shrink_idx = np.array(
            sorted(i for blk in self.params.shrink_blocks for i in blocks[blk] if i < self.n), dtype=int)
        self.reset()

    def reset(self) -> None:
        self.x = np.zeros(self.n)
        self.P = np.eye(self.n)
        self.t_ns: int | None = None
        self._pending_ns: int | None = None   # stamp of a (re-)initialisation the next update makes

    def snapshot(self) -> tuple:
        """The whole filter state, for rewind-and-replay (arrival.py)."""
        return (self.x.copy(), self.P.copy(), self.t_ns, self._pending_ns)

    def restore(self, snap: tuple) -> None:
        """Back to a :meth:`snapshot` (copied again, so it can be restored more than once)."""
        self.x, self.P = snap[0].copy(), snap[1].copy()
        self.t_ns, self._pending_ns = snap[2], snap[3]

    @property
    def initialized(self) -> bool:
        return self.t_ns is not None

    @property
    def time_ns(self) -> int | None:
        """The stamp the next update is made at: the state's, or that of a pending (re-)initialisation."""
        return self._pending_ns if self._pending_ns is not None else self.t_ns

    @property
    def bias(self) -> np.ndarray:
        return self.x[6:9].copy() if self.has_bias else np.zeros(3)

    def _init_state(self, t_ns: int, z_global, z_local, keep_bias: bool, dt: float) -> Step:
        pr = self.params
        b = self.x[6:9].copy() if (self.has_bias and keep_bias) else np.zeros(3)
        Pbb = self.P[6:9, 6:9] + pr.bias_walk * dt * _I3 if (self.has_bias and keep_bias) else \
            pr.init_bias_std**2 * _I3
        p = np.asarray(z_local if z_local is not None else np.asarray(z_global) - b, dtype=float)
        self.x = np.zeros(self.n)
        self.x[0:3] = p
        self.P = np.zeros((self.n, self.n))
        self.P[0:3, 0:3] = pr.init_pos_std**2 * _I3
        self.P[3:6, 3:6] = pr.init_vel_std**2 * _I3
        if self.has_bias:
            self.x[6:9] = b
            self.P[6:9, 6:9] = Pbb
        self.t_ns = int(t_ns)
        self._pending_ns = None
        src = (SOURCE_GLOBAL if z_global is not None else 0) | (SOURCE_LOCAL if z_local is not None else 0)
        return Step(self.t_ns, p.copy(), np.zeros(3), self.bias, self.P.copy(), src, reset=True)

    def predict(self, t_ns: int) -> None:
        """Eq. (9)-(10): x' = F x, P' = F P F^T + Q with dt from the state's stamp to ``t_ns``."""
        t, dt = predict_interval(t_ns, self.t_ns, self._pending_ns, self.params.max_gap_s)
        if dt is None:
            self._pending_ns = t
            return
        pr = self.params
        F = transition(dt, self.has_bias)
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + process_noise(dt, pr.accel_noise, pr.bias_walk, self.has_bias)
        self.t_ns = t

    def update(self, *measurements: Measurement) -> Step:
        """Eq. (11)-(14) for one measurement or a (global, local) pair, at the filter's time (predicted to the
        newest stamp first if that is ahead); an older measurement gets its lag in H (module docstring)."""
        mg, ml = split_update(self.kind, measurements)
        t_new = max(m.t_ns for m in measurements)
        if self.time_ns is None or t_new > self.time_ns:
            self.predict(t_new)
        t = self.time_ns
        pr = self.params
        zg = None if mg is None else mg.p
        zl = None if ml is None else ml.p
        if self._pending_ns is not None:
            keep = self.t_ns is not None
            return self._init_state(t, zg, zl, keep_bias=keep, dt=(t - self.t_ns) * 1e-9 if keep else 0.0)
        x_pred, P_pred = self.x, self.P

        # measurement rows, eq. (11), global first; R from the measurement's covariance or the fixed noise
        Hs, zs, Rs = [], [], []
        for m, std in ((mg, pr.global_std), (ml, pr.local_std)):
            if m is None:
                continue
            lag = (t - m.t_ns) * 1e-9
            if lag > pr.max_gap_s:
                raise ValueError(f"measurement {lag:.3f} s older than the filter time (max_gap_s {pr.max_gap_s})")
            Hs.append(measurement_matrix(m.source, self.has_bias, lag))
            zs.append(m.p)
            Rs.append(std**2 * _I3 if m.cov is None else m.cov[0:3, 0:3])
        if len(Hs) == 1:
            H, z, R = Hs[0], zs[0], Rs[0]
        else:
            H, z = np.vstack(Hs), np.concatenate(zs)
            R = np.zeros((6, 6))
            R[0:3, 0:3], R[3:6, 3:6] = Rs

        y = z - H @ x_pred
        S = H @ P_pred @ H.T + R
        nis = float(y @ np.linalg.solve(S, y))
        nis_g = 0.0
        hop = False
        if zg is not None:
            yg, Sg = y[0:3], S[0:3, 0:3]
            nis_g = float(yg @ np.linalg.solve(Sg, yg))
            hop = nis_g > pr.hop_gate
            if hop and self.has_bias and pr.hop_to_bias:
                P_pred = P_pred.copy()
                P_pred[6:9, 6:9] += np.diag(yg * yg)

        # gain and update, eq. (12)-(13)
        x_upd, P_upd, _G, y, _S = kalman_update(x_pred, P_pred, z, H, R)

        # biased estimator, eq. (14) -- see the module docstring for the covariance decision
        m_diag = None
        if self.biased:
            m_diag = np.ones(self.n)
            idx = self._shrink_idx
            m_diag[idx] = biased_factors(x_upd[idx], np.diag(P_upd)[idx])
            x_upd = m_diag * x_upd
            P_base = P_upd if pr.eq14_covariance == "posterior" else P_pred
            P_upd = P_base * np.outer(m_diag, m_diag)

        if not (np.all(np.isfinite(x_upd)) and np.all(np.isfinite(P_upd))):
            self.reset()
            raise FloatingPointError("filter produced a non-finite state; it was reset")
        self.x, self.P, self.t_ns = x_upd, P_upd, t
        src = (SOURCE_GLOBAL if zg is not None else 0) | (SOURCE_LOCAL if zl is not None else 0)
        return Step(t, self.x[0:3].copy(), self.x[3:6].copy(), self.bias, self.P.copy(), src,
                    innovation=y[0:3].copy(), nis=nis, nis_global=nis_g, hop=hop, m=m_diag)


class PassThrough(StepCompat):
    """The ``omc`` "filter": the raw global measurement, for comparison (no state, no local data).

    Its position covariance is the measurement's ``cov[:3, :3]``, or ``global_std**2 I`` without one.
    """

    kind = "omc"

    def __init__(self, params: FilterParams | None = None) -> None:
        self.params = (params or FilterParams()).validate()
        self.t_ns: int | None = None

    def reset(self) -> None:
        self.t_ns = None

    def snapshot(self) -> int | None:
        """The whole state (the stamp of the newest global measurement), for rewind-and-replay."""
        return self.t_ns

    def restore(self, snap: int | None) -> None:
        self.t_ns = snap

    def predict(self, t_ns: int) -> None:
        """Nothing to predict: the output is the newest global measurement."""

    def update(self, *measurements: Measurement) -> Step | None:
        mg = next((m for m in measurements if m.source == SOURCE_GLOBAL), None)
        if mg is None:
            return None
        self.t_ns = mg.t_ns
        P = np.zeros((6, 6))
        P[0:3, 0:3] = np.eye(3) * self.params.global_std**2 if mg.cov is None else mg.cov[0:3, 0:3]
        return Step(self.t_ns, mg.p.copy(), np.zeros(3), np.zeros(3), P, SOURCE_GLOBAL)
