"""Time offset (and drift) between two trackers' stamps from a recording of one moving target (ROS-free core).

Why: fusion pairs an OMC sample with the Vega sample of the same instant by their ``header.stamp``. A stamp that is
late by a few milliseconds (a latency the driver does not subtract, a mis-set ``device_latency_s``) is a position
error of speed x offset on every moving sample -- 1 mm at 0.2 m/s and 5 ms -- that no filter can tell from a tracker
error. This module measures the offset from data both trackers already give.

How: the two devices see the target in different frames (``omc``, ``ots``) and the link between them may not be
calibrated yet, but the **speed** of a rigid body's point is the same in every frame (rotations and translations
of the world frame do not change it), and so is its **angular speed**. So each device's pose series becomes a
scalar motion signal -- speed [m/s] (``signal="speed"``), angular speed [rad/s] (``"angular"``: also independent
of where each device puts the body's origin, which the linear speed is not once the body rotates), or both --
differentiated with a zero-phase Savitzky-Golay filter of the same length in seconds on each device (a symmetric
filter delays neither), per gap-free segment. Then

1. coarse: the normalised cross-correlation of the two signals on a common 1 ms grid over lags in
   ``[-max_lag_s, max_lag_s]`` (gaps masked), its peak refined by a parabola through the three samples around it;
2. fine: a least-squares fit of the offset ``d`` in  ``s_ots(u) = g * s_omc(u - d) + c``  -- the reference OMC
   signal interpolated by a cubic spline at each Vega stamp ``u`` shifted by ``d``, the gain ``g`` and bias ``c``
   solved linearly for every ``d`` (they absorb the two filters' different noise floors and bandwidths), ``d``
   by a bounded scalar search around the coarse value. Sub-sample precision: the spline is continuous in ``d``;
3. windows: the same fine fit on consecutive non-overlapping windows of ``window_s`` with enough motion gives
   one offset per window; their scatter (standard error of the mean) or the fit's own standard error, whichever
   is larger, is the offset's uncertainty, a straight line through them the drift between the two stamp clocks.

Sign convention (pinned by ``test_time_align.py``): ``offset_s = d > 0`` means **the OTS (Vega) stamps are late
by d seconds relative to the OMC's**: the Vega stamps an instant ``d`` later than the OMC stamps the same
instant. It is corrected by subtracting ``d`` from the Vega's stamps: ``ndi_driver``'s ``device_latency_s``
(which the driver subtracts from every stamp) becomes ``current + d``: the ``time_align`` tool writes that
(``fullperc_eval.evaluation.time_align_cli``); fusion_node watches the same estimate live (``fusion_health``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize_scalar

SIGNALS = ("speed", "angular", "both")
COARSE_STEP_S = 0.001          # grid of the cross-correlation [s]
MIN_OVERLAP_S = 2.0            # least time both devices' signals must overlap [s]


class AlignmentError(ValueError):
    """The recording cannot give an offset (too little overlap or motion, no clear correlation peak)."""


@dataclass
class Motion:
    """A device's motion signal: per gap-free segment, stamps [s] and signal values (n, channels)."""

    segments: list[tuple[np.ndarray, np.ndarray]]

    @property
    def samples(self) -> int:
        return sum(len(t) for t, _ in self.segments)

    @property
    def channels(self) -> int:
        return self.segments[0][1].shape[1] if self.segments else 0


@dataclass
class Alignment:
    """The estimate. ``offset_s`` > 0: OTS stamps late relative to OMC by that much (see the module docstring)."""

    offset_s: float                 # at ``t_ref_s`` (the middle of the overlap), from the fit over all of it
    offset_sigma_s: float           # 1-sigma: the larger of window scatter / sqrt(n) and the fit's own error
    offset_sigma_windows_s: float   # scatter of the window offsets / sqrt(n) (NaN with fewer than 3 windows)
    offset_sigma_fit_s: float       # least-squares standard error, inflated for the filter's correlated residuals
    drift: float                    # d(offset)/dt [s/s] (NaN with fewer than 3 windows)
    drift_sigma: float
    t_ref_s: float                  # stamps in the caller's time base
    peak_corr: float                # normalised cross-correlation at the coarse peak (1 = identical shapes)
    gain: float                     # g of the fine fit (about 1 for speeds of the same point)
    windows: list[dict] = field(default_factory=list)   # t_s, offset_s, corr, samples of each window used
    samples: dict = field(default_factory=dict)         # samples of each device used
    signal: str = "speed"

    def as_dict(self) -> dict:
        return asdict(self)


# ------------------------------------------------------------------------------------------------- signals
def segments_of(t: np.ndarray, max_gap_s: float | None = None) -> list[slice]:
    """Slices of ``t`` (increasing) without a gap longer than ``max_gap_s`` (default 2.5 x the median step)."""
    t = np.asarray(t, float)
    if len(t) < 2:
        return [slice(0, len(t))] if len(t) else []
    dt = np.diff(t)
    gap = 2.5 * float(np.median(dt)) if max_gap_s is None else float(max_gap_s)
    cuts = np.flatnonzero(dt > gap) + 1
    edges = [0, *cuts.tolist(), len(t)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def _rotmats(q_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = (np.asarray(q_xyzw, float) / np.linalg.norm(q_xyzw, axis=1, keepdims=True)).T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1)


def savgol_slope(x: np.ndarray, n: int, delta: float) -> np.ndarray:
    """The first derivative of a quadratic Savitzky-Golay filter of odd length ``n`` along axis 0, at the samples
    whose whole window lies inside ``x`` (``len(x) - n + 1`` rows: the ``h = n // 2`` at each end are left out).

    There a window is symmetric, so the quadratic's even term does not move its slope at the centre: the slope is
    the least-squares line's, sum_k k x[i + k] / (delta sum_k k^2), k = -h..h -- what ``scipy.signal.savgol_filter(x,
    n, 2, deriv=1, delta=delta, axis=0)`` gives there, to rounding (``test_time_offset_kernels.py``). Written out
    because scipy.signal's import (with scipy.stats: ~0.35 s of CPU, 1 s cold) would be most of fusion_node's start.
    """
    h = n // 2
    k = np.arange(-h, h + 1, dtype=float)
    c = k / (delta * float(k @ k))
    return np.lib.stride_tricks.sliding_window_view(x, n, axis=0) @ c


def xcorr_full(g: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The full cross-correlation of two real 1-D series by FFT: entry ``len(f) - 1 + lag`` is sum_i f[i - lag]
    g[i] (``scipy.signal.correlate(g, f, mode="full", method="fft")``, to rounding)."""
    m = len(g) + len(f) - 1
    nf = sfft.next_fast_len(m, real=True)
    return sfft.irfft(sfft.rfft(g, nf) * sfft.rfft(f[::-1], nf), nf)[:m]


def motion_signal(t_s: np.ndarray, p: np.ndarray, q_xyzw: np.ndarray | None = None, signal: str = "speed",
                  smooth_s: float = 0.1, max_gap_s: float | None = None) -> Motion:
    """Speed |dp/dt| [m/s] and/or angular speed |omega| [rad/s] of a pose series, per gap-free segment.

    The derivative is a Savitzky-Golay filter (quadratic, first derivative) over ``smooth_s`` seconds of the
    segment's own sampling, so two devices with different rates get the same smoothing in time; it is symmetric,
    so it shifts neither signal. The angular speed is ||dR/dt||_F / sqrt(2) (dR/dt = [omega]x R), which a constant
    rotation on either side does not change: neither the world frame nor the body's origin matter. Only samples
    with the whole filter window inside their segment are kept (half a window is cut at each end of a segment:
    a one-sided derivative would shift the signal of the device that loses the target more often). Non-finite
    samples are removed first (a tracker that lost the target).
    """
    if signal not in SIGNALS:
        raise ValueError(f"signal must be one of {', '.join(SIGNALS)}, got {signal!r}")
    t_s = np.asarray(t_s, float)
    p = np.asarray(p, float).reshape(len(t_s), 3)
    ok = np.isfinite(t_s) & np.isfinite(p).all(axis=1)
    R = None
    if signal != "speed":
        if q_xyzw is None:
            raise ValueError(f"signal {signal!r} needs orientations")
        q = np.asarray(q_xyzw, float).reshape(len(t_s), 4)
        ok &= np.isfinite(q).all(axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
        R = _rotmats(np.where(ok[:, None], q, [0.0, 0.0, 0.0, 1.0]))
    order = np.argsort(t_s[ok], kind="stable")
    t, p = t_s[ok][order], p[ok][order]
    R = None if R is None else R[ok][order]
    out = []
    for s in segments_of(t, max_gap_s):
        ts = t[s]
        if len(ts) < 5:
            continue
        dt = float(np.median(np.diff(ts)))
        n = int(round(smooth_s / dt)) // 2 * 2 + 1
        n = max(n, 5)
        if len(ts) < n + 4:
            continue
        # only where the whole window is inside the segment: at its ends the filter is one-sided, and a one-sided
        # derivative lags or leads -- the device that loses the target more often would look shifted
        cols = []
        if signal in ("speed", "both"):
            cols.append(np.linalg.norm(savgol_slope(p[s], n, dt), axis=1))
        if signal in ("angular", "both"):
            dR = savgol_slope(R[s], n, dt)
            cols.append(np.linalg.norm(dR, axis=1) / np.sqrt(2.0))
        h = n // 2
        out.append((ts[h:len(ts) - h], np.stack(cols, axis=1)))
    return Motion(out)


# ----------------------------------------------------------------------------------------------- alignment
def _on_grid(m: Motion, grid: np.ndarray) -> np.ndarray:
    """The signal linearly interpolated on ``grid`` (NaN outside every segment)."""
    out = np.full((len(grid), m.channels), np.nan)
    for ts, v in m.segments:
        k = (grid >= ts[0]) & (grid <= ts[-1])
        for c in range(v.shape[1]):
            out[k, c] = np.interp(grid[k], ts, v[:, c])
    return out


def _masked_ncc(a: np.ndarray, b: np.ndarray, lags: np.ndarray, min_overlap: int) -> np.ndarray:
    """Mean over channels of the Pearson correlation of b[i] with a[i - lag] over the samples valid in both.

    Every sum the correlation needs (pairs, sums, sums of squares and products over the valid pairs) is a
    cross-correlation of the zero-filled signals and their masks, so all lags come from a few FFTs.
    """
    n = len(a)
    ma = np.isfinite(a).all(axis=1).astype(float)
    mb = np.isfinite(b).all(axis=1).astype(float)
    idx = n - 1 + lags

    def xc(f: np.ndarray, g: np.ndarray) -> np.ndarray:     # sum_i f[i - lag] g[i] at each lag
        return xcorr_full(g, f)[idx]

    pairs = np.rint(xc(ma, mb))
    r = np.zeros(len(lags))
    for c in range(a.shape[1]):
        x, y = np.where(ma > 0, a[:, c], 0.0), np.where(mb > 0, b[:, c], 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            sx, sy = xc(x, mb), xc(ma, y)
            cov = xc(x, y) - sx * sy / pairs
            vx, vy = xc(x * x, mb) - sx * sx / pairs, xc(ma, y * y) - sy * sy / pairs
            r += cov / np.sqrt(np.clip(vx, 0, None) * np.clip(vy, 0, None))
    r /= a.shape[1]
    r[(pairs < min_overlap) | ~np.isfinite(r)] = np.nan
    return r


class _Fine:
    """Least-squares residual of ``s_ots(u) = g s_omc(u - d) + c`` (per channel) as a function of ``d``."""

    def __init__(self, ref: Motion, other: Motion, d0: float, reach_s: float) -> None:
        self.splines = [(ts[0], ts[-1], CubicSpline(ts, v, axis=0)) for ts, v in ref.segments]
        u = np.concatenate([ts for ts, _ in other.segments]) if other.segments else np.zeros(0)
        y = np.concatenate([v for _, v in other.segments]) if other.segments else np.zeros((0, 1))
        # the samples whose shifted stamp stays inside one reference segment over the whole search: a fixed set,
        # so the residual is continuous in d
        seg = np.full(len(u), -1)
        for i, (a, b, _) in enumerate(self.splines):
            seg[(u - d0 - reach_s >= a) & (u - d0 + reach_s <= b)] = i
        keep = seg >= 0
        self.u, self.y, self.seg = u[keep], y[keep], seg[keep]
        self.scale = np.where(self.y.std(axis=0) > 0, self.y.std(axis=0), 1.0) if len(self.y) else np.ones(1)

    def __len__(self) -> int:
        return len(self.u)

    def trim(self, d: float, pad_s: float, k: float = 4.0) -> int:
        """Drop the samples whose residual at ``d`` exceeds ``k`` robust sigmas, and those within ``pad_s`` of
        them; returns how many were dropped.

        Why: a tracker's pose hops (the OMC's, when the set of cameras that see a marker changes) are a step in
        position, so a bump of the filter's length in its speed; least squares would pull the offset toward
        whichever side of the bump the motion makes cheaper. Trimmed and refitted, they no longer count.
        """
        _, _, res = self.solve(d)
        z = np.abs(res) / np.maximum(1.4826 * np.median(np.abs(res), axis=0), 1e-12)
        bad = self.u[(z > k).any(axis=1)]
        if not len(bad):
            return 0
        j = np.searchsorted(bad, self.u)
        near = np.minimum(np.abs(self.u - bad[np.clip(j, 0, len(bad) - 1)]),
                          np.abs(self.u - bad[np.clip(j - 1, 0, len(bad) - 1)])) <= pad_s
        self.u, self.y, self.seg = self.u[~near], self.y[~near], self.seg[~near]
        return int(near.sum())

    def robust_fit(self, d0: float, reach_s: float, pad_s: float, rounds: int = 2) -> float:
        """:meth:`fit`, then :meth:`trim` and fit again, ``rounds`` times (or until nothing is trimmed)."""
        d = self.fit(d0, reach_s)
        for _ in range(rounds):
            if not self.trim(d, pad_s) or len(self.u) < 20:
                break
            d = self.fit(d0, reach_s)
        return d

    def ref_at(self, d: float, deriv: int = 0) -> np.ndarray:
        x = np.empty_like(self.y)
        for i, (_, _, sp) in enumerate(self.splines):
            k = self.seg == i
            if k.any():
                x[k] = sp(self.u[k] - d, deriv)
        return x

    def solve(self, d: float) -> tuple[float, np.ndarray, np.ndarray]:
        """(normalised residual sum of squares, gains, residuals) at offset ``d``."""
        x = self.ref_at(d)
        rss, gains, res = 0.0, np.empty(x.shape[1]), np.empty_like(x)
        for c in range(x.shape[1]):
            A = np.stack([x[:, c], np.ones(len(x))], axis=1)
            coef, *_ = np.linalg.lstsq(A, self.y[:, c], rcond=None)
            res[:, c] = self.y[:, c] - A @ coef
            gains[c] = coef[0]
            rss += float((res[:, c] ** 2).sum()) / self.scale[c] ** 2
        return rss, gains, res

    def fit(self, d0: float, reach_s: float) -> float:
        r = minimize_scalar(lambda d: self.solve(d)[0], bounds=(d0 - reach_s, d0 + reach_s), method="bounded",
                            options={"xatol": 1e-7})
        return float(r.x)

    def sigma(self, d: float, corr_samples: float) -> float:
        """Least-squares standard error of ``d``; the residuals of a smoothed signal are correlated over about
        ``corr_samples`` samples, which inflates it by sqrt(corr_samples)."""
        _, gains, res = self.solve(d)
        dx = self.ref_at(d, 1) * gains
        info = sum(float((dx[:, c] ** 2).sum()) / max(float(res[:, c].var()), 1e-30) for c in range(res.shape[1]))
        return float(np.sqrt(max(corr_samples, 1.0) / info)) if info > 0 else float("nan")


def _subset(m: Motion, a: float, b: float) -> Motion:
    out = []
    for ts, v in m.segments:
        k = (ts >= a) & (ts < b)
        if k.sum() >= 4:
            out.append((ts[k], v[k]))
    return Motion(out)


def estimate_offset(omc: Motion, ots: Motion, *, max_lag_s: float = 0.5, window_s: float = 2.0,
                    min_motion: float | None = None, smooth_s: float = 0.1, min_corr: float = 0.5,
                    signal: str = "speed") -> Alignment:
    """The offset of the OTS stamps relative to the OMC's (> 0: OTS late) from the two devices' motion signals.

    ``max_lag_s``: the search range of the coarse cross-correlation (a periodic motion correlates at multiples of
    its period too: wave the tool irregularly). ``window_s``: the length of the windows whose scatter gives the
    uncertainty and the drift; a window counts when its OTS signal varies by more than ``min_motion`` (standard
    deviation; default 0.02 m/s or 0.05 rad/s, the order of a still tool's noise) and it holds at least half a
    window of samples. ``smooth_s``: the derivative filter's length used for ``motion_signal`` (it sets how
    correlated the residuals are). AlignmentError when the overlap is too short or the peak is below ``min_corr``.
    """
    if not omc.segments or not ots.segments:
        raise AlignmentError(f"no motion signal from {'the OMC' if not omc.segments else 'the OTS'} "
                             "(too few consecutive samples of the target)")
    if min_motion is None:
        min_motion = 0.02 if signal == "speed" else 0.05
    t0 = max(omc.segments[0][0][0], ots.segments[0][0][0]) - max_lag_s
    t1 = min(omc.segments[-1][0][-1], ots.segments[-1][0][-1]) + max_lag_s
    if t1 - t0 < 2 * max_lag_s + MIN_OVERLAP_S:
        raise AlignmentError(f"the two devices' signals overlap for {max(t1 - t0 - 2 * max_lag_s, 0):.2f} s; "
                             "record at least a few seconds of motion seen by both")
    grid = np.arange(t0, t1, COARSE_STEP_S)
    a, b = _on_grid(omc, grid), _on_grid(ots, grid)
    nlag = int(round(max_lag_s / COARSE_STEP_S))
    lags = np.arange(-nlag, nlag + 1)
    ncc = _masked_ncc(a, b, lags, min_overlap=int(1.0 / COARSE_STEP_S))
    if not np.isfinite(ncc).any():
        raise AlignmentError("the two devices never see the target moving at the same time")
    j = int(np.nanargmax(ncc))
    peak = float(ncc[j])
    if peak < min_corr:
        raise AlignmentError(f"no clear correlation between the two devices' motion (peak {peak:.2f} < "
                             f"{min_corr}): do both see the same target moving?")
    d_coarse = float(lags[j]) * COARSE_STEP_S
    if 0 < j < len(lags) - 1 and np.isfinite(ncc[j - 1]) and np.isfinite(ncc[j + 1]):
        den = ncc[j - 1] - 2 * ncc[j] + ncc[j + 1]
        if den < 0:
            d_coarse += 0.5 * (ncc[j - 1] - ncc[j + 1]) / den * COARSE_STEP_S
    reach = 3 * COARSE_STEP_S
    fine = _Fine(omc, ots, d_coarse, reach)
    if len(fine) < 20:
        raise AlignmentError("too few OTS samples inside the OMC's gap-free segments")
    d = fine.robust_fit(d_coarse, reach, pad_s=0.5 * smooth_s)
    if abs(d - d_coarse) > 0.95 * reach:     # at the bound: the coarse peak was broad; search wider
        reach *= 4
        fine = _Fine(omc, ots, d_coarse, reach)
        d = fine.robust_fit(d_coarse, reach, pad_s=0.5 * smooth_s)
    _, gains, _ = fine.solve(d)
    dt_ots = float(np.median(np.concatenate([np.diff(ts) for ts, _ in ots.segments if len(ts) > 1])))
    sigma_fit = fine.sigma(d, smooth_s / dt_ots)

    # windows: one offset each, from the fit restricted to it
    ts_all = np.concatenate([ts for ts, _ in ots.segments])
    lo, hi = float(ts_all[0]), float(ts_all[-1])
    wins = []
    n_win = int((hi - lo) // window_s)
    rate = 1.0 / dt_ots
    for k in range(n_win):
        wa, wb = lo + k * window_s, lo + (k + 1) * window_s
        sub = _subset(ots, wa, wb)
        if sub.samples < 0.5 * window_s * rate:
            continue
        motion = float(np.concatenate([v for _, v in sub.segments]).std(axis=0).min())
        if motion < min_motion:
            continue
        fw = _Fine(omc, sub, d, reach)
        if len(fw) < 0.5 * window_s * rate:
            continue
        dw = fw.robust_fit(d, reach, pad_s=0.5 * smooth_s)
        x, y = fw.ref_at(dw), fw.y
        corr = float(np.mean([np.corrcoef(x[:, c], y[:, c])[0, 1] for c in range(y.shape[1])]))
        if not corr >= min_corr:
            continue
        wins.append({"t_s": 0.5 * (wa + wb), "offset_s": dw, "corr": corr, "samples": len(fw)})
    t_ref = 0.5 * (lo + hi)
    sig_w = drift = drift_sig = float("nan")
    if len(wins) >= 3:
        tw = np.array([w["t_s"] for w in wins]) - t_ref
        dw = np.array([w["offset_s"] for w in wins])
        sig_w = float(dw.std(ddof=1) / np.sqrt(len(dw)))
        A = np.stack([np.ones_like(tw), tw], axis=1)
        coef, *_ = np.linalg.lstsq(A, dw, rcond=None)
        drift = float(coef[1])
        dof = len(dw) - 2
        if dof > 0 and float((tw ** 2).sum()) > 0:
            s2 = float(((dw - A @ coef) ** 2).sum()) / dof
            drift_sig = float(np.sqrt(s2 / ((tw - tw.mean()) ** 2).sum()))
    # the larger of the two: a scatter of 3-5 windows can be small by chance, the fit's own error misses what
    # varies between windows (where the tool was, which OMC cameras saw it)
    sigma = max(sig_w, sigma_fit) if np.isfinite(sig_w) else sigma_fit
    return Alignment(offset_s=d, offset_sigma_s=float(sigma), offset_sigma_windows_s=sig_w,
                     offset_sigma_fit_s=sigma_fit, drift=drift, drift_sigma=drift_sig, t_ref_s=t_ref,
                     peak_corr=peak, gain=float(np.mean(gains)), windows=wins,
                     samples={"omc": omc.samples, "ots": len(fine)}, signal=signal)


def align_tracks(t_omc_s, p_omc, t_ots_s, p_ots, q_omc=None, q_ots=None, *, signal: str = "speed",
                 smooth_s: float = 0.1, **kw) -> Alignment:
    """:func:`estimate_offset` from the two devices' raw pose series (stamps [s] in one time base, positions [m]
    in each device's own frame, quaternions x y z w for the angular signal)."""
    a = motion_signal(t_omc_s, p_omc, q_omc, signal, smooth_s)
    b = motion_signal(t_ots_s, p_ots, q_ots, signal, smooth_s)
    return estimate_offset(a, b, smooth_s=smooth_s, signal=signal, **kw)


__all__ = ["Alignment", "AlignmentError", "Motion", "SIGNALS", "align_tracks", "estimate_offset", "motion_signal",
           "segments_of"]
