"""The scale mu of the global source's rotation noise, learnt where the local source sees the tool (``fullperc``).

Issue 18. The OMC model's rotation covariance (:func:`measurement_models.omc_covariance`) is the room's average;
where the Vega sees the tool -- near the OR table, where the OMC's cameras see it well too -- the OMC scatters far
less (``spec`` seed 0 P-G-B, ``scripts/orientation_phases.py --raw``: 0.47-0.71 mrad per axis, below the model's
1.64 mrad floor alone), so a filter that takes the model at face value leans on the Vega there and its orientation
is no better than the Vega's. Both :mod:`.fullperc_reference` and :mod:`.fullperc` use the global sample's
covariance with its rotation block scaled by mu (and its position-rotation blocks by sqrt(mu), so the matrix stays a
covariance), with mu from these rules:

* learnt from a (global, local) pair, both with an orientation: their disagreement after the bias,
      d = Log(R_g (Exp(beta) Exp((s_l - s_g) w) R_l)^T)     (s: each sample's lag behind the filter time),
  has E|d|^2 = mu tr R_g,rot + tr R_l,rot + tr P_beta (independent white noises and the bias's uncertainty), so
      est = (|d|^2 - tr R_l,rot - tr P_beta) / tr R_g,rot,
      mu <- clip((1 - a) mu + a est, mu_min, mu_max),   a = 1 - exp(-dt / tau),
  dt the time since the previous pair (the first pair after a (re)initialisation only starts the clock). A pair
  is the one place the OMC's rotation noise can be told from the filter's own error: a global sample alone is
  judged against a prediction made from the global source itself (learning from those too was tried during
  development and dropped: it drove mu down where the Vega does not see the tool).
* forgotten over the distance once the local source has lost the tool (no local sample for ``local_lost_s``), as
  beta is (:mod:`fullperc_reference`): with d the distance of the filter's position from where the local source
  last saw the tool and d_max the largest d since, a prediction taking d beyond d_max moves mu towards 1,
      mu <- 1 + (mu - 1) exp(-(d - d_max) / L),
  L = ``rot_noise_length`` (56.5 mm: the correlation length of the raw OMC rotation error over distance,
  ``sensor_stats.structure_over_distance`` on the ``paper`` bags). The scale belongs to the region it was learnt
  in; without the decay a low mu carried on after the Vega lost the tool and the output leaned on an OMC that was
  noisier where the tool went. Distance from the place, not path length: a tool held still beside the OR table
  keeps its mu however long the filter's position jitters.
* mu = 1 at every (re)initialisation; an update uses the mu in force after its prediction (the decay above
  included), and a pair's estimate acts from the next update on (as the position scale lambda,
  ``noise_adapt_time``).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["pair_estimate", "scale_decay", "scale_step", "scaled_cov"]


def pair_estimate(d: list[float], tr_local: float, tr_beta: float, tr_global: float) -> float:
    """est = (|d|^2 - tr R_l,rot - tr P_beta) / tr R_g,rot (module docstring); may be negative (a pair closer than
    the other terms explain), which the clip in :func:`scale_step` bounds."""
    return (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - tr_local - tr_beta) / tr_global


def scale_step(mu: float, t_prev_ns: int | None, t_ns: int, est: float, tau: float, lo: float, hi: float) -> float:
    """mu after a pair at ``t_ns`` with estimate ``est``, the previous pair at ``t_prev_ns`` (None: mu unchanged)."""
    if t_prev_ns is None or not math.isfinite(est):
        return mu
    a = 1.0 - math.exp(-max(0.0, (t_ns - t_prev_ns) * 1e-9) / tau)
    return min(hi, max(lo, (1.0 - a) * mu + a * est))


def scale_decay(mu: float, dist: float, length: float) -> float:
    """mu after the tool went ``dist`` [m] further from where the local source lost it: 1 + (mu - 1) exp(-dist / L);
    L = 0 keeps mu."""
    if length <= 0.0 or dist <= 0.0 or mu == 1.0:
        return mu
    return 1.0 + (mu - 1.0) * math.exp(-dist / length)


def scaled_cov(R: np.ndarray, mu: float) -> np.ndarray:
    """A copy of a 6x6 [p, theta] covariance with the rotation block x mu and the position-rotation blocks
    x sqrt(mu) (= D R D, D = diag(1, 1, 1, sqrt(mu) x 3): positive definite when R is)."""
    s = math.sqrt(mu)
    d = np.array([1.0, 1.0, 1.0, s, s, s])
    return R * np.outer(d, d)
