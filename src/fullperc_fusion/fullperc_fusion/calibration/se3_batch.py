"""Robust SE(3) means of many windows of one stream at once: :func:`.se3_stats.robust_se3_mean`'s results, stacked.

Why: the link monitor (:mod:`.monitor`) takes the robust mean of the last ``window_s`` of OTS base sightings every
half window -- in a 28 s bag ~50 means of ~60 matrices, each ~0.6 ms, nearly all of it numpy's and scipy's cost per
call on small arrays (some 150 calls per mean: residuals, medians, the medoid, the gates); they were about a tenth of
an offline evaluation. Offline every window is known before any mean is needed (the monitor decides when to evaluate
from stamps alone; :meth:`.monitor.LinkMonitor.defer`), so what does not depend on a window's inlier set runs once
over all windows of one size, stacked:

* once for the stream: the pose checks and the quaternions (:func:`.se3_stats.stack_and_quats`; the checks are per
  sample, and :func:`.so3_stack.quats` converts each matrix on its own, so a window's quaternions are rows of the
  stream's);
* stacked over the windows: the medoid's Gram matrices, angles and medians, the coordinate-wise medians, every
  round's residuals (one stacked matmul and rotation-vector conversion) and the MAD gate;
* one call per window, as robust_se3_mean makes it, whatever depends on the window's inlier set: the mean of the
  kept samples, the covariance of their residuals and the two Mahalanobis gates -- reductions whose summation order
  (numpy's, BLAS's) follows the subset's shape, so they stay the very calls on the very arrays.

Equality: each stacked operation is elementwise, a sort along one axis (each slice sorted by the same routine as the
single window's column), or numpy's matmul, which computes every matrix of a stack with the inner loop (and the BLAS
call) the single window's matmul uses for the same shapes and inner strides. So each window's mean, inlier set and
``LinkEstimate.T`` are robust_se3_mean's on that window, bit for bit (test_exact_fast_paths.py: random windows with
outliers, sizes past the medoid's cap, windows too inconsistent for a mean, and the monitor on long streams). A stream
that fails the pose checks, or a NaN in a median, goes window by window through robust_se3_mean itself.
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtri

from fullperc_common.transforms import T_to_pq, make_T
from fullperc_fusion.calibration.se3_stats import (
    GATE_FLOOR,
    CalibrationError,
    _mean_T_of,
    cov_rows,
    medoid_indices,
    medoid_medians,
    robust_se3_mean,
    sorted_middle,
    stack_and_quats,
)
from fullperc_fusion.calibration.so3_stack import rotvecs

__all__ = ["robust_se3_means", "robust_se3_means_of"]


class _NaN(Exception):
    """A median met a NaN (np.median's own path in robust_se3_mean): the windows go one by one."""


def robust_se3_means(Ts: np.ndarray, rows: np.ndarray, *, alpha: float = 1e-3,
                     max_iter: int = 50) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """For each row of ``rows`` (W, n) -- the indices of one window's samples in the stack ``Ts`` (M, 4, 4) --
    ``(est.T, est.inliers)`` of ``est = robust_se3_mean(Ts[row], alpha=alpha, max_iter=max_iter)``, or None where
    that raises :class:`~.se3_stats.CalibrationError` (module docstring)."""
    rows = np.asarray(rows, dtype=np.intp)
    if len(rows) == 0:
        return []
    rows = rows.reshape(len(rows), -1)
    if rows.shape[1] < 2:
        return [None] * len(rows)   # robust_se3_mean refuses fewer than 2 samples
    try:
        Ts, q_all = stack_and_quats(Ts)
        if q_all is not None:
            return _stacked(Ts, q_all, rows, alpha, max_iter)
    except (CalibrationError, _NaN):
        pass
    return [_one(Ts, r, alpha, max_iter) for r in rows]


def robust_se3_means_of(Ts: np.ndarray, windows: list[np.ndarray], *,
                        alpha: float = 1e-3) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """:func:`robust_se3_means` of windows of any sizes (``windows``: each an index array into ``Ts``), in their
    order: the windows of one size go through one stacked call."""
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(windows)
    by_n: dict[int, list[int]] = {}
    for i, w in enumerate(windows):
        by_n.setdefault(len(w), []).append(i)
    for ids in by_n.values():
        for i, m in zip(ids, robust_se3_means(Ts, np.stack([windows[i] for i in ids]), alpha=alpha), strict=True):
            out[i] = m
    return out


def _one(Ts, row: np.ndarray, alpha: float, max_iter: int) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        est = robust_se3_mean(np.asarray(Ts)[row], alpha=alpha, max_iter=max_iter)
    except CalibrationError:
        return None
    assert est.inliers is not None
    return est.T, est.inliers


def _median1(x: np.ndarray) -> np.ndarray:
    """``_median0`` of each window (axis 1 of a stacked array): the middle element of each sorted column, or the mean
    of the two middle ones."""
    s = np.sort(x, axis=1)
    if np.isnan(s[:, -1]).any():
        raise _NaN
    return sorted_middle(s, 1)


def _residuals(T_ref: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``se3_residuals(T_ref[w], S[w])`` of each window w, stacked (W, n, 6)."""
    dp = S[:, :, :3, 3] - T_ref[:, None, :3, 3]
    M = S[:, :, :3, :3] @ T_ref[:, None, :3, :3].swapaxes(-1, -2)
    dth = rotvecs(M.reshape(-1, 3, 3)).reshape(M.shape[:2] + (3,))
    return np.concatenate([dp, dth], axis=2)


def _stacked(Ts: np.ndarray, q_all: np.ndarray, rows: np.ndarray, alpha: float,
             max_iter: int) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """robust_se3_mean's steps on every window at once (its comments say what each step is)."""
    W, n = rows.shape
    q3 = chdtri(3, alpha)
    k1 = float(np.sqrt(chdtri(1, alpha)))
    S = Ts[rows]            # (W, n, 4, 4): each window's stack
    Q = q_all[rows]         # (W, n, 4): its quaternions
    # start: the medoid's rotation and the coordinate-wise median of the positions
    idx = medoid_indices(n)
    med_ang = medoid_medians(Q[:, idx])
    if med_ang is None:
        raise _NaN
    medoid = idx[np.argmin(med_ang, axis=1)]
    T0 = np.tile(np.eye(4), (W, 1, 1))          # make_T(p, R=R)
    T0[:, :3, :3] = S[np.arange(W), medoid, :3, :3]
    T0[:, :3, 3] = _median1(S[:, :, :3, 3])
    r = _residuals(T0, S)
    med = _median1(r)[:, None]
    floors = np.repeat(GATE_FLOOR, 3)
    floors2 = [f**2 * np.eye(3) for f in GATE_FLOOR]   # _block_d2's C + floor^2 I
    s = np.maximum(1.4826 * _median1(np.abs(r - med)), floors)
    masks = list(np.all(np.abs(r - med) <= k1 * s[:, None], axis=2))
    # rounds: the windows still iterating, together for the residuals, one by one for what depends on the mask
    means: list[np.ndarray | None] = [None] * W
    active = list(range(W))
    for _ in range(max_iter):
        active = [w for w in active if masks[w].sum() >= 2]
        if not active:
            break
        Tm = [_mean_T_of(S[w], Q[w], masks[w]) for w in active]
        R = _residuals(np.stack(Tm), S[active])
        # _block_d2's inverses, of every window's two blocks in one stacked call (LAPACK, matrix by matrix)
        C = np.stack([cov_rows(R[a][masks[w]]) for a, w in enumerate(active)])
        Ci = np.linalg.inv(np.concatenate([C[:, :3, :3] + floors2[0], C[:, 3:, 3:] + floors2[1]]))
        A = len(active)
        still = []
        for a, w in enumerate(active):
            r, mask = R[a], masks[w]
            rp, rr = r[:, :3], r[:, 3:]
            new = (np.einsum("ni,ij,nj->n", rp, Ci[a], rp) <= q3) & (np.einsum("ni,ij,nj->n", rr, Ci[A + a], rr) <= q3)
            if np.array_equal(new, mask):
                means[w] = Tm[a]   # converged
            else:
                masks[w] = new
                still.append(w)
        active = still
    out: list[tuple[np.ndarray, np.ndarray] | None] = []
    for w in range(W):
        if masks[w].sum() < 2:
            out.append(None)
            continue
        Tm_w = means[w] if means[w] is not None else _mean_T_of(S[w], Q[w], masks[w])
        out.append((make_T(*T_to_pq(Tm_w)), masks[w]))   # LinkEstimate.T: the mean through its stored (p, q)
    return out
