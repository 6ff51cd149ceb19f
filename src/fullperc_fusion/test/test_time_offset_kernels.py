"""time_offset's two signal kernels against the scipy.signal calls they stand in for (fusion_node does not import
scipy.signal: with scipy.stats it would be most of the node's start-up)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import correlate, savgol_filter

from fullperc_fusion.calibration.time_offset import savgol_slope, xcorr_full


@pytest.mark.parametrize("n", [5, 7, 25, 61])
def test_savgol_slope_is_scipys_quadratic_first_derivative_where_the_window_fits(n):
    x = np.random.default_rng(n).normal(size=(400, 9)).cumsum(axis=0)
    want = savgol_filter(x, n, 2, deriv=1, delta=0.004, axis=0)[n // 2:400 - n // 2]
    got = savgol_slope(x, n, 0.004)
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= 1e-11 * np.abs(want).max()   # measured <= 3.1e-13 (lstsq's rounding)


def test_savgol_slope_of_a_quadratic_is_its_exact_derivative():
    t = np.arange(50) * 0.01
    x = (3.0 * t**2 - 2.0 * t + 1.0)[:, None]
    assert np.allclose(savgol_slope(x, 7, 0.01)[:, 0], 6.0 * t[3:47] - 2.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("la, lb", [(100, 100), (1000, 997), (37, 5), (1, 1)])
def test_xcorr_full_is_scipys_full_correlation(la, lb):
    rng = np.random.default_rng(la + lb)
    g, f = rng.normal(size=la), rng.normal(size=lb)
    want = correlate(g, f, mode="full", method="fft")
    got = xcorr_full(g, f)
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    lag = 2 if la > 3 and lb > 3 else 0   # entry len(f) - 1 + lag = sum_i f[i - lag] g[i]
    direct = sum(f[i - lag] * g[i] for i in range(la) if 0 <= i - lag < lb)
    assert got[lb - 1 + lag] == pytest.approx(direct, abs=1e-12)
