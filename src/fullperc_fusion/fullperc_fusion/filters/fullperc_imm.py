"""``fullperc`` with ``motion: auto``: one :class:`.fullperc.FullpercFilter` per motion preset, run as an IMM.

Why: how a target moves decides three things the filter cannot get right with one setting for every target -- how
fast its velocity may change (q_a, q_alpha), its velocity prior when first seen, and whether a jump of its OMC pose
is the sensor's (into the bias) or the target's own (into the pose). A tool on the arm and an instrument in a hand
need opposite answers, and a target may be both in turn (an instrument laid down). Instead of a hand-set model per
target, every preset of ``motion_models`` (:data:`.motion.PRESETS`: ``arm``, ``hand``, ``static``) runs as one
model of an interacting multiple model estimator (:mod:`.motion` states the recursion), and the samples decide: each
model's weight follows the likelihood of every update under it: ``Step.log_lik``, the innovation against the model's
own S before a hop raises it (a jump that the ``arm`` model would put into the bias costs it weight), plus the
speed envelope of its class (:func:`.motion.speed_log_lik` of the model's own speed estimate: per-sample innovations
alone cannot tell a walk from an arm's motion, :mod:`.motion`).

The mixing works on the filters' error state (:mod:`.fullperc_reference`'s layout): model i's offset from a reference
state is x_i - x_ref, with the orientation's Log(R_i R_ref^T) in the theta rows (the left perturbation of the
filter); the mixture's mean is put back as x_ref + dx0, R = Exp(dtheta0) R_ref. The reference is the most probable
model, for the interaction and the output alike: each model's offset is taken once per step (the models' states
are millimetres and milliradians apart, where the tangent spaces of any of them agree to first order). The models'
own adaptive scales, anchors and clocks (lambda, mu, a_r ...) are each model's own and are not mixed.

A model's hop rule (``hop_to_bias``: a step of the OMC pose is the sensor's, because this class moves smoothly) acts
only while the bank holds that model at least as probable as all the others together (its predicted probability
>= ``HOP_MAJORITY`` 0.5); in a minority model a flagged hop is fused as any sample. Why: the rule is the class's
belief about the target, and a model the data do not support would act on it for the output anyway, since the
interaction mixes its bias into every model. Measured: after a gap re-initialises the bank (equal weights, every
velocity at its prior), the ``static`` and ``arm`` models flagged a walking instrument's first samples as hops and
put millimetres into the bias (``paper`` seed 5 B-G-P, instrument: 3.67 mm against the OMC's 3.18; 2.60 mm with the
rule); while one class holds the target (an arm-held tool under ``arm``, a reference under ``static``), nothing
changes.

The output is the mixture over the models with weights mu: p, v, b + g, the orientation, and the covariance with
the spread of the models (the ``pose_cov`` of the step). The innovation, NIS and hop flag are the most probable
model's; ``log_lik`` is the mixture's. :attr:`probabilities` gives mu per model (the node's ``FusionStatus`` does not
carry it).
"""

from __future__ import annotations

import math
from dataclasses import replace
from operator import add, sub

import numpy as np

from fullperc_fusion.filters.api import Measurement, Step, StepCompat
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_state import POSE_FLAT, TH
from fullperc_fusion.filters.motion import mix, mix_each, mixing, posterior, speed_log_lik, transition, with_preset
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.filters.so3_float import R9_to_quat, exp9, log9, mul9, mul9_t

__all__ = ["HOP_MAJORITY", "FullpercImm"]

HOP_MAJORITY = 0.5   # a model puts a hop into its bias only while at least this probable (module docstring)
_POSE_6X6 = POSE_FLAT.reshape(6, 6)   # P.take(_POSE_6X6): the step's 6x6 pose covariance in one call
_CACHE_MAX = 64   # transition matrices kept; cleared when full



class FullpercImm(StepCompat):
    """``fullperc`` over several motion models at once (module docstring); a :class:`~.api.Filter`."""

    kind = "fullperc"

    def __init__(self, params: FilterParams | None = None) -> None:
        self.params = FullpercParams.from_params(params).validate()
        pr = self.params
        self.names = tuple(pr.motion_models)
        self.models = []
        for name in self.names:
            f = FullpercFilter(with_preset(pr, name))
            f.likelihood = True
            self.models.append(f)
        self._tcache: dict[int, np.ndarray] = {}   # transition() by the step [ns] (a stream has few distinct steps)
        self.reset()

    # ---- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        for f in self.models:
            f.reset()
        self._mu = np.full(len(self.models), 1.0 / len(self.models))

    @property
    def probabilities(self) -> dict[str, float]:
        """mu: the weight of each motion model after the newest update."""
        return dict(zip(self.names, self._mu.tolist(), strict=True))

    def snapshot(self) -> object:
        return ("fullperc_imm", tuple(f.snapshot() for f in self.models), self._mu)

    def restore(self, obj: object) -> None:
        if not (isinstance(obj, tuple) and len(obj) == 3 and obj[0] == "fullperc_imm"
                and len(obj[1]) == len(self.models)):
            raise TypeError(f"not a fullperc_imm snapshot: {type(obj).__name__}")
        for f, s in zip(self.models, obj[1], strict=True):
            f.restore(s)
        self._mu = obj[2]

    @property
    def time_ns(self) -> int | None:
        return self.models[0].time_ns

    @property
    def t_ns(self) -> int | None:
        return self.models[0].t_ns

    def express_in(self, T_frame: np.ndarray, local: bool = True) -> np.ndarray | None:
        moved = [f.express_in(T_frame, local) for f in self.models]
        return moved[0]

    # ---- the IMM ----------------------------------------------------------------------------------
    @staticmethod
    def _offsets(ref: FullpercFilter, models: list[FullpercFilter]) -> np.ndarray:
        """Each model's error-state offset from ``ref``'s state (module docstring), one row per model: the
        differences in Python floats (the models keep their states as float lists), one array call for all."""
        xr, Rr = ref._x, ref._R
        flat: list[float] = []
        for f in models:
            d = list(map(sub, f._x, xr))
            d[9:12] = log9(mul9_t(f._R, Rr))
            flat += d
        return np.fromiter(flat, float, len(flat)).reshape(len(models), -1)

    def _advance(self, t_ns: int) -> None:
        """Mix the models before they predict to ``t_ns`` (the IMM's interaction step), when all have a state.

        :func:`.motion.mixing`, and one :func:`.motion.mix` per model computed as every model's mixture in one
        :func:`.motion.mix_each`."""
        fs = self.models
        t0 = fs[0]._t
        if len(fs) == 1 or t0 is None or t_ns <= t0 or any(f._pend is not None or f._t != t0 for f in fs):
            return
        n = len(fs)
        T = self._tcache.get(t_ns - t0)
        if T is None:
            if len(self._tcache) >= _CACHE_MAX:
                self._tcache.clear()
            T = self._tcache[t_ns - t0] = transition((t_ns - t0) * 1e-9, n, self.params.motion_dwell)
        c, W = mixing(self._mu, T)
        # every model's offset from one reference, the most probable model (the tangent space the output is mixed
        # in too, _combine): one offset per model, not one per pair of models
        ref = fs[int(np.argmax(self._mu))]
        xr, Rr = ref._x, ref._R
        dx0, P0 = mix_each(W, self._offsets(ref, fs), np.array([f._P for f in fs]))
        for f, d, P in zip(fs, dx0.tolist(), P0, strict=True):
            x = list(map(add, xr, d))
            x[9] = x[10] = x[11] = 0.0
            # new objects: a snapshot taken before still holds the old ones (P: one of P0's planes, never written)
            f._x, f._R, f._P = x, mul9(exp9(d[9], d[10], d[11]), Rr), P
        self._mu = c

    def predict(self, t_ns: int) -> None:
        self._advance(int(t_ns))
        for f in self.models:
            f.predict(t_ns)

    def update(self, *measurements: Measurement) -> Step:
        """Every model's update, the models' weights from their likelihoods, and the mixture (module docstring)."""
        t_new = max(m.t_ns for m in measurements)
        now = self.time_ns
        if now is not None and t_new > now:
            self.predict(t_new)
        before = self.snapshot()
        for f, c in zip(self.models, self._mu.tolist(), strict=True):   # a hop rule acts in a majority model only
            f.hop_allowed = c >= HOP_MAJORITY
        try:
            steps = [f.update(*measurements) for f in self.models]
        except Exception:
            self.restore(before)   # all models or none: a model that refused the sample leaves the others as they were
            raise
        if any(s.reset for s in steps):
            self._mu = np.full(len(self.models), 1.0 / len(self.models))
            log_l = 0.0
        else:
            lls = [s.log_lik + speed_log_lik(math.sqrt(s.v.dot(s.v)), name)   # np.linalg.norm's arithmetic
                   for name, s in zip(self.names, steps, strict=True)]
            self._mu, log_l = posterior(self._mu, lls)
        return self._combine(steps, log_l)

    def _combine(self, steps: list[Step], log_l: float) -> Step:
        """The output: the models' mixture with weights mu; the most probable model's innovation, NIS and hop."""
        mu = self._mu
        k = int(np.argmax(mu))
        ref, top = self.models[k], steps[k]
        if len(self.models) == 1:
            return replace(top, log_lik=log_l)
        dx, P = mix(mu, self._offsets(ref, self.models), [s.P for s in steps])
        x = np.array(ref._x) + dx
        has_q = top.q is not None
        q = R9_to_quat(mul9(exp9(*dx[TH].tolist()), ref._R)) if has_q else None
        return Step(top.t_ns, x[0:3], x[3:6], x[6:9] + x[18:21], P, top.sources, innovation=top.innovation,
                    nis=top.nis, nis_global=top.nis_global, hop=top.hop, reset=top.reset, q=q,
                    pose_cov=P.take(_POSE_6X6) if has_q else None, log_lik=log_l)
