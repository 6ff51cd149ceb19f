"""How a target moves: the motion presets and the interacting-multiple-model (IMM) arithmetic of ``motion: auto``.

A target's ``motion`` (``<target>.motion``, :mod:`fullperc_fusion.fusion_config`) is ``auto`` (the default) or one of
:data:`PRESETS`. A preset sets the motion fields of every filter of the target (:func:`preset_fields`); values the
target sets itself (``<target>.accel_noise`` ...) still win. With ``auto`` the paper's four filters, which have one
motion model each, keep the node-wide values (their tuning: the paper's), and ``fullperc`` runs one model per preset
of ``fullperc.motion_models`` at once and weighs them by how well each predicted the samples
(:class:`.fullperc_imm.FullpercImm`): a target needs no hand-set motion values.

The presets are physical classes of motion, not fits to any recording (the twin's truth included):

* ``arm``: a tool carried by a robot arm. Surgical and collaborative arms move their tool at up to ~0.1-0.25 m/s
  with limited accelerations; the paper's tuning q_a = 0.05 m^2/s^3 (its filters' ``noise.accel``) lets the
  speed change by ~0.2 m/s within a second, and ``init_vel_std`` 0.1 m/s is that speed range. It turns the same
  way: a reorientation of the tool at up to ~0.25 rad/s, reached within about a second (~0.2 rad/s^2), gives by the
  same rule as q_a (q = v a, below) q_alpha ~ 0.25 x 0.2 = 0.05 rad^2/s^3. Its motion is smooth, so a step of the
  OMC pose is the sensor's (a camera came into or left its view): ``hop_to_bias``.
* ``hand``: an instrument carried by a walking person: ~1 m/s (a careful walk in a crowded room), ~2 m/s^2 of a
  hand starting and stopping: q_a ~ v a = 2 m^2/s^3 (a constant-velocity model lets the velocity change by
  ~sqrt(q T) over T; reaching v from rest at a takes T = v / a, so q = v^2 / T = v a; Bar-Shalom, Li, Kirubarajan
  2001, 6.2.2), ``init_vel_std`` 1 m/s (it may be walking when first seen); wrist turns of ~1 rad/s within a
  second or two: q_alpha 0.5. A jump of its OMC pose cannot be told from the hand's own motion: no hop into the
  bias.
* ``static``: a marker fixed to something that barely moves, e.g. a patient reference frame on the table: breathing
  moves it by a few mm at 12-20 per minute, v ~ 2 pi f A ~ 6 mm/s, a ~ (2 pi f)^2 A ~ 13 mm/s^2, q_a ~ 1e-4;
  ``init_vel_std`` 0.01 m/s. Breathing tilts it by only ~1 mrad, but a patient is turned and re-draped by staff:
  ~0.1 rad/s reached within ~2 s, q_alpha ~ 0.1 x 0.05 = 0.005 -- a class that ruled out turning would, in ``auto``,
  give any target that stands still while it turns (an arm-held tool) a far too small orientation covariance. Steps
  of its OMC pose are the sensor's.

Why each class's turn allowance matters in ``auto``: the IMM starts every model from the mixture of all of them at
every sample (:func:`mix`), so the models' states stay nearly equal and they differ in their process noise; whenever
the innovations are small the model with the smaller allowance predicts the tighter S and takes the weight. A class
whose q_alpha is below how its target can turn then carries a hand's turns too, with too small an orientation
covariance (measured: an arm q_alpha of 0.005, from a turn rate changed by 0.03 rad/s^2, gave the hand-held
instrument a pose NEES share of 0.58 on ``paper`` G-B-P, 0.64 on ``spec`` P-B-G-P, and twice the orientation error of
the ``hand`` preset, while the tool's figures did not move).

Why a speed envelope: each class is also defined by how fast its target can move -- an arm's tool at up to
``MAX_SPEED`` 0.25 m/s (the speed limit of a collaborative or surgical arm's tool), a breathing patient's marker at
a few cm/s, a hand as fast as a person walks. The samples' innovations alone cannot tell the classes apart: at
100-400 Hz a walk's accelerations (~2 m/s^2) move the position by 0.5 a dt^2 ~ 0.02 mm per OMC frame, far below the
OMC's noise, so the smoother ``arm`` model predicts a walk as well as ``hand`` does (measured: weight 0.007 for
``hand`` on the ``spec`` twin's instrument, seed 0, G-B-P) -- and its hop rule then puts the walk's jumps into the
bias. So a model whose own speed estimate exceeds its class's by e gets log L_j - e^2 / (2 SPEED_TOL^2) (SPEED_TOL
0.05 m/s: a speed estimated from sub-millimetre positions at 100+ Hz is good to a few cm/s; the factor is 1 within
the envelope, so a target that moves as its class allows is weighed by its innovations alone).

Why a hop mixture: a model with ``hop_to_bias`` (``arm``, ``static``) says that its target moves smoothly and a step
of the OMC pose is the sensor's (a camera came into or left the body's view), which happens at a small share of the
frames. So at a flagged hop its likelihood is the mixture (1 - pi) N(y; 0, S) + pi N(y; 0, S_hop), S_hop the S its
hop rule raised by y^2 on the bias (:func:`hop_mixture`, pi = ``HOP_PRIOR`` 0.01: a few steps per second at most
among the OMC's 100-240 frames). Without the second term a sensor's step of several mm on an arm-held tool costs
the ``arm`` model its weight and the output follows the step (measured: ``paper`` tool, 5 seeds, fullperc 4.5 %
worse than the ``arm`` preset, one task-seed 40 %); with S_hop alone the ``arm`` model explains any jump, a hand's
start too, and keeps its weight where it should not (``spec`` instrument 18 % worse than the ``hand`` preset on
seed 0's G-B-P). The weights barely depend on pi: 0.01 or 0.001 gave the same MAE to 0.3 % on those bags.

The IMM (Blom and Bar-Shalom 1988; Bar-Shalom, Li, Kirubarajan 2001, 11.6.6), the same recursion as filterpy's
``IMMEstimator`` (``test_motion.py`` holds :func:`mixing`, :func:`mix` and :func:`posterior` to it on linear
models), with the model switching as a continuous-time Markov chain of mean dwell time tau (``motion_dwell``):

* transition over dt: T_ii = exp(-dt / tau), the rest 1 - T_ii spread evenly over the other models
  (:func:`transition`);
* predicted model probabilities c_j = sum_i T_ij mu_i, mixing weights w_ij = T_ij mu_i / c_j (:func:`mixing`);
* each model starts its prediction from the mixture x0_j = sum_i w_ij x_i, P0_j = sum_i w_ij (P_i + d_ij d_ij^T),
  d_ij = x_i - x0_j (:func:`mix`; on a manifold the caller gives the d's in its tangent space);
* after the update, mu_j proportional to c_j L_j, L_j the likelihood of the sample under model j times its speed
  envelope's factor (:func:`posterior`, in logarithms), and the output is the mixture of the models with weights mu
  (:func:`mix`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

__all__ = ["HOP_PRIOR", "MAX_SPEED", "MOTIONS", "PRESETS", "SPEED_TOL", "gaussian_log_lik", "hop_mixture", "mix",
           "mix_each", "mixing", "posterior", "preset_fields", "speed_log_lik", "transition", "with_preset"]

# the motion fields of each preset (FilterParams / FullpercParams field names; module docstring for the values)
PRESETS: dict[str, dict[str, float | bool]] = {
    "arm": {"accel_noise": 0.05, "ang_accel_noise": 0.05, "init_vel_std": 0.1, "hop_to_bias": True},
    "hand": {"accel_noise": 2.0, "ang_accel_noise": 0.5, "init_vel_std": 1.0, "hop_to_bias": False},
    "static": {"accel_noise": 1e-4, "ang_accel_noise": 0.005, "init_vel_std": 0.01, "hop_to_bias": True},
}
MOTIONS = ("auto", *PRESETS)   # the values of <target>.motion
_LOG_2PI = math.log(2.0 * math.pi)
MAX_SPEED = {"arm": 0.25, "hand": 3.0, "static": 0.02}   # [m/s] the speed envelope of each class (module docstring)
SPEED_TOL = 0.05   # [m/s] how far beyond it a speed estimate may be before it counts against the class
HOP_PRIOR = 0.01   # prior probability that a flagged hop is the sensor's, in a model that puts hops into the bias


def preset_fields(motion: str) -> dict[str, float | bool]:
    """The filter fields a target's ``motion`` sets: a preset's motion fields, nothing for ``auto``."""
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
    return dict(PRESETS.get(motion, {}))


def with_preset(params, motion: str):
    """``params`` (a filter parameter dataclass) as one model of preset ``motion``: its motion fields, ``motion``
    "fixed" (the model of the IMM, or fullperc evaluated under that preset)."""
    return replace(params, motion="fixed", **PRESETS[motion])


def transition(dt: float, n: int, dwell: float) -> np.ndarray:
    """T (n x n, rows sum to 1) of the model switch over ``dt`` [s]: stay with probability exp(-dt / dwell).
    Built from one nested list (one array call; the IMM makes one per sample)."""
    if n == 1:
        return np.ones((1, 1))
    stay = math.exp(-max(dt, 0.0) / dwell)
    move = (1.0 - stay) / (n - 1)
    return np.array([[stay if i == j else move for j in range(n)] for i in range(n)])


def mixing(mu: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(c, W): the predicted model probabilities c_j = sum_i T_ij mu_i and the mixing weights W_ij = T_ij mu_i / c_j
    (each column of W sums to 1). W in Python floats: each entry the same two roundings as (T * mu[:, None]) /
    c[None, :], without the numpy calls (the IMM makes one mixing per sample, for a few models)."""
    c = mu @ T
    m, cl, Tl = mu.tolist(), c.tolist(), T.tolist()
    return c, np.array([[Tl[i][j] * m[i] / cl[j] for j in range(len(cl))] for i in range(len(m))])


def mix(weights: np.ndarray, dx: Sequence[np.ndarray], Ps: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(dx0, P0) of the mixture with ``weights`` (summing to 1) of Gaussians with means ``dx`` (offsets from any
    common reference point) and covariances ``Ps``: dx0 = sum w_i dx_i, P0 = sum w_i (P_i + e_i e_i^T),
    e_i = dx_i - dx0."""
    D = np.asarray(dx, dtype=float)
    dx0 = weights @ D
    E = D - dx0
    Ps = np.asarray(Ps)
    n = len(weights)
    # sum w_i P_i as np.tensordot(weights, Ps, axes=1) computes it -- the same one dot of a (1, n) by an (n, k*k)
    # matrix, so the same bits -- without its ~15 us of Python (four calls per IMM step, fullperc_imm.py)
    Pw = np.dot(weights.reshape(1, n), Ps.reshape(n, -1)).reshape(Ps.shape[1:])
    P0 = Pw + (E.T * weights) @ E
    return dx0, 0.5 * (P0 + P0.T)


def mix_each(W: np.ndarray, dx: np.ndarray, Ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mix` of the same Gaussians once per column of ``W`` (n x m, each column summing to 1; the IMM's
    interaction: column j is model j's mixture, :func:`mixing`), as (dx0 (m, k), P0 (m, k, k)); ``dx`` (n, k) and
    ``Ps`` (n, k, k) arrays.

    The same bits as ``mix(W[:, j], dx, Ps)`` for every j (``test_imm_fast.py``) in a third of the numpy calls:
    each stacked ``np.matmul`` runs, per j, the BLAS call that ``mix`` makes (gemv for the weighted sums, gemm for
    the spread); the rest is element-wise. The weights stay W's strided columns (a view): BLAS takes another path
    for a strided vector than for a contiguous one, with other roundings."""
    n, m = W.shape
    Wc = W.T[:, None, :]                                  # Wc[j, 0] is W[:, j], with its stride (a view)
    dx0 = np.matmul(Wc, dx)                               # (m, 1, k): W[:, j] @ dx
    E = dx - dx0                                          # (m, n, k): e_ij = dx_i - dx0_j
    Pw = np.matmul(Wc, Ps.reshape(n, -1)).reshape(m, *Ps.shape[1:])
    P0 = Pw + np.matmul(E.transpose(0, 2, 1) * Wc, E)
    return dx0.reshape(m, -1), 0.5 * (P0 + P0.transpose(0, 2, 1))


def posterior(c: np.ndarray, log_lik: Sequence[float]) -> tuple[np.ndarray, float]:
    """(mu, log L): mu_j = c_j L_j / sum_k c_k L_k from the models' log-likelihoods (the largest taken out first,
    so a sample that all models find unlikely underflows none), and the mixture's log-likelihood log sum c_k L_k.
    The largest is taken in Python (a NaN makes it NaN, as an array's max), the exponentials and the sum in numpy."""
    top = max(log_lik)
    if any(v != v for v in log_lik):
        top = math.nan
    a = c * np.exp(np.array([v - top for v in log_lik], dtype=float))
    s = float(a.sum())
    return a / s, float(top) + math.log(s)


def speed_log_lik(speed: float, motion: str) -> float:
    """log of the speed envelope's factor in a model's likelihood: 0 within ``MAX_SPEED[motion]``, -e^2 / (2
    SPEED_TOL^2) for a speed e beyond it (module docstring)."""
    e = speed - MAX_SPEED[motion]
    return 0.0 if e <= 0.0 else -0.5 * (e / SPEED_TOL) ** 2


def gaussian_log_lik(nis: float, log_det: float, dof: int) -> float:
    """log N(y; 0, S) from its NIS y^T S^-1 y, log |S| and the dimension of y (both forms of fullperc, Step.log_lik)."""
    return -0.5 * (nis + log_det + dof * _LOG_2PI)


def hop_mixture(log_lik: float, hop_log_lik: float) -> float:
    """log((1 - HOP_PRIOR) L + HOP_PRIOR L_hop): the likelihood of a flagged hop under a model that puts hops into the
    bias, ``log_lik`` with the update's S, ``hop_log_lik`` with the S the hop rule raised (module docstring)."""
    a, b = math.log1p(-HOP_PRIOR) + log_lik, math.log(HOP_PRIOR) + hop_log_lik
    top = max(a, b)
    return top + math.log(math.exp(a - top) + math.exp(b - top))
