"""``fullperc`` in its general form, the reference: CBKF's compensated position model with per-measurement
covariance, plus orientation on SO(3).

This is the model's definition, written as the textbook 21-state error-state filter in numpy matrix form, and the
tests' reference; the pipeline runs :class:`.fullperc.FullpercFilter` (``"fullperc"`` in :mod:`.registry`), the same
filter restructured for speed, which ``test_fullperc_fast.py`` holds to this one at 1e-12. Parameters:
:class:`.fullperc_params.FullpercParams`. Its registry entry declares ``models`` (:class:`~.api.Capabilities`): the
pipeline gives it :mod:`.measurement_models`' covariances (the paper's four keep their fixed noise).

Nominal state (``base``, SI): position p, velocity v, the global source's position bias in two parts -- b, CBKF's
compensation term (random walk: the part that stays, e.g. the error of the calibrated global link), and g, a
Gauss-Markov part (the OMC's systematic error that decorrelates over ~``sys_time`` of motion: distortion along
the path, camera-set changes) --, orientation R (tool -> base), angular velocity w (base axes) and the global
source's orientation bias beta (a rotation vector: the OMC reports R_omc = Exp(beta) R). Error state, 21 dims,
rotation errors on the left about the base axes (the :mod:`.api` convention, R_true = Exp(dtheta) R):

    dx = [dp dv db | dtheta dw dbeta | dg]      (indices 0:3 3:6 6:9 | 9:12 12:15 15:18 | 18:21)

Why two bias parts (raw OMC error vs the Diana truth, :mod:`measurement_models`): the rms increment of the OMC's
error over a lag grows from the white level towards a plateau (spec 0.07 -> 0.18 -> 0.30 mm at 8 ms / 1 s / 10 s;
paper 0.16 -> 1.84 -> 3.19 mm; Gauss-Markov fit: tau ~3 s): a random walk (CBKF's b alone) keeps a learnt
compensation forever, so after the local source is gone the output carries a compensation that no longer holds;
a Gauss-Markov process forgets it at the rate the sensor's error does, and the mean offset (per bag ~0.1 mm spec,
~1.5 mm paper) stays in b.

* predict over dt (constant velocity, constant angular velocity):
  p += v dt, R = Exp(w dt) R, g *= phi, phi = exp(-dt / sys_time), beta *= phi_b, phi_b = exp(-dt / rot_sys_time)
  (1 when rot_sys_time is 0);
  and, once the local source has lost the tool (newest local sample older than ``local_lost_s``), beta's spatial
  decay: d = |p - a_r| (a_r: p when that sample was fused), d_max the largest d since; a prediction taking d beyond
  d_max scales beta and its rows and columns of P by f = exp(-(d - d_max) / rot_bias_length) and adds
  rot_sys_std^2 (1 - f^2) to its variance: beta = exp(-d_max / L) beta(a_r), Gauss-Markov in that distance;
  the same step, with f_b = exp(-(d - d_max) / bias_length) (``bias_length`` > 0), takes b to f_b b, its rows and
  columns of P times f_b and bias_field_std^2 (1 - f_b^2) onto its variance: b(d') = exp(-(d' - d) / L_b) b(d) + w,
  Var(w) = s_f^2 (1 - exp(-2 (d' - d) / L_b)), first-order Gauss-Markov in distance, so far from a_r b is back at
  its prior (mean 0, std s_f) and the output at the raw OMC;
  F = I with F_pv = dt I, F_thth = Exp(w dt), F_thw = dt I, F_gg = phi I, F_bebe = phi_b I;
  Q = q_a [[dt^3/3, dt^2/2], [dt^2/2, dt]] on (p, v), q_b dt on b, q_alpha the same form on (theta, w),
  q_beta dt + s_b^2 (1 - phi_b^2) on beta (a random walk plus a Gauss-Markov part of stationary variance
  s_b^2 = rot_sys_std^2: the OMC's slow rotation error decorrelates along the path; ``FullpercParams``),
  s^2 (1 - phi^2) on g (white acceleration / angular acceleration, random-walk biases, a
  first-order Gauss-Markov g of stationary variance s^2: the ``sys_var`` of the newest global sample,
  :func:`measurement_models.omc_systematic_var`, margin- and fit-error-adaptive; ``sys_std^2`` without one).
* a global sample (lag s = filter time - sample stamp, as the paper filters: exact under constant velocity):
  z_p = p - s v + b + g,  R_z = Exp(beta) Exp(-s w) R;
  residual r_theta = Log(R_z R_pred^T), H rows p: [I, -s I, I, 0, 0, 0], theta: [0, 0, 0, A, -s I, I] with
  A = Exp(beta) Exp(-s w) (the left perturbation carried through the prediction); a local sample the same
  without b and beta.
* R of the update: the measurement's full 6x6 ``cov`` (the models' or a device's; position-rotation correlation
  of the lever arm included); without ``cov`` the fixed noise ``global_std`` / ``local_std`` and
  ``rot_global_std`` / ``rot_local_std``. A sample without ``q`` updates the position only.
* the global source's white position noise, scaled by what its innovations show (``noise_adapt_time`` tau > 0):
  its R_p is used as lambda R_p, lambda >= 1 an exponentially weighted mean of the global position NIS per degree
  of freedom, each taken with the lambda in force,
      lambda <- clip((1 - a) lambda + a lambda NIS_g / 3, 1, ``noise_adapt_max``),  a = 1 - exp(-dt_g / tau),
  dt_g the time since the previous global sample (after the update; the NIS is the hop test's). Why: where few
  cameras see the body, frames alternate between camera sets and the OMC's sample-to-sample scatter is up to
  ~2.5 times what the model gives (``spec`` seed 7 P-G-B-P, 16.8-21 s: 0.16 mm in x against the model's 0.065 mm);
  fused at face value those samples swing the velocity by tens of mm/s per update and cross the hop gate without
  being hops (docs/fullperc_filter.md "Where a hop goes"). Scaling R only up, over ~tau of samples, keeps the model
  where it holds (lambda = 1) and trusts the OMC less where its innovations say it is noisier (covariance matching,
  Mehra 1972).
* the global source's rotation noise, scaled by mu (``rot_noise_adapt_time`` > 0): R_rot used as mu R_rot, mu learnt
  from the disagreement of (global, local) pairs, back to 1 over the distance beta decays over (:mod:`rot_noise_scale`).
* hops: NIS of the global position rows above ``hop_gate`` on ``hop_confirm`` global samples in a row, each
  innovation in the direction of the one before (:func:`.fullperc_state.hop_run_step`) -> the variance of b
  (``hop_into: b``, CBKF's rule, :mod:`.paper_family`) or g (``hop_into: g``, forgotten over ``sys_time``) is raised
  by y_p^2 per axis before the gain (a step of the global source goes into its bias), by default once a local
  source has seen the target (``hop_needs_local``, :func:`.fullperc_state.hop_watched`). Unconfirmed crossings are
  held out (R_p x ``HOLD_OUT``): noise beyond the model crosses in single frames pointing anywhere
  (docs/fullperc_filter.md "Where a hop goes"). A rotation hop is flagged, not put into beta (``omc_covariance``).
* the update's log-likelihood log N(y; 0, S) (``Step.log_lik``), S before a hop raises it; at a crossing (held out or
  not) the mixture (1 - pi) N(y; 0, S) + pi N(y; 0, S_hop), S_hop raised (:func:`.motion.hop_mixture`): how well
  this model predicted the sample -- the weight of a motion model in ``motion: auto`` (:mod:`.fullperc_imm`).
* error-state update (Joseph form), injection p += dp ..., R = Exp(dtheta) R, and the reset of the error state:
  P = G P G^T with G_thth = I - [dtheta/2]x (the first-order reset Jacobian of the multiplicative update).
* why the spatial decay: the OMC's rotation error is a field over the room (its structure function over the
  distance between samples, ``sensor_stats.structure_over_distance``: L = 56.5 mm on the ``paper`` bags); once the
  local source has lost the tool, beta, the OMC's error where the Vega saw it, is not the error here
  (docs/fullperc_filter.md "The orientation bias after the Vega lost the tool"); while it sees the tool, beta is
  observed. The position error is such a field too (issue 41): b, learnt in the Vega's volume and applied metres
  away, left the output worse there than the raw OMC. Its length and std come from the raw (OMC - local chain)
  differences' semivariogram over distance (``fullperc_eval`` ``bias_variogram``), not from the truth. With
  ``bias_length`` 0 (b kept as learnt) the output's position covariance gets the field's change since a_r instead,
  2 s^2 (1 - exp(-d / L_f)) per axis, s^2 = max(s_f^2, |b|^2 / 3) (:func:`.fullperc_state.field_var`). d is the
  distance from a_r, not the path length: the error is a function of where the tool is, so coming back towards a_r
  forgets nothing more, and d_max keeps the decay monotone (no variance given back).
* gaps longer than ``max_gap_s`` re-initialise p, v, R, w from the next sample; b and beta (and their variances)
  are kept (propagated over the gap: b's walk, beta's decay and walk, g's decay).
* (re-)initialisation: p from the local sample if there is one, else p = z - b - g from the global one. Then p's
  error is minus the errors of b and g plus the prior's own: P_pp = init_pos_std^2 I + P_bb + P_gg, P_pb = -P_bb,
  P_pg = -P_gg, so z's sum p + b + g has the prior's variance alone and the global source by itself cannot move b
  or g (cov(b, p + b + g) = 0). Why: with p independent of b, each model's first global samples split their
  innovation (velocity not yet known) between p and b by the priors -- about half into b for a small velocity prior
  --, and b, which no source observes before the local one, kept that (``spec``'s instrument, seed 0: 0.15-0.2 mm
  off the raw OMC until the Vega first saw it, 1.3x the OMC's error; ``test_fullperc_filter.py``).

CBKF's biased estimator M is left out: on the position block it is a shrinkage towards the origin of ``base``
with m = 1 - O(1e-7) (see :mod:`.paper_family`), i.e. micrometres, and on the other blocks it breaks the filter.
Output: :class:`~.api.Step` with ``q`` (x y z w) and ``pose_cov`` (6x6, [p, theta], base)."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import block_diag

from fullperc_common.so3 import R_to_quat, quat_to_R, skew, so3_exp, so3_log
from fullperc_fusion.filters.api import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    Measurement,
    Step,
    StepCompat,
    predict_interval,
    split_update,
)
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_state import (
    B_,
    BE,
    G_,
    HOLD_OUT,
    P_,
    TH,
    V_,
    W_,
    FullpercState,
    N,
    copy_state,
    field_var,
    hop_run_step,
    hop_watched,
    noise_scale_step,
)
from fullperc_fusion.filters.motion import gaussian_log_lik, hop_mixture
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.filters.rot_noise_scale import pair_estimate, scale_decay, scale_step, scaled_cov

__all__ = ["N", "FullpercReference", "noise_scale_step"]

_I3, _IN = np.eye(3), np.eye(N)


class FullpercReference(StepCompat):
    """The ``fullperc`` filter in general form; implements :class:`~.api.Filter` (module docstring)."""

    kind = "fullperc"

    def __init__(self, params: FilterParams | None = None) -> None:
        self.params = FullpercParams.from_params(params).validate()
        self.hop_counts = {"position": 0, "rotation": 0}   # hops flagged so far, per kind (diagnostics)
        self.reset()

    # ---- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        pr = self.params
        self.s = FullpercState(np.zeros(3), np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3),
                        self._prior(pr.init_bias_std**2 * _I3, pr.init_rot_bias_std**2 * _I3, pr.sys_std**2 * _I3),
                        None, None, False, np.zeros(3), pr.sys_std**2)

    def _prior(self, Pbb: np.ndarray, Pbeta: np.ndarray, Pgg: np.ndarray) -> np.ndarray:
        pr = self.params
        P = np.zeros((N, N))
        P[P_, P_] = pr.init_pos_std**2 * _I3
        P[V_, V_] = pr.init_vel_std**2 * _I3
        P[B_, B_] = Pbb
        P[TH, TH] = pr.init_rot_std**2 * _I3
        P[W_, W_] = pr.init_angvel_std**2 * _I3
        P[BE, BE] = Pbeta
        P[G_, G_] = Pgg
        return P

    def snapshot(self) -> object:
        """A copy of the whole filter state, for :meth:`restore` (rewind and replay)."""
        return copy_state(self.s)

    def restore(self, obj: object) -> None:
        """Put back a state taken by :meth:`snapshot` (the snapshot stays usable)."""
        if not isinstance(obj, FullpercState):
            raise TypeError(f"not a fullperc snapshot: {type(obj).__name__}")
        self.s = copy_state(obj)

    @property
    def time_ns(self) -> int | None:
        s = self.s
        return s.pending_ns if s.pending_ns is not None else s.t_ns

    @property
    def t_ns(self) -> int | None:
        return self.s.t_ns

    @property
    def bias(self) -> np.ndarray:
        """The whole position bias of the global source, b + g."""
        return self.s.b + self.s.g

    @property
    def rot_bias(self) -> np.ndarray:
        return self.s.beta.copy()

    def express_in(self, T_frame: np.ndarray, local: bool = True) -> np.ndarray | None:
        """The item about to be fused comes in the frame ``T_frame`` (4x4; the caller's name for it: the pipeline
        passes the static link T_base_ots its local samples are mapped through); ``local``: the item carries a
        sample of that frame. Returns the move M applied to the estimate (None: none).

        The estimate is tied to a frame once a local sample in it is fused (before that, the global source and
        the prior on b alone place it): a call with ``local`` records the frame and the anchor a = p, where the
        global bias b was last learnt against that frame. When a later frame differs from the recorded one (a
        calibrated link replaced the average that bridged until it was done, a re-calibration), the estimate is
        moved with the frame and the new one recorded: M = T_new T_old^-1 maps a point of the old frame into the
        new one, d = M a - a, and

            p' = p + d,  v' = R_M v,  R' = R_M R,  w' = R_M w,
            b' = b - d,  Exp(beta') = Exp(beta) R_M^T,     g, P unchanged,

        which keeps what the global source is predicted to report (p + b + g and Exp(beta) R) as it was: the OMC
        did not move, the frame the filter expresses it in did. Why: b was learnt against the local samples of
        the old frame, at a; without the move every OMC-only output after the change stays in the old frame until
        the local source sees the tool again -- never, in a run that leaves the Vega's view before the
        calibration is done (the twin's B-G-P: the 30-sample bridge link is 0.2-0.5 mm off at the tool;
        docs/fullperc_filter.md "The link's covariance and the bridge link"). d is taken at a, not at p: the old
        frame's error that b holds is the one at a (a link's rotation error makes it differ from place to place), so
        the output is what it would have been had the new frame been used when b was learnt. P is kept: R_M is
        within a milliradian of I, and the link's own uncertainty is the pipeline's frame covariance, not the
        filter's.
        A reset forgets the frame.
        """
        s = self.s
        if local and s.t_ns is not None:
            s.anchor = s.p
        if T_frame is s.frame:
            return None
        old = s.frame
        if old is None:
            if local:
                s.frame = T_frame   # kept by reference: the caller replaces a frame, never edits it
            return None
        s.frame = T_frame
        if np.array_equal(old, T_frame) or s.anchor is None:
            return None
        M = np.asarray(T_frame, dtype=float) @ np.linalg.inv(old)
        RM, tM = M[:3, :3], M[:3, 3]
        d = RM @ s.anchor + tM - s.anchor
        s.p, s.b = s.p + d, s.b - d
        s.v, s.w = RM @ s.v, RM @ s.w
        s.R = RM @ s.R
        s.beta = so3_log(so3_exp(s.beta) @ RM.T)
        s.anchor = s.anchor + d
        return M

    # ---- predict --------------------------------------------------------------------------------
    def predict(self, t_ns: int) -> None:
        """Move the state to ``t_ns`` (constant velocity and angular velocity; module docstring)."""
        s = self.s
        t, dt = predict_interval(t_ns, s.t_ns, s.pending_ns, self.params.max_gap_s)
        if dt is None:
            s.pending_ns = t
            return
        if dt == 0.0:
            return
        pr = self.params
        Rw = so3_exp(s.w * dt)
        phi = math.exp(-dt / pr.sys_time)
        s.p = s.p + s.v * dt
        s.R = Rw @ s.R
        s.g = phi * s.g
        phb, qbe = pr.rot_decay(dt)
        s.beta = phb * s.beta
        # P = F P F^T with F = I except F_pv = dt I, F_thth = Rw, F_thw = dt I, F_gg = phi I, F_bebe = phi_beta I:
        # as row and column operations on the blocks F touches (equal to the product, ~3x cheaper at 21x21 in numpy)
        P = s.P.copy()
        P[P_, :] += dt * P[V_, :]
        P[TH, :] = Rw @ P[TH, :] + dt * P[W_, :]
        P[G_, :] *= phi
        P[BE, :] *= phb
        P[:, P_] += dt * P[:, V_]
        P[:, TH] = P[:, TH] @ Rw.T + dt * P[:, W_]
        P[:, G_] *= phi
        P[:, BE] *= phb
        qa, qr = pr.accel_noise, pr.ang_accel_noise
        for (i, j), q in (((0, 3), qa), ((9, 12), qr)):
            for k in range(3):
                P[i + k, i + k] += q * dt**3 / 3
                P[i + k, j + k] += q * dt**2 / 2
                P[j + k, i + k] += q * dt**2 / 2
                P[j + k, j + k] += q * dt
        for k in range(3):
            P[6 + k, 6 + k] += pr.bias_walk * dt
            P[15 + k, 15 + k] += qbe
            P[18 + k, 18 + k] += s.sys_var * (1.0 - phi * phi)
        self._spatial_decay(P, t)
        s.P = 0.5 * (P + P.T)
        s.t_ns = t

    def _spatial_decay(self, P: np.ndarray, t: int) -> None:
        """beta's and b's spatial decay after the prediction to ``t`` (module docstring), on s.beta, s.b and ``P`` in
        place; mu's (:mod:`rot_noise_scale`) over the same distance."""
        s, pr = self.s, self.params
        if s.rot_anchor is None or (t - s.t_local_ns) * 1e-9 <= pr.local_lost_s:
            return
        d = math.dist(s.p, s.rot_anchor)   # as the fast form computes it (one rounding less than norm of a difference)
        if d <= s.rot_dmax:
            return
        s.rot_scale = scale_decay(s.rot_scale, d - s.rot_dmax, pr.rot_noise_length)   # mu's own decay
        if pr.rot_bias_length > 0.0:
            f = math.exp(-(d - s.rot_dmax) / pr.rot_bias_length)
            s.beta = f * s.beta
            P[BE, :] *= f
            P[:, BE] *= f
            P[BE, BE] += pr.rot_sys_std**2 * (1.0 - f * f) * _I3
        if pr.bias_length > 0.0:
            f = math.exp(-(d - s.rot_dmax) / pr.bias_length)
            s.b = f * s.b
            P[B_, :] *= f
            P[:, B_] *= f
            P[B_, B_] += pr.bias_field_std**2 * (1.0 - f * f) * _I3
        s.rot_dmax = d

    def _local_fused(self, ml: Measurement | None) -> None:
        """Record where the local source last saw the tool (beta's and b's spatial decay start from there)."""
        if ml is not None:
            s = self.s
            s.t_local_ns, s.rot_anchor, s.rot_dmax = ml.t_ns, s.p.copy(), 0.0

    # ---- update ---------------------------------------------------------------------------------
    def _init_state(self, t: int, mg: Measurement | None, ml: Measurement | None) -> Step:
        s = self.s
        pr = self.params
        keep = s.t_ns is not None
        dt = (t - s.t_ns) * 1e-9 if keep else 0.0
        Pbb = s.P[B_, B_] + pr.bias_walk * dt * _I3 if keep else pr.init_bias_std**2 * _I3
        phb, qbe = pr.rot_decay(dt)
        Pbe = phb * phb * s.P[BE, BE] + qbe * _I3 if keep else pr.init_rot_bias_std**2 * _I3
        phi = math.exp(-dt / pr.sys_time)
        Pgg = phi * phi * s.P[G_, G_] + s.sys_var * (1 - phi * phi) * _I3 if keep else s.sys_var * _I3
        s.g = phi * s.g if keep else np.zeros(3)
        s.beta = phb * s.beta
        if not keep:
            s.b, s.beta = np.zeros(3), np.zeros(3)
        s.p = ml.p.copy() if ml is not None else mg.p - s.b - s.g
        s.v, s.w = np.zeros(3), np.zeros(3)
        s.has_R = False
        if ml is not None and ml.q is not None:
            s.R, s.has_R = quat_to_R(ml.q), True
        elif mg is not None and mg.q is not None:
            s.R, s.has_R = so3_exp(-s.beta) @ quat_to_R(mg.q), True
        s.P = self._prior(Pbb, Pbe, Pgg)
        if ml is None:   # p = z - b - g: its error is minus theirs (module docstring, "(re-)initialisation")
            s.P[P_, P_] += Pbb + Pgg
            s.P[P_, B_] = s.P[B_, P_] = -Pbb
            s.P[P_, G_] = s.P[G_, P_] = -Pgg
        s.t_ns, s.pending_ns = t, None
        s.t_global_ns = None   # lambda is kept; its next step starts from the next global sample fused
        s.rot_scale, s.t_rot_scale_ns = 1.0, None   # mu starts again (rot_noise_scale)
        self._local_fused(ml)
        return self._step(t, mg, ml, reset=True)

    def _rows(self, m: Measurement, t: int):
        """(H, y, Rm, n_pos_rows) of one measurement at filter time t; rotation rows only with ``q``."""
        s = self.s
        pr = self.params
        lag = (t - m.t_ns) * 1e-9
        if lag > pr.max_gap_s:
            raise ValueError(f"measurement {lag:.3f} s older than the filter time (max_gap_s {pr.max_gap_s})")
        glob = m.source == SOURCE_GLOBAL
        rot = m.q is not None
        H = np.zeros((6 if rot else 3, N))
        H[0:3, P_] = _I3
        H[0:3, V_] = -lag * _I3
        zp = s.p - lag * s.v
        if glob:
            H[0:3, B_] = _I3
            H[0:3, G_] = _I3
            zp = zp + s.b + s.g
        y = np.zeros(6 if rot else 3)
        y[0:3] = m.p - zp
        if rot:
            A = so3_exp(-lag * s.w) if lag > 0 else _I3
            if glob:
                A = so3_exp(s.beta) @ A
                H[3:6, BE] = _I3
            H[3:6, TH] = A
            H[3:6, W_] = -lag * _I3
            y[3:6] = so3_log(quat_to_R(m.q) @ (A @ s.R).T)
        if m.cov is not None:
            Rm = m.cov if rot else m.cov[0:3, 0:3]
        else:
            sp, sr = (pr.global_std, pr.rot_global_std) if glob else (pr.local_std, pr.rot_local_std)
            Rm = np.diag([sp * sp] * 3 + ([sr * sr] * 3 if rot else []))
        return H, y, Rm

    def update(self, *measurements: Measurement) -> Step:
        """Fuse one measurement or a (global, local) pair in one stacked error-state update (module docstring)."""
        mg, ml = split_update(self.kind, measurements)
        t_new = max(m.t_ns for m in measurements)
        if self.time_ns is None or t_new > self.time_ns:
            self.predict(t_new)
        t = self.time_ns
        s = self.s
        if s.pending_ns is not None:
            return self._init_state(t, mg, ml)
        if not s.has_R:   # first sample with an orientation after a position-only start: take it as is
            m = ml if ml is not None and ml.q is not None else mg if mg is not None and mg.q is not None else None
            if m is not None:
                s.R = quat_to_R(m.q) if m is ml else so3_exp(-s.beta) @ quat_to_R(m.q)
                s.has_R = True
        pr = self.params
        blocks = [self._rows(m, t) for m in (mg, ml) if m is not None]
        H = np.vstack([b[0] for b in blocks])
        y = np.concatenate([b[1] for b in blocks])
        Rm = block_diag(*[b[2] for b in blocks])
        mu = None
        if mg is not None and mg.q is not None and pr.rot_noise_adapt_time > 0.0:   # mu R_rot (rot_noise_scale)
            mu = self._rot_scale(t, mg, ml, blocks)
            if mu[0] != 1.0:
                Rm[0:6, 0:6] = scaled_cov(Rm[0:6, 0:6], mu[0])
        if mg is not None and s.noise_scale != 1.0:   # lambda R_p of the global sample (module docstring)
            Rm[0:3, 0:3] *= s.noise_scale
        P = s.P
        if mg is not None:
            sv = mg.extras.get("sys_var")
            s.sys_var = float(sv) if sv is not None and math.isfinite(sv) and sv > 0 else pr.sys_std**2
        S = H @ P @ H.T + Rm
        nis = float(y @ np.linalg.solve(S, y))
        log_lik = gaussian_log_lik(nis, np.linalg.slogdet(S)[1], len(y))   # before a hop raises S
        nis_g, hop, held = 0.0, False, False
        if mg is not None:
            ng = len(blocks[0][1])
            nis_g = float(y[0:3] @ np.linalg.solve(S[0:3, 0:3], y[0:3]))
            hop_p = nis_g > pr.hop_gate
            hop_r = ng == 6 and float(y[3:6] @ np.linalg.solve(S[3:6, 3:6], y[3:6])) > pr.hop_gate
            lam_next = noise_scale_step(s.noise_scale, s.t_global_ns, mg.t_ns, nis_g, pr)
            hop = hop_p or hop_r
            self.hop_counts["position"] += hop_p
            self.hop_counts["rotation"] += hop_r
            confirmed, hop_run = hop_run_step(s.hop_run, hop_p, *y[0:3].tolist(), pr)
            if hop_p and pr.hop_to_bias and hop_watched(t, s.t_local_ns, ml is not None, pr):   # module docstring
                Ph = P.copy()
                k = G_ if pr.hop_into == "g" else B_
                Ph[k, k] += np.diag(y[0:3] ** 2)
                Sh = H @ Ph @ H.T + Rm
                log_lik = hop_mixture(log_lik, gaussian_log_lik(float(y @ np.linalg.solve(Sh, y)),
                                                                np.linalg.slogdet(Sh)[1], len(y)))
                if confirmed:   # into the bias
                    P, S = Ph, Sh
                else:           # not (yet) a step: its position held out
                    Rm[0:3, 0:3] *= HOLD_OUT
                    S, held = H @ P @ H.T + Rm, True
        G = np.linalg.solve(S, H @ P).T
        dx = G @ (np.concatenate([np.zeros(3), y[3:]]) if held else y)   # held out: its position moves nothing
        IKH = _IN - G @ H
        P = IKH @ P @ IKH.T + G @ Rm @ G.T
        # inject and reset the error state
        s.p = s.p + dx[P_]
        s.v = s.v + dx[V_]
        s.b = s.b + dx[B_]
        s.R = so3_exp(dx[TH]) @ s.R
        s.w = s.w + dx[W_]
        s.beta = s.beta + dx[BE]
        s.g = s.g + dx[G_]
        Gt = _I3 - 0.5 * skew(dx[TH])     # reset Jacobian G = I except G_thth: P = G P G^T on those rows/columns
        P[TH, :] = Gt @ P[TH, :]
        P[:, TH] = P[:, TH] @ Gt.T
        s.P = 0.5 * (P + P.T)
        if not (np.all(np.isfinite(s.P)) and np.all(np.isfinite(s.p)) and np.all(np.isfinite(s.R))):
            self.reset()
            raise FloatingPointError("filter produced a non-finite state; it was reset")
        s.t_ns = t
        if mg is not None:
            s.noise_scale, s.t_global_ns, s.hop_run = lam_next, mg.t_ns, hop_run
        if mu is not None:
            s.rot_scale, s.t_rot_scale_ns = mu[1:]
        self._local_fused(ml)
        return self._step(t, mg, ml, innovation=y[0:3].copy(), nis=nis, nis_global=nis_g, hop=hop, log_lik=log_lik)

    def _rot_scale(self, t: int, mg: Measurement, ml: Measurement | None, blocks: list) -> tuple:
        """(mu for this update, then mu and the pair clock after it) of a global sample with an orientation,
        before the update (:mod:`rot_noise_scale`); ``blocks`` from :meth:`_rows`."""
        s, pr = self.s, self.params
        mu, t_mu = s.rot_scale, s.t_rot_scale_ns
        if ml is None or ml.q is None:
            return mu, mu, t_mu
        Rl = so3_exp((mg.t_ns - ml.t_ns) * 1e-9 * s.w) @ quat_to_R(ml.q)   # the local sample at the global's stamp
        d = so3_log(quat_to_R(mg.q) @ (so3_exp(s.beta) @ Rl).T)
        est = pair_estimate(d.tolist(), float(np.trace(blocks[1][2][3:6, 3:6])), float(np.trace(s.P[BE, BE])),
                            float(np.trace(blocks[0][2][3:6, 3:6])))
        return mu, scale_step(mu, t_mu, mg.t_ns, est, pr.rot_noise_adapt_time, pr.rot_noise_adapt_min,
                              pr.rot_noise_adapt_max), mg.t_ns

    def _step(self, t: int, mg, ml, **kw) -> Step:
        s = self.s
        src = (SOURCE_GLOBAL if mg is not None else 0) | (SOURCE_LOCAL if ml is not None else 0)
        P = s.P.copy()
        P[P_, P_] += field_var(t, s.t_local_ns, s.p, s.rot_anchor, self.params, s.b) * _I3   # the output's only
        pose_cov = P[np.ix_(np.r_[P_, TH], np.r_[P_, TH])]   # the [p, theta] rows and columns
        return Step(t, s.p.copy(), s.v.copy(), s.b + s.g, P, src,
                    q=R_to_quat(s.R) if s.has_R else None, pose_cov=pose_cov if s.has_R else None,
                    reset=kw.pop("reset", False), **kw)
