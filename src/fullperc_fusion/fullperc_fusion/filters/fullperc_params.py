"""``FullpercParams``: the parameters of the ``fullperc`` filter, apart from the filter.

Production code reads them without the filter -- the node's configuration (``fusion_config``: its rows, defaults and
checks), the noise-model file (:mod:`.noise_model_file`), the registry's parameter class -- and two forms of the
filter share them (:mod:`.fullperc_reference`, the general form whose module docstring states the model each
parameter belongs to, and :mod:`.fullperc`, the fast form). What each field means and where its value comes from is
in the class docstring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fullperc_fusion.filters.motion import PRESETS
from fullperc_fusion.filters.paper_family import FilterParams

__all__ = ["HOP_INTO", "HOP_NEEDS_LOCAL", "FullpercParams"]

HOP_INTO = ("b", "g")   # FullpercParams.hop_into: the bias part a position hop goes into
HOP_NEEDS_LOCAL = ("never", "once", "always")   # FullpercParams.hop_needs_local


@dataclass
class FullpercParams(FilterParams):
    """The position parameters of CBKF (:class:`.paper_family.FilterParams`, same meaning) plus the orientation's.

    ang_accel_noise  q_alpha, white angular-acceleration density [rad^2/s^3]: 0.5 lets a hand-held tool change its
                     turn rate by ~0.7 rad/s within a second.
    rot_bias_walk    q_beta, random walk of the OMC's orientation bias [rad^2/s]: 1e-6 -> ~1 mrad per sqrt(s) as
                     the camera set and the distortion change along the path.
    rot_global_std   OMC orientation noise per axis [rad] without a covariance (5 mrad: raw OMC, spec bags).
    rot_local_std    Vega orientation noise per axis [rad] without a covariance (2.2 mrad: raw Vega, spec bags).
    init_rot_std, init_angvel_std, init_rot_bias_std  prior stds of theta [rad], w [rad/s], beta [rad].
    sys_time         correlation time of the OMC's systematic position error [s] (3.06 s: Gauss-Markov fit of the
                     raw OMC error's structure function, spec bags, measurement_models).
    sys_std          its per-axis std [m] for a global sample without ``sys_var`` (0.21 mm: raw OMC, spec bags).
    rot_sys_time     correlation time of beta's Gauss-Markov part [s]; 0: beta is the random walk alone.
    rot_bias_length  L [m], beta's decay length once the local source has lost the tool (0: off); 0.0527: the raw
                     OMC rotation error over distance, white + Gauss-Markov (``paper`` bags; ``sensor_stats``).
    bias_length      L_b [m], the position bias b's decay length once the local source has lost the tool (0: off,
                     b kept as learnt: CBKF's compensation); Gauss-Markov in the distance from where it last saw it.
    bias_field_std   s_f [m], the OMC's position error field's per-axis std (the sill of its semivariogram over
                     distance): b's stationary std in that model, what b's variance returns to far away.
    bias_field_length  L_f [m], that field's correlation length. With ``bias_length`` 0 (b kept as learnt) the
                     output's position covariance adds the field's change since the local source last saw the tool,
                     2 s^2 (1 - exp(-d / L_f)) per axis at the distance d from there, the sill s^2 the larger of
                     s_f^2 and |b|^2 / 3 (the learnt b: this room's own draw of the field; :func:`.fullperc_state.
                     field_var`): the estimate is unchanged, its covariance says how far the learnt b may be off.
                     ``bias_length`` 0 by default (b kept as learnt, CBKF's rule); s_f and L_f the ``spec`` bags' fit
                     (0.341 mm, 0.296 m); a room's own noise-model file sets all three (``fit_noise_model --write``:
                     the raw (OMC - local chain) position differences' semivariogram over distance, no truth, no
                     filter output; ``bias_length`` 0 where the fit shows no length). No one decay length fits every
                     room: the ``paper`` bags show none (their error field holds beyond the Vega's 0.54 m), and
                     shipping spec's, measured over 10 seeds (``make accuracy``), helps ``spec`` (tool 0.308 -> 0.297
                     mm) and hurts ``paper`` (tool 2.073 -> 2.245 mm, above CBKF's 2.097).
    local_lost_s     no local sample for this long [s]: it has lost the tool (0.1: the evaluation's split).
    hop_into         "b" (default) or "g": the bias part a position hop goes into (module docstring).
    hop_needs_local  when a position hop may go into the bias (:func:`.fullperc_state.hop_watched`): "once" (default)
                     once a local source has seen the target, "always" only while one sees it, "never" (CBKF's rule)
                     needs none.
    hop_confirm      global samples in a row over the hop gate, each innovation in the direction of the one before,
                     that make a hop (1: every crossing is one, CBKF's rule, the default); a crossing not (yet)
                     confirmed is held out (:mod:`.fullperc_reference`). 2 keeps single frames of an OMC noisier than
                     its model out of the bias: measured over 10 seeds it helps ``spec`` (tool 0.315 -> 0.299 mm) and
                     costs ``paper`` (tool 2.028 -> 2.072 mm; docs/fullperc_filter.md "Where a hop goes").
    noise_adapt_time tau of the global white-noise scale lambda [s] (module docstring; 0 = off). 0.4 s: the
                     scale follows a change of the camera set within about half a second (~50 OMC frames at
                     120 Hz), long enough that a single outlier moves it little.
    noise_adapt_max  the largest lambda (25: the OMC's white std at most 5x the model's).
    rot_noise_adapt_time  tau of the global rotation-noise scale mu [s] (:mod:`rot_noise_scale`; 0 = off): 1 s,
                     ~60 (OMC, Vega) pairs, a few centimetres of a hand-held tool's path.
    rot_noise_adapt_min, rot_noise_adapt_max  mu's bounds (0.05 and 25: the OMC's rotation std 0.22x to 5x the model's).
    rot_noise_length L [m] over which mu returns to 1 once the local source has lost the tool, by the distance beta
                     decays over (0.0527: ``rot_bias_length``'s fit; 0: mu kept).
    motion           "fixed" (one model: the fields above) or "auto": one model per preset of ``motion_models``, run
                     as an IMM (:mod:`.fullperc_imm`; the node's ``<target>.motion``, :mod:`.motion`).
    motion_models    the presets ``auto`` runs (:data:`.motion.PRESETS`).
    motion_dwell     tau [s], the mean time a target keeps one motion (the IMM's switching rate): 2 s, an
                     instrument is picked up, carried and laid down over seconds, not frames.
    rot_sys_std      stationary per-axis std of that part [rad]. 3.38 s and 8.94 mrad: the slow part of the raw
                     OMC rotation error's structure function fitted as white + two Gauss-Markov processes
                     (``paper`` bags: fast 5.3 mrad / 0.33 s, slow 8.94 mrad / 3.38 s; the fast part reverts within
                     frames and stays noise of the sample, :func:`measurement_models.omc_covariance`). On the
                     ``spec`` bags the slow part is 1.44 mrad / 2.8 s, whose short-lag increments 2 s^2 / tau ~
                     1.5e-6 rad^2/s are ``rot_bias_walk``'s order.
    """

    ang_accel_noise: float = 0.5
    rot_bias_walk: float = 1e-6
    rot_global_std: float = 5e-3
    rot_local_std: float = 2.2e-3
    init_rot_std: float = 0.05
    init_angvel_std: float = 0.5
    init_rot_bias_std: float = 0.02
    sys_time: float = 3.06
    sys_std: float = 0.210e-3
    rot_sys_time: float = 3.38
    rot_sys_std: float = 8.94e-3
    rot_bias_length: float = 0.0527
    bias_length: float = 0.0
    bias_field_std: float = 0.341e-3
    bias_field_length: float = 0.296
    local_lost_s: float = 0.1
    hop_into: str = "b"
    hop_needs_local: str = "once"
    hop_confirm: int = 1
    noise_adapt_time: float = 0.4
    noise_adapt_max: float = 25.0
    rot_noise_adapt_time: float = 1.0
    rot_noise_adapt_min: float = 0.05
    rot_noise_adapt_max: float = 25.0
    rot_noise_length: float = 0.0527
    motion: str = "fixed"
    motion_models: tuple[str, ...] = ("static", "arm", "hand")
    motion_dwell: float = 2.0

    def validate(self) -> FullpercParams:
        super().validate()
        if self.hop_into not in HOP_INTO:
            raise ValueError(f"filter parameter hop_into must be one of {HOP_INTO}, got {self.hop_into!r}")
        if self.hop_needs_local not in HOP_NEEDS_LOCAL:
            raise ValueError(f"filter parameter hop_needs_local must be one of {HOP_NEEDS_LOCAL}, "
                             f"got {self.hop_needs_local!r}")
        for name in ("ang_accel_noise", "rot_bias_walk", "init_rot_std", "init_angvel_std", "init_rot_bias_std",
                     "rot_sys_time", "rot_sys_std", "noise_adapt_time", "rot_bias_length", "rot_noise_adapt_time",
                     "rot_noise_length", "bias_length", "bias_field_std", "bias_field_length"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"filter parameter {name} must be finite and >= 0, got {v!r}")
        for name in ("rot_global_std", "rot_local_std", "sys_time", "sys_std", "local_lost_s"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"filter parameter {name} must be finite and > 0, got {v!r}")
        if not (np.isfinite(float(self.noise_adapt_max)) and self.noise_adapt_max >= 1.0):
            raise ValueError(f"filter parameter noise_adapt_max must be finite and >= 1, got {self.noise_adapt_max!r}")
        if isinstance(self.hop_confirm, bool) or not isinstance(self.hop_confirm, int) or self.hop_confirm < 1:
            raise ValueError(f"filter parameter hop_confirm must be an integer >= 1, got {self.hop_confirm!r}")
        if self.motion not in ("fixed", "auto"):
            raise ValueError(f"filter parameter motion must be 'fixed' or 'auto', got {self.motion!r}")
        self.motion_models = tuple(self.motion_models)
        if not self.motion_models or len(set(self.motion_models)) != len(self.motion_models) or not set(
                self.motion_models) <= set(PRESETS):
            raise ValueError(f"filter parameter motion_models must be distinct presets of {tuple(PRESETS)}, got "
                             f"{self.motion_models!r}")
        if not (np.isfinite(float(self.motion_dwell)) and self.motion_dwell > 0):
            raise ValueError(f"filter parameter motion_dwell must be finite and > 0, got {self.motion_dwell!r}")
        lo, hi = float(self.rot_noise_adapt_min), float(self.rot_noise_adapt_max)
        if not (np.isfinite(lo) and np.isfinite(hi) and 0.0 < lo <= 1.0 <= hi):
            raise ValueError(f"filter parameters rot_noise_adapt_min/max must be finite with 0 < min <= 1 <= max, got "
                             f"{lo!r} / {hi!r}")
        return self

    def rot_decay(self, dt: float) -> tuple[float, float]:
        """(phi_beta, q_beta) of beta over dt: phi_beta = exp(-dt / rot_sys_time) (1 when that is 0) and the
        process variance per axis q_beta = rot_bias_walk dt + rot_sys_std^2 (1 - phi_beta^2)."""
        if self.rot_sys_time <= 0.0:
            return 1.0, self.rot_bias_walk * dt
        phi = math.exp(-dt / self.rot_sys_time)
        return phi, self.rot_bias_walk * dt + self.rot_sys_std**2 * (1.0 - phi * phi)

    @classmethod
    def from_params(cls, params: FilterParams | None) -> FullpercParams:
        """``params`` itself when it already is one; else its position fields with the orientation defaults."""
        if isinstance(params, FullpercParams):
            return params
        if params is None:
            return cls()
        return cls(**{k: getattr(params, k) for k in FilterParams.__dataclass_fields__})

