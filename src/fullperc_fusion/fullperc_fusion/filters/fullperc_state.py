"""The state layout of the ``fullperc`` filter and the rules both of its forms share without the filter.

:mod:`.fullperc_reference` (the general form, whose module docstring states the model) and :mod:`.fullperc` (the
fast form) read the same error-state layout, the same state record and the same parameter-only rules from here;
kept apart so the reference holds the model's equations and stays within the fusion package's module size
(test/test_code_rules.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fullperc_fusion.filters.fullperc_params import FullpercParams

__all__ = ["BE", "B_", "G_", "HOLD_OUT", "N", "POSE_FLAT", "P_", "TH", "V_", "W_", "FullpercState", "copy_state",
           "field_var", "hop_run_step", "hop_watched", "noise_scale_step"]

# the error state dx = [dp dv db | dtheta dw dbeta | dg] (:mod:`.fullperc_reference`)
N = 21
P_, V_, B_, TH, W_, BE, G_ = (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15), slice(15, 18),
                              slice(18, 21))
# the [p, theta] rows and columns of P.ravel(): a step's 6x6 pose covariance is P.ravel()[POSE_FLAT].reshape(6, 6)
POSE_FLAT = np.array([N * r + c for r in (0, 1, 2, 9, 10, 11) for c in (0, 1, 2, 9, 10, 11)])


def noise_scale_step(lam: float, t_prev_ns: int | None, t_ns: int, nis_g: float, pr: FullpercParams) -> float:
    """lambda after a global sample at ``t_ns`` with position NIS ``nis_g``, the previous one fused at ``t_prev_ns``
    (None: none since the start or the last re-initialisation; :mod:`.fullperc_reference`'s module docstring)."""
    if pr.noise_adapt_time <= 0.0:
        return 1.0
    dt = 0.0 if t_prev_ns is None else max(0.0, (t_ns - t_prev_ns) * 1e-9)
    a = 1.0 - math.exp(-dt / pr.noise_adapt_time)
    return min(pr.noise_adapt_max, max(1.0, (1.0 - a) * lam + a * lam * nis_g / 3.0))


# a gate crossing not (yet) confirmed as a hop: its position variance times this (std x 1000), so it moves the state by
# ~1e-6 of a normal sample's pull -- held out, while the update's other rows (its rotation, a local sample) count
HOLD_OUT = 1e6


def hop_run_step(run: tuple | None, hop_p: bool, y0: float, y1: float, y2: float,
                 pr: FullpercParams) -> tuple[bool, tuple | None]:
    """(confirmed, run after this sample) of a global sample whose position crossed the hop gate (``hop_p``) with
    innovation (y0, y1, y2), ``run`` = (n, innovation) of the crossings in a row before it (None: the previous
    global sample did not cross): a crossing in the same direction as the previous one (positive dot product)
    extends the run, any other starts one; the hop is confirmed once the run has ``hop_confirm`` samples
    (:mod:`.fullperc_reference`'s module docstring)."""
    if not hop_p:
        return False, None
    n = run[0] + 1 if run is not None and y0 * run[1] + y1 * run[2] + y2 * run[3] > 0.0 else 1
    return n >= pr.hop_confirm, (n, y0, y1, y2)


def hop_watched(t_ns: int, t_local_ns: int | None, with_local: bool, pr: FullpercParams) -> bool:
    """Whether a position hop of a global sample fused at ``t_ns`` may go into the bias, by ``hop_needs_local``:
    ``never`` (CBKF's rule) always; ``once`` (the default) once a local source has seen the target (a local sample
    in the same update, ``with_local``, or one fused before, at ``t_local_ns``); ``always`` only while one sees it
    (a local sample in the update or within ``local_lost_s`` before).

    Why: only the local source observes the bias (the OMC minus the local chain). Before it has first seen the target,
    b holds no learnt compensation: a hop put into it keeps nothing worth keeping (the OMC's error before the step is
    no better known than after it), and the hops add up like a random walk while the OMC's own error stays bounded.
    Measured on ``spec`` seed 4 P-B-G (the OMC alone for the first 9.6 s; docs/fullperc_filter.md "Where a hop
    goes"): b grew to about 1 mm over some twenty flagged hops, the output 1.0 mm off the truth there against the raw
    OMC's 0.32 mm. Once b has been learnt, a step of the OMC put into b keeps that compensation valid, which is what a
    lasting camera-set change needs (``paper``); ``always`` also fuses the steps after the Vega has lost the target
    as samples, for an OMC whose steps do not last (``spec``). Unwatched, the sample is fused as any other (no hop
    mixture in its likelihood either: a jump counts against a model that moves smoothly)."""
    if pr.hop_needs_local == "never" or with_local:
        return True
    if t_local_ns is None:
        return False
    return pr.hop_needs_local == "once" or (t_ns - t_local_ns) * 1e-9 <= pr.local_lost_s


def field_var(t_ns: int, t_local_ns: int | None, p, anchor, pr: FullpercParams, b=None) -> float:
    """The variance per axis [m^2] the OMC's position error field adds to the output at ``p`` once the local source
    has lost the tool (its newest sample, fused at ``anchor``, older than ``local_lost_s`` at ``t_ns``).

    Why: with ``bias_length`` 0 the filter keeps b as learnt where the local source last saw the tool (CBKF's rule,
    what the ``paper`` room needs: its error field holds beyond the Vega's volume). The OMC's error is a field over
    the room, e(x) = b(x) + white, whose semivariogram of the raw (OMC - local chain) differences is
    gamma(h) = nugget^2 + s_f^2 (1 - exp(-h / L_f)) (``fit_noise_model``): so at a distance d from where it was
    learnt, b may be off by e(x) - e(a) less the white part, variance 2 s_f^2 (1 - exp(-d / L_f)) per axis, which
    the filter's P (b a random walk in time) does not hold. It goes into the output's covariance only -- the
    estimate, whose best guess of the field is still b, is unchanged. 0 while the local source sees the tool, when
    b itself decays with distance (``bias_length`` > 0: P holds that), or with s_f or L_f 0.

    The sill is the larger of s_f^2 and |b|^2 / 3 (``b``, the learnt bias, when given). Why: s_f is a room's fit
    (the built-in one ``spec``'s, 0.341 mm), and b is the same field drawn once, in this room, where the Vega saw the
    tool: for a zero-mean field E[b_i^2] = s_f^2 per axis, so |b|^2 / 3 is the room's own evidence of its sill. A room
    whose OMC is off by millimetres there (``paper``) has a field of that size, and a covariance built
    on 0.34 mm would claim a confidence the carried b does not have; the estimate is not touched either way."""
    if (pr.bias_length > 0.0 or pr.bias_field_std <= 0.0 or pr.bias_field_length <= 0.0 or anchor is None
            or t_local_ns is None or (t_ns - t_local_ns) * 1e-9 <= pr.local_lost_s):
        return 0.0
    d = math.dist(p, anchor)
    sill = pr.bias_field_std**2
    if b is not None:
        sill = max(sill, (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]) / 3.0)
    return 2.0 * sill * -math.expm1(-d / pr.bias_field_length)


@dataclass
class FullpercState:
    """The reference's state (``FullpercReference.s``), everything its ``snapshot`` copies; the fast form gives its own
    state in this form (``FullpercFilter.state``)."""

    p: np.ndarray
    v: np.ndarray
    b: np.ndarray
    R: np.ndarray
    w: np.ndarray
    beta: np.ndarray
    P: np.ndarray
    t_ns: int | None
    pending_ns: int | None
    has_R: bool
    g: np.ndarray                  # Gauss-Markov part of the global position bias
    sys_var: float                 # its stationary variance (newest global sample's model, else sys_std^2)
    noise_scale: float = 1.0       # lambda, the global white position noise's scale (noise_adapt_time)
    t_global_ns: int | None = None  # stamp of the newest global sample fused (for lambda's dt_g)
    frame: np.ndarray | None = None  # the 4x4 the caller says the estimate is expressed in (express_in)
    anchor: np.ndarray | None = None  # p when the newest local sample in that frame came (express_in)
    t_local_ns: int | None = None  # stamp of the newest local sample fused (beta's and b's spatial decay)
    rot_anchor: np.ndarray | None = None  # a_r: p after that sample was fused
    rot_dmax: float = 0.0          # d_max: the farthest p has been from a_r since
    rot_scale: float = 1.0         # mu, the global rotation noise's scale (rot_noise_scale)
    t_rot_scale_ns: int | None = None  # stamp of the global sample of the newest pair mu was learnt from
    hop_run: tuple | None = None   # (n, y_p) of the global samples in a row over the hop gate (hop_run_step)


def copy_state(s: FullpercState) -> FullpercState:
    """A copy of every array of the state (the scalars are immutable): ~10x cheaper than copy.deepcopy."""
    return FullpercState(s.p.copy(), s.v.copy(), s.b.copy(), s.R.copy(), s.w.copy(), s.beta.copy(), s.P.copy(), s.t_ns,
                  s.pending_ns, s.has_R, s.g.copy(), s.sys_var, s.noise_scale, s.t_global_ns, s.frame,
                  s.anchor, s.t_local_ns, s.rot_anchor, s.rot_dmax, s.rot_scale, s.t_rot_scale_ns, s.hop_run)
