"""The OMC position bias's length and std over distance from raw sensor data: ``FullpercParams.bias_length`` and
``bias_field_std`` (issue 41 item 1).

``fullperc`` learns the OMC's position bias b against the local chain while the Vega sees the target, and, once the
Vega has lost it, lets b decay as a first-order Gauss-Markov process in the distance d from where it was last seen
(:mod:`fullperc_fusion.filters.fullperc_reference`). The length and std of that process are what this module fits.
What b learns is the difference of the two devices, so that is what is measured, and only that:

    e = p_omc - p_local     (both in ``base``: the OMC by T_omc_base, the Vega's target by the static local chain)

at every Vega sample of the target with OMC samples on both sides within :data:`MAX_BRACKET_S` (the OMC position
linearly interpolated to the Vega's stamp: the two devices do not share frames, and at 0.1 m/s a nearest neighbour
4 ms away would add 0.4 mm of motion). No truth (the arm's joint states, /sim/truth) and no filter output is read.
Its empirical semivariogram over the distance h between the local chain's positions of two samples of one bag,

    gamma(h) = 1/2 E[(e_i - e_j)^2]   (per axis; pairs binned by h = |x_i - x_j|),

is fitted as nugget + s_f^2 (1 - exp(-h / L)): the nugget is what differs from sample to sample at the same place
(both devices' white noise, the OMC's camera-set changes over time), s_f^2 and L the part b can carry from one place
to another -- exactly the model b(d') = exp(-(d' - d) / L) b(d) + w, Var(w) = s_f^2 (1 - exp(-2 (d' - d) / L)),
whose semivariogram is s_f^2 (1 - exp(-h / L)).

Why distance between positions, not time or path length: the OMC's error in the twin is a function of where the
body is (distortion, camera coverage), and b is applied where the tool is, not when. Pairs at any time apart in the
same bag count (a place revisited later says how well b learnt there holds); pairs of different bags do not (each bag
has its own link calibration, whose error is part of e).

Pure functions on arrays; ``fit_noise_model`` (:mod:`.sensor_stats`, which reads the bags' raw samples) prints the
fit per directory and writes it into a noise-model file::

    fit_noise_model bags/spec bags/paper
"""

from __future__ import annotations

import numpy as np

__all__ = ["LENGTH_GRID", "MAX_BRACKET_S", "VARIOGRAM_BINS", "differences", "fit_semivariogram", "semivariogram"]

# an OTS sample counts when OMC samples on either side of it are at most this far apart (two OMC frames at 120 Hz
# plus jitter): a longer OMC gap (the OMC lost the target) is not interpolated across
MAX_BRACKET_S = 0.02
# distance bins [m]: from the white level (millimetres) to beyond the Vega's volume along a task's path
VARIOGRAM_BINS = (0.0, 0.0025, 0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.75, 1.0)
MIN_PAIRS = 200   # a bin with fewer pairs is not fitted
# the lengths the fit tries [m]; a fitted length at the upper end means no level-off within the data's distances
LENGTH_GRID = (0.005, 5.0)


def differences(samples: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps [s], e (n x 3) [m], local chain position x (n x 3) [m]) of one bag's
    ``sensor_stats.bag_samples``: e = OMC - local chain at each Vega sample bracketed by OMC samples
    (module docstring)."""
    omc = [(t, T[:3, 3]) for dev, t, _, T in samples if dev == "omc"]
    ots = [(t, T[:3, 3]) for dev, t, _, T in samples if dev == "ots"]
    if len(omc) < 2 or not ots:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    to = np.array([t for t, _ in omc], dtype=np.int64)
    order = np.argsort(to, kind="stable")
    to, po = to[order], np.array([p for _, p in omc])[order]
    tl = np.array([t for t, _ in ots], dtype=np.int64)
    xl = np.array([p for _, p in ots])
    k = np.searchsorted(to, tl, side="right")          # to[k - 1] <= tl < to[k]
    ok = (k > 0) & (k < len(to))
    k = np.clip(k, 1, len(to) - 1)
    t0, t1 = to[k - 1], to[k]
    ok &= (t1 - t0) <= MAX_BRACKET_S * 1e9
    a = np.where(t1 > t0, (tl - t0) / np.maximum(t1 - t0, 1), 0.0)[:, None]
    p = (1.0 - a) * po[k - 1] + a * po[k]
    return tl[ok] * 1e-9, (p - xl)[ok], xl[ok]


def semivariogram(parts: list[tuple[np.ndarray, np.ndarray]], bins=VARIOGRAM_BINS, stride: int = 1
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean distance [m], gamma [m^2] per axis, number of pairs) per distance bin (empty bins left out) over every
    pair of samples (each ``stride``-th) within each part: ``parts`` is one (e, x) per bag (module docstring)."""
    bins = np.asarray(bins, dtype=float)
    nb = len(bins) - 1
    sq, dist, cnt = np.zeros(nb), np.zeros(nb), np.zeros(nb)
    for e, x in parts:
        e, x = np.asarray(e)[::stride], np.asarray(x)[::stride]
        for i0 in range(0, len(e) - 1, 512):            # rows in blocks: all pairs without n^2 memory
            i = np.arange(i0, min(i0 + 512, len(e) - 1))
            ii, jj = np.nonzero(np.arange(len(e))[None, :] > i[:, None])
            ii = i[ii]
            d = np.linalg.norm(x[ii] - x[jj], axis=1)
            b = np.digitize(d, bins) - 1
            ok = (b >= 0) & (b < nb)
            np.add.at(sq, b[ok], 0.5 * ((e[ii] - e[jj]) ** 2).mean(1)[ok])
            np.add.at(dist, b[ok], d[ok])
            np.add.at(cnt, b[ok], 1)
    has = cnt > 0
    return dist[has] / cnt[has], sq[has] / cnt[has], cnt[has]


def fit_semivariogram(h: np.ndarray, gamma: np.ndarray, count: np.ndarray, grid: tuple[float, float] = LENGTH_GRID,
                      min_pairs: int = MIN_PAIRS) -> tuple[float, float, float]:
    """(nugget std, s_f, L [m]) of gamma(h) = nugget^2 + s_f^2 (1 - exp(-h / L)) fitted to the bins with at least
    ``min_pairs`` pairs: a grid over L within ``grid`` (log-spaced), non-negative least squares for the two variances
    at each L, residuals relative to gamma (the bins span two orders of magnitude) weighted by sqrt(pairs). An L at
    the grid's end means the data show no level-off within their range (report it, do not trust it)."""
    from scipy.optimize import nnls

    use = np.asarray(count) >= min_pairs
    h, g, w = np.asarray(h)[use], np.asarray(gamma)[use], np.sqrt(np.asarray(count)[use])
    if len(h) < 3:
        raise ValueError(f"{len(h)} distance bins with >= {min_pairs} pairs: too few to fit")
    best = (np.inf, 0.0, 0.0, 0.0)
    for L in np.geomspace(grid[0], grid[1], 600):
        A = np.column_stack([np.ones_like(h), 1.0 - np.exp(-h / L)]) * (w / g)[:, None]
        coef, _ = nnls(A, w)
        res = float(np.sum((A @ coef - w) ** 2))
        if res < best[0]:
            best = (res, float(np.sqrt(coef[0])), float(np.sqrt(coef[1])), float(L))
    return best[1], best[2], best[3]
