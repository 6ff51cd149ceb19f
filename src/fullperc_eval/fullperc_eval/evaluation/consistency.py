"""Covariance consistency of a method's output: the NEES and the share inside the chi2 95 % bound.

A filter that reports a covariance promises how wrong it may be. The normalised estimation error squared,

    NEES_k = delta_k^T C_k^-1 delta_k      (delta_k: the true error of output k, C_k: its reported covariance),

is chi2-distributed with ``dof`` degrees of freedom when the promise holds (errors zero-mean Gaussian with
covariance C_k). Two figures per method (issue 18 "NEES consistent"):

* ``share_95``: the fraction of outputs with NEES <= chi2_dof^-1(0.95) -- 0.95 for an honest covariance, far less
  for an over-confident one (the OMC pass-through reports 0.3 mm while its error is millimetres);
* ``mean``: the mean NEES -- ``dof`` for an honest covariance, above for over-, below for under-confidence.

Position NEES uses the position block (dof 3) of every method's 6x6 output covariance; the full-pose NEES (dof 6)
only the outputs whose rotation block is the method's own estimate (:data:`FUSED_ORIENTATION`), not a fixed
``orientation_std`` attached to a copied source orientation, which would say nothing about the method.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import gammaincinv  # chi2.ppf's own formula: scipy.stats costs every evaluate process ~0.6 s

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL

CONFIDENCE = 0.95
# FusedOutput.orientation_source with both bits set: the filter fused the orientation itself (fullperc); one bit:
# the orientation of that source copied, its rotation covariance a fixed figure (the paper's filters, omc).
FUSED_ORIENTATION = SOURCE_GLOBAL | SOURCE_LOCAL


def bound(dof: int, confidence: float = CONFIDENCE) -> float:
    """The chi2 quantile a consistent NEES of ``dof`` degrees of freedom stays below with ``confidence``."""
    return float(2.0 * gammaincinv(dof / 2, confidence))   # = scipy.stats.chi2.ppf(confidence, dof), bit for bit


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """NEES of (N, d) errors with (N, d, d) covariances; NaN where either is non-finite or C is not positive
    definite (a covariance that cannot be inverted promises nothing that could be checked)."""
    e = np.asarray(err, dtype=float)
    C = np.asarray(cov, dtype=float)
    if e.ndim != 2 or C.shape != (*e.shape, e.shape[1]):
        raise ValueError(f"nees: errors (N, d) and covariances (N, d, d) expected, got {e.shape} and {C.shape}")
    out = np.full(len(e), np.nan)
    idx = np.flatnonzero(np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(C), axis=(1, 2)))
    if idx.size == 0:
        return out
    S = 0.5 * (C[idx] + np.swapaxes(C[idx], 1, 2))
    try:
        L = np.linalg.cholesky(S)          # the whole batch at once (the usual case: every C positive definite)
    except np.linalg.LinAlgError:
        keep = []
        for k in range(len(idx)):          # one bad covariance must not spoil the batch
            try:
                np.linalg.cholesky(S[k])
                keep.append(k)
            except np.linalg.LinAlgError:
                pass
        idx, S = idx[keep], S[keep]
        if idx.size == 0:
            return out
        L = np.linalg.cholesky(S)
    y = np.linalg.solve(L, e[idx][..., None])[..., 0]
    out[idx] = np.einsum("ni,ni->n", y, y)
    return out


def summary(values: np.ndarray, dof: int) -> dict[str, Any]:
    """``n``, ``mean``, ``median``, ``share_95`` and the ``bound`` of the finite NEES values (None when none)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    b = bound(dof)
    if v.size == 0:
        return {"dof": dof, "n": 0, "mean": None, "median": None, "share_95": None, "bound": b}
    return {"dof": dof, "n": int(v.size), "mean": float(v.mean()), "median": float(np.median(v)),
            "share_95": float(np.mean(v <= b)), "bound": b}
