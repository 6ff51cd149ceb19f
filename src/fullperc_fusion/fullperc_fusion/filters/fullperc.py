"""``fullperc``, the filter the pipeline runs: the general form of :mod:`.fullperc_reference`, restructured for speed.

Issue 16 item 3 (``filter_step_us[fullperc]``). The model, its equations and every rule (hops, gaps, position-only
samples, the error-state reset) are those of :class:`.fullperc_reference.FullpercReference`, the reference; this
module changes how they are computed, never what: ``test_fullperc_fast.py`` runs both on long randomised streams
(gaps, hops, resets, local only / global only / pairs, lags, full 6x6 covariances, snapshot/restore) and fails when
they differ by more than 1e-12 (module docstring there). Registered as ``"fullperc"`` in :mod:`.registry`; its
parameters are :class:`.fullperc_params.FullpercParams`.

Why each change (the reference runs each step as well over 100 numpy operations on 21x21 arrays, 3x3 helpers and
single elements; at these sizes an operation's ~1-2 us overhead, not the arithmetic, is the cost):

* the nominal state is a list of 21 Python floats (rotation slots 9:12 always 0) and R a 9-tuple: the injection,
  the prediction of p and g and the SO(3) functions (Exp, Log, quaternion <-> matrix: :mod:`.so3_float`, the
  shared ``fullperc_common.so3`` specialised to floats, which its docstring shows to cost measurably less) are a
  few float operations each instead of one numpy call per 3-vector;
* predict is P = F P F^T + Q with F from a template cached by dt (only Exp(w dt) written into a copy) and Q cached
  by (dt, sys_var): two matmuls and an add instead of ~30 row/column operations and 33 scalar writes;
* the measurement matrix H comes from a per-layout template (global/local, with/without orientation, single or
  pair) with only the lag entries and the 3x3 block A written; U = P H^T is formed once and gives S = H U + R;
  one LAPACK ``dgesv`` (the LU solve of ``np.linalg.solve``, without its ~4 us wrapper) on [y | U^T] gives the
  NIS and the gain together; the hop tests' 3x3 NIS are Python floats (LDL^T);
* the covariance update is P - U S^-1 U^T, equal to the reference's Joseph form for the optimal gain (to
  rounding: the comparison holds at 1e-12), followed by the reference's reset G_r P G_r^T;
* arrays are never changed in place once stored, so :meth:`snapshot` is a tuple of references (rewind-and-replay
  in arrival.py takes one per item) and the :class:`Step` shares P instead of copying it;
* re-initialisation (first sample, gaps) is rare and is delegated to the reference itself.

Measured (``python bench/bench_filter.py``, one run, load 2.2-2.4 on 2 cores): 53.2 us per predict + update on the
cbkf line's position-only items (reference 141.8 us, CBKF's closed form 16.5 us), 59.3 us with orientations and
model covariances on every sample (reference 168.0 us). The floor of this form is its array work: the ~30 numpy
operations of one step alone (``fullperc_array_floor_us`` in the same benchmark) take about half of that, so the
issue's 20 us is out of reach for the joint 21-state form in numpy.

Why not two small filters (position per axis, orientation apart) as the paper's kinds (:mod:`.paper_kernel`): they are
exact only while the covariance has no entry between the position and orientation errors or between position
axes, and the pipeline's measurements always bring such entries: the local sample's covariance carries the
calibrated link's rotation error through the lever arm (position-rotation terms, and cross-axis position terms up
to ~20 % of the diagonal), and the OMC's isotropic covariance rotated into ``base`` has cross-axis entries of
~1e-16 relative from rounding (counted in the pipeline on bags/spec/P-B-G: all 3,339 OMC samples; 652 of the 675
local samples with position-rotation terms, the other 23 with cross-axis ones). A split that is exact would never
engage; one with a tolerance would not be the same filter.
"""

from __future__ import annotations

import math
from operator import add, mul

import numpy as np
from scipy.linalg.lapack import dgesv as _dgesv

from fullperc_fusion.filters.api import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    Measurement,
    Step,
    StepCompat,
    predict_interval,
    split_update,
)
from fullperc_fusion.filters.fullperc_reference import FullpercReference
from fullperc_fusion.filters.fullperc_state import (
    HOLD_OUT,
    POSE_FLAT,
    FullpercState,
    N,
    field_var,
    hop_run_step,
    hop_watched,
    noise_scale_step,
)
from fullperc_fusion.filters.motion import gaussian_log_lik, hop_mixture
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.filters.rot_noise_scale import pair_estimate, scale_decay, scale_step, scaled_cov
from fullperc_fusion.filters.so3_float import R9_IDENT, R9_to_quat, exp9, log9, mul9, mul9_t, quat_to_R9

__all__ = ["FullpercFilter", "N"]

_I21 = np.eye(N)
_F_PV = ([0, 1, 2], [3, 4, 5])
_F_TW = ([9, 10, 11], [12, 13, 14])
_F_GG = ([18, 19, 20], [18, 19, 20])
_F_BB = ([15, 16, 17], [15, 16, 17])
_F_TH = np.array([21 * r + c for r in (9, 10, 11) for c in (9, 10, 11)])   # F[theta, theta] in F.ravel()
_CACHE_MAX = 64     # entries per cache; cleared when full (a stream with jittering dt still reuses most keys)


def _nis3(S: list, y0: float, y1: float, y2: float) -> float:
    """y^T S^-1 y of a symmetric positive definite 3x3 S (nested list) through its LDL^T factors."""
    d0 = S[0][0]
    l10, l20 = S[1][0] / d0, S[2][0] / d0
    d1 = S[1][1] - l10 * S[1][0]
    l21 = (S[2][1] - l20 * S[1][0]) / d1
    d2 = S[2][2] - l20 * S[2][0] - l21 * l21 * d1
    e0 = y0
    e1 = y1 - l10 * e0
    e2 = y2 - l20 * e0 - l21 * e1
    return e0 * e0 / d0 + e1 * e1 / d1 + e2 * e2 / d2


def _solve(S: np.ndarray, y: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S^-1 [y | U^T] (k x 22), S's LU factors): LAPACK's dgesv (the LU solve of np.linalg.solve) without numpy's
    ~4 us wrapper; the factors' diagonal gives log |S|."""
    B = np.empty((len(y), N + 1))
    B[:, 0] = y
    B[:, 1:] = U.T
    lu, _, Z, info = _dgesv(S, B)
    if info != 0:
        raise np.linalg.LinAlgError("singular innovation covariance")
    return Z, lu


class FullpercFilter(StepCompat):
    """The ``fullperc`` filter (:class:`~.api.Filter`); the model is :mod:`.fullperc_reference`'s.

    State: ``_x`` 21 floats in the error-state layout of the reference (p v b | theta(=0) w beta | g), ``_R``
    the orientation (9-tuple), ``_P`` the 21x21 covariance, stamps and flags as the reference's ``FullpercState``.
    """

    kind = "fullperc"
    likelihood = False   # fill Step.log_lik (the reference always does; motion: auto's models ask for it)

    def __init__(self, params: FilterParams | None = None) -> None:
        self._ref = FullpercReference(params)   # re-initialisation and the non-finite reset are delegated to it
        self.params = self._ref.params
        self.hop_counts = self._ref.hop_counts    # one dict: counts made by either are counted once
        self.hop_allowed = True   # False: a flagged position hop stays out of the bias (fullperc_imm: a minority model)
        self._fcache: dict = {}
        self._qcache: dict = {}
        self._hcache: dict = {}
        pr = self.params
        self._fixed = {(SOURCE_GLOBAL, True): np.diag([pr.global_std**2] * 3 + [pr.rot_global_std**2] * 3),
                       (SOURCE_GLOBAL, False): np.diag([pr.global_std**2] * 3),
                       (SOURCE_LOCAL, True): np.diag([pr.local_std**2] * 3 + [pr.rot_local_std**2] * 3),
                       (SOURCE_LOCAL, False): np.diag([pr.local_std**2] * 3)}
        self.reset()

    # ---- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        self._ref.reset()
        self._load(self._ref.s)

    def _load(self, s: FullpercState) -> None:
        """Take the state of a reference ``FullpercState`` (after a re-initialisation or a reset)."""
        self._x = s.p.tolist() + s.v.tolist() + s.b.tolist() + [0.0, 0.0, 0.0] + s.w.tolist() + s.beta.tolist() \
            + s.g.tolist()
        self._R = tuple(s.R.ravel().tolist())
        self._P = s.P.copy()
        self._t, self._pend, self._has_R, self._sys_var = s.t_ns, s.pending_ns, s.has_R, s.sys_var
        self._lam, self._tg, self._frame = s.noise_scale, s.t_global_ns, s.frame
        self._anchor = None if s.anchor is None else s.anchor.tolist()
        self._tl, self._dmax = s.t_local_ns, s.rot_dmax
        self._ra = None if s.rot_anchor is None else s.rot_anchor.tolist()
        self._mu, self._tmu, self._hrun = s.rot_scale, s.t_rot_scale_ns, s.hop_run

    @property
    def state(self) -> FullpercState:
        """A copy of the state in the reference's form (``FullpercReference.s``), for tests and diagnostics."""
        x = self._x
        return FullpercState(np.array(x[0:3]), np.array(x[3:6]), np.array(x[6:9]), np.array(self._R).reshape(3, 3),
                      np.array(x[12:15]), np.array(x[15:18]), self._P.copy(), self._t, self._pend, self._has_R,
                      np.array(x[18:21]), self._sys_var, self._lam, self._tg, self._frame,
                      None if self._anchor is None else np.array(self._anchor), self._tl,
                      None if self._ra is None else np.array(self._ra), self._dmax, self._mu, self._tmu, self._hrun)

    def express_in(self, T_frame: np.ndarray, local: bool = True) -> np.ndarray | None:
        """:meth:`FullpercReference.express_in`; a change (rare: once per link change) is delegated to the
        reference, the same frame object costs one identity test (the pipeline calls this before every item)."""
        if local and self._t is not None:
            self._anchor = self._x[0:3]   # a new list: nothing stored is changed in place
        if T_frame is self._frame or (self._frame is None and not local):
            return None
        self._ref.s = self.state
        M = self._ref.express_in(T_frame, local)
        self._load(self._ref.s)
        return M

    def snapshot(self) -> object:
        """The whole filter state, for :meth:`restore`: references only (nothing stored is changed in place)."""
        return ("fullperc", self._x, self._R, self._P, self._t, self._pend, self._has_R, self._sys_var, self._lam,
                self._tg, self._frame, self._anchor, self._tl, self._ra, self._dmax, self._mu, self._tmu, self._hrun)

    def restore(self, obj: object) -> None:
        """Back to a :meth:`snapshot` (it stays usable)."""
        if not (isinstance(obj, tuple) and len(obj) == 18 and obj[0] == "fullperc"):
            raise TypeError(f"not a fullperc snapshot: {type(obj).__name__}")
        (_, self._x, self._R, self._P, self._t, self._pend, self._has_R, self._sys_var, self._lam, self._tg,
         self._frame, self._anchor, self._tl, self._ra, self._dmax, self._mu, self._tmu, self._hrun) = obj

    @property
    def time_ns(self) -> int | None:
        return self._pend if self._pend is not None else self._t

    @property
    def t_ns(self) -> int | None:
        return self._t

    @property
    def bias(self) -> np.ndarray:
        """The whole position bias of the global source, b + g."""
        x = self._x
        return np.array([x[6] + x[18], x[7] + x[19], x[8] + x[20]])

    @property
    def rot_bias(self) -> np.ndarray:
        return np.array(self._x[15:18])

    # ---- predict --------------------------------------------------------------------------------
    def _transition(self, dt: float, w: tuple) -> tuple:
        """(Exp(w dt), F, phi, phi_beta) of one prediction: F's dt, phi and phi_beta entries from a template cached by
        dt, Exp(w dt) written into a copy (w changes with every orientation update); the template itself when w = 0."""
        hit = self._fcache.get(dt)
        if hit is None:
            if len(self._fcache) >= _CACHE_MAX:
                self._fcache.clear()
            phi = math.exp(-dt / self.params.sys_time)
            phb = self.params.rot_decay(dt)[0]
            F0 = np.eye(N)
            F0[_F_PV] = dt
            F0[_F_TW] = dt
            F0[_F_GG] = phi
            F0[_F_BB] = phb
            hit = self._fcache[dt] = (F0, phi, phb)
        F0, phi, phb = hit
        if w[0] == 0.0 and w[1] == 0.0 and w[2] == 0.0:
            return R9_IDENT, F0, phi, phb
        Rw = exp9(w[0] * dt, w[1] * dt, w[2] * dt)
        F = F0.copy()
        F.put(_F_TH, Rw)
        return Rw, F, phi, phb

    def _noise(self, dt: float, sys_var: float) -> np.ndarray:
        """Q of one prediction (module docstring of the reference), cached by (dt, sys_var)."""
        key = (dt, sys_var)
        Q = self._qcache.get(key)
        if Q is None:
            if len(self._qcache) >= _CACHE_MAX:
                self._qcache.clear()
            pr = self.params
            phi = math.exp(-dt / pr.sys_time)
            qbe = pr.rot_decay(dt)[1]
            Q = np.zeros((N, N))
            for (i, j), q in (((0, 3), pr.accel_noise), ((9, 12), pr.ang_accel_noise)):
                for k in range(3):
                    Q[i + k, i + k] = q * dt**3 / 3
                    Q[i + k, j + k] = Q[j + k, i + k] = q * dt**2 / 2
                    Q[j + k, j + k] = q * dt
            for k in range(3):
                Q[6 + k, 6 + k] = pr.bias_walk * dt
                Q[15 + k, 15 + k] = qbe
                Q[18 + k, 18 + k] = sys_var * (1.0 - phi * phi)
            self._qcache[key] = Q
        return Q

    def predict(self, t_ns: int) -> None:
        """Move the state to ``t_ns`` (the reference's predict)."""
        t, dt = predict_interval(t_ns, self._t, self._pend, self.params.max_gap_s)
        if dt is None:
            self._pend = t
            return
        if dt == 0.0:
            return
        x = self._x
        Rw, F, phi, phb = self._transition(dt, (x[12], x[13], x[14]))
        x = x[:]
        x[0], x[1], x[2] = x[0] + x[3] * dt, x[1] + x[4] * dt, x[2] + x[5] * dt
        x[18], x[19], x[20] = phi * x[18], phi * x[19], phi * x[20]
        if phb != 1.0:
            x[15], x[16], x[17] = phb * x[15], phb * x[16], phb * x[17]
        self._x = x
        self._R = mul9(Rw, self._R)
        Q = self._qcache.get((dt, self._sys_var))
        P = F @ self._P @ F.T + (Q if Q is not None else self._noise(dt, self._sys_var))
        ra, pr = self._ra, self.params
        if ra is not None and (t - self._tl) * 1e-9 > pr.local_lost_s:
            d = math.dist(x[0:3], ra)   # beta's, b's and mu's spatial decay (the reference's _spatial_decay)
            if d > self._dmax:
                self._mu = scale_decay(self._mu, d - self._dmax, pr.rot_noise_length)
                if pr.rot_bias_length > 0.0:
                    f = math.exp(-(d - self._dmax) / pr.rot_bias_length)
                    x[15], x[16], x[17] = f * x[15], f * x[16], f * x[17]
                    P[15:18, :] *= f
                    P[:, 15:18] *= f
                    ex = pr.rot_sys_std**2 * (1.0 - f * f)
                    P[15, 15] += ex
                    P[16, 16] += ex
                    P[17, 17] += ex
                if pr.bias_length > 0.0:   # b's (the reference's, after beta's)
                    f = math.exp(-(d - self._dmax) / pr.bias_length)
                    x[6], x[7], x[8] = f * x[6], f * x[7], f * x[8]
                    P[6:9, :] *= f
                    P[:, 6:9] *= f
                    ex = pr.bias_field_std**2 * (1.0 - f * f)
                    P[6, 6] += ex
                    P[7, 7] += ex
                    P[8, 8] += ex
                self._dmax = d
        self._P = 0.5 * (P + P.T)
        self._t = t

    # ---- update ---------------------------------------------------------------------------------
    def _template(self, sig: tuple) -> tuple:
        """(H with its constant entries, per measurement the flat indices of its -lag entries and of its A block)
        of one row layout (global / local, with / without orientation)."""
        hit = self._hcache.get(sig)
        if hit is None:
            blocks, k = [], 0
            for glob, rot in sig:
                blocks.append((k, glob, rot))
                k += 6 if rot else 3
            H = np.zeros((k, N))
            lag_idx, a_idx = [], []
            for o, glob, rot in blocks:
                for i in range(3):
                    H[o + i, i] = 1.0
                    if glob:
                        H[o + i, 6 + i] = H[o + i, 18 + i] = 1.0
                        if rot:
                            H[o + 3 + i, 15 + i] = 1.0
                rows = [o, o + 1, o + 2] + ([o + 3, o + 4, o + 5] if rot else [])
                cols = [3, 4, 5] + ([12, 13, 14] if rot else [])
                lag_idx.append(np.array([N * r + c for r, c in zip(rows, cols, strict=True)]))
                a_idx.append(np.array([N * (o + 3 + r) + 9 + c for r in range(3) for c in range(3)]))
            hit = self._hcache[sig] = (H, lag_idx, a_idx)
        return hit

    def update(self, *measurements: Measurement) -> Step:
        """Fuse one measurement or a (global, local) pair (the reference's update; module docstring)."""
        mg, ml = split_update(self.kind, measurements)
        t_new = max(m.t_ns for m in measurements)
        now = self._pend if self._pend is not None else self._t
        if now is None or t_new > now:
            self.predict(t_new)
        t = self._pend if self._pend is not None else self._t
        if self._pend is not None:
            return self._reinit(t, mg, ml)
        x = self._x
        if not self._has_R:   # first sample with an orientation after a position-only start: take it as is
            m = ml if ml is not None and ml.q is not None else mg if mg is not None and mg.q is not None else None
            if m is not None:
                Rq = quat_to_R9(m.q)
                self._R = Rq if m is ml else mul9(exp9(-x[15], -x[16], -x[17]), Rq)
                self._has_R = True
        pr = self.params
        ms = [m for m in (mg, ml) if m is not None]
        H, lag_idx, offs = self._template(tuple((m.source == SOURCE_GLOBAL, m.q is not None) for m in ms))
        H = H.copy()
        y: list[float] = []
        Rblocks = []
        Rq_g = Rq_l = Eb = None   # the samples' rotations and Exp(beta), reused by the rotation noise scale
        for m, lag_flat, a_flat in zip(ms, lag_idx, offs, strict=True):
            lag = (t - m.t_ns) * 1e-9
            if lag > pr.max_gap_s:
                raise ValueError(f"measurement {lag:.3f} s older than the filter time (max_gap_s {pr.max_gap_s})")
            glob = m.source == SOURCE_GLOBAL
            rot = m.q is not None
            H.put(lag_flat, -lag)
            z0, z1, z2 = m.p.tolist()
            if glob:   # z - (p - lag v + b + g), in the reference's order of operations
                y += [z0 - (x[0] - lag * x[3] + x[6] + x[18]), z1 - (x[1] - lag * x[4] + x[7] + x[19]),
                      z2 - (x[2] - lag * x[5] + x[8] + x[20])]
            else:
                y += [z0 - (x[0] - lag * x[3]), z1 - (x[1] - lag * x[4]), z2 - (x[2] - lag * x[5])]
            if rot:
                Rq = quat_to_R9(m.q)
                A = exp9(-lag * x[12], -lag * x[13], -lag * x[14]) if lag > 0 else R9_IDENT
                if glob:
                    Rq_g, Eb = Rq, exp9(x[15], x[16], x[17])
                    A = mul9(Eb, A)
                else:
                    Rq_l = Rq
                H.put(a_flat, A)
                y += log9(mul9_t(Rq, self._R if A is R9_IDENT else mul9(A, self._R)))
            c = m.cov
            Rblocks.append(self._fixed[(m.source, rot)] if c is None else c if rot else c[0:3, 0:3])
        mu = None
        if mg is not None and mg.q is not None and pr.rot_noise_adapt_time > 0.0:   # mu R_rot (rot_noise_scale)
            mu = self._rot_scale(mg, ml, Rblocks, Rq_g, Rq_l, Eb)
            if mu[0] != 1.0:
                Rblocks[0] = scaled_cov(Rblocks[0], mu[0])
        if len(Rblocks) == 1:
            Rm = Rblocks[0]
        else:
            k0 = len(Rblocks[0])
            Rm = np.zeros((len(y), len(y)))
            Rm[:k0, :k0] = Rblocks[0]
            Rm[k0:, k0:] = Rblocks[1]
        if mg is not None and self._lam != 1.0:   # lambda R_p of the global sample (the reference's rule)
            Rm = Rm.copy()
            Rm[0:3, 0:3] *= self._lam
        if mg is not None:
            sv = mg.extras.get("sys_var")
            self._sys_var = float(sv) if sv is not None and math.isfinite(sv) and sv > 0 else pr.sys_std**2
        P = self._P
        U = P @ H.T
        S = H @ U + Rm
        yv = np.array(y)
        Z, lu = _solve(S, yv, U)
        nis = sum(map(mul, y, Z[:, 0].tolist()))
        log_lik = gaussian_log_lik(nis, float(np.log(np.abs(lu.diagonal())).sum()), len(y)) if self.likelihood else 0.0
        nis_g, hop, held = 0.0, False, False
        if mg is not None:
            Sl = S[0:6, 0:6].tolist() if len(y) >= 6 else S.tolist()
            nis_g = _nis3(Sl, y[0], y[1], y[2])
            hop_p = nis_g > pr.hop_gate
            hop_r = mg.q is not None and _nis3([r[3:6] for r in Sl[3:6]], y[3], y[4], y[5]) > pr.hop_gate
            hop = hop_p or hop_r
            lam_next = noise_scale_step(self._lam, self._tg, mg.t_ns, nis_g, pr)
            self.hop_counts["position"] += hop_p
            self.hop_counts["rotation"] += hop_r
            confirmed, hop_run = hop_run_step(self._hrun, hop_p, y[0], y[1], y[2], pr)
            if hop_p and pr.hop_to_bias and self.hop_allowed and hop_watched(t, self._tl, ml is not None, pr):
                Ph = P.copy()
                k = 18 if pr.hop_into == "g" else 6     # g or b
                Ph[k, k] += y[0] * y[0]
                Ph[k + 1, k + 1] += y[1] * y[1]
                Ph[k + 2, k + 2] += y[2] * y[2]
                Uh = Ph @ H.T
                Zh, luh = _solve(H @ Uh + Rm, yv, Uh)
                if self.likelihood:   # the reference's hop mixture of the likelihood (motion.hop_mixture)
                    hop_ll = gaussian_log_lik(sum(map(mul, y, Zh[:, 0].tolist())),
                                              float(np.log(np.abs(luh.diagonal())).sum()), len(y))
                    log_lik = hop_mixture(log_lik, hop_ll)
                if confirmed:   # into the bias
                    P, U, Z = Ph, Uh, Zh
                else:           # not (yet) a step: its position held out
                    Rm = Rm.copy()
                    Rm[0:3, 0:3] *= HOLD_OUT
                    held = True
                    Z, lu = _solve(H @ U + Rm, yv, U)
        Gt = Z[:, 1:]                      # K^T = S^-1 U^T
        if held:   # its position moves nothing
            yv[0:3] = 0.0
        dx = (yv @ Gt).tolist()
        d0, d1, d2 = dx[9], dx[10], dx[11]
        P = P - U @ Gt                     # = the reference's Joseph form for this (optimal) gain, to rounding
        # the error-state reset P = G_r P G_r^T, G_r = I - [dtheta/2]x on the theta rows and columns
        Gr = _I21.copy()
        Gr.put(_F_TH, (1.0, 0.5 * d2, -0.5 * d1, -0.5 * d2, 1.0, 0.5 * d0, 0.5 * d1, -0.5 * d0, 1.0))
        P = Gr @ P @ Gr.T
        P = 0.5 * (P + P.T)
        xn = list(map(add, x, dx))
        xn[9] = xn[10] = xn[11] = 0.0
        Rn = mul9(exp9(d0, d1, d2), self._R)
        if not (math.isfinite(float(P.sum())) and math.isfinite(sum(xn[0:3])) and math.isfinite(sum(Rn))) and not (
                np.all(np.isfinite(P)) and all(math.isfinite(v) for v in xn[0:3] + list(Rn))):
            self.reset()
            raise FloatingPointError("filter produced a non-finite state; it was reset")
        self._x, self._R, self._P, self._t = xn, Rn, P, t
        if mg is not None:
            self._lam, self._tg, self._hrun = lam_next, mg.t_ns, hop_run
        if mu is not None:
            self._mu, self._tmu = mu[1:]
        if ml is not None:   # where the local source last saw the tool (beta's and b's spatial decay)
            self._tl, self._ra, self._dmax = ml.t_ns, xn[0:3], 0.0
        return self._step(t, mg, ml, innovation=np.array(y[0:3]), nis=nis, nis_global=nis_g, hop=hop,
                          log_lik=log_lik)

    def _rot_scale(self, mg: Measurement, ml: Measurement | None, Rblocks: list, Rq_g: tuple, Rq_l: tuple | None,
                   Eb: tuple) -> tuple:
        """The reference's ``_rot_scale`` (mu for this update, then mu and the pair clock after it); ``Rq_g``,
        ``Rq_l``: the samples' rotations, ``Eb`` = Exp(beta), as the update computed them."""
        x, pr = self._x, self.params
        mu, t_mu = self._mu, self._tmu
        if ml is None or ml.q is None:
            return mu, mu, t_mu
        dl = (mg.t_ns - ml.t_ns) * 1e-9   # the local sample at the global's stamp
        Rl = Rq_l if dl == 0.0 else mul9(exp9(dl * x[12], dl * x[13], dl * x[14]), Rq_l)
        d = log9(mul9_t(Rq_g, mul9(Eb, Rl)))
        Rg, Rl_, P = Rblocks[0], Rblocks[1], self._P
        est = pair_estimate(d, Rl_[3, 3] + Rl_[4, 4] + Rl_[5, 5], P[15, 15] + P[16, 16] + P[17, 17],
                            Rg[3, 3] + Rg[4, 4] + Rg[5, 5])
        return mu, scale_step(mu, t_mu, mg.t_ns, est, pr.rot_noise_adapt_time, pr.rot_noise_adapt_min,
                              pr.rot_noise_adapt_max), mg.t_ns

    def _reinit(self, t: int, mg: Measurement | None, ml: Measurement | None) -> Step:
        """A pending (re-)initialisation: the reference's rule, run by the reference on this state."""
        r = self._ref
        r.s = self.state
        r._init_state(t, mg, ml)
        self._load(r.s)
        return self._step(t, mg, ml, reset=True)

    def _step(self, t: int, mg, ml, **kw) -> Step:
        x, P = self._x, self._P
        fv = field_var(t, self._tl, x[0:3], self._ra, self.params, x[6:9])   # the output's only (fullperc_state)
        if fv > 0.0:
            P = P.copy()
            P[0, 0] += fv
            P[1, 1] += fv
            P[2, 2] += fv
        src = (SOURCE_GLOBAL if mg is not None else 0) | (SOURCE_LOCAL if ml is not None else 0)
        has_R = self._has_R
        return Step(t, np.array(x[0:3]), np.array(x[3:6]), np.array([x[6] + x[18], x[7] + x[19], x[8] + x[20]]),
                    P, src, q=R9_to_quat(self._R) if has_R else None,
                    pose_cov=P.ravel()[POSE_FLAT].reshape(6, 6) if has_R else None, reset=kw.pop("reset", False), **kw)
