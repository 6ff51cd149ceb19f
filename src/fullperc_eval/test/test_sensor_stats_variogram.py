"""bias_variogram (evaluation/bias_variogram.py): the semivariogram of the raw (OMC - local chain) position differences
over distance and its fit, which give ``FullpercParams.bias_length`` and ``bias_field_std``. On synthetic data of known
length and std, so the fit is shown to recover what it is meant to (test/test_model_constants.py holds the shipped
defaults to the fit on the committed bags)."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_eval.evaluation.bias_variogram import MAX_BRACKET_S, differences, fit_semivariogram, semivariogram


def _field(rng: np.random.Generator, n: int, length: float, std: float, nugget: float, size: float):
    """(e, x): n places in a cube of side ``size`` [m] -- n / 20 stations uniform in it, 20 places within ~2 mm of
    each (a tool held still, then moved on: the bags' close pairs, which show the nugget) -- and, per axis, a Gaussian
    field of covariance std^2 exp(-|x - x'| / length) (valid in 3-D) plus white noise of std ``nugget``: the model
    the fit assumes."""
    x = np.repeat(rng.uniform(0.0, size, (n // 20, 3)), 20, axis=0) + rng.normal(0.0, 2e-3, (n // 20 * 20, 3))
    n = len(x)
    C = std**2 * np.exp(-np.linalg.norm(x[:, None] - x[None], axis=2) / length)
    Lc = np.linalg.cholesky(C + 1e-18 * np.eye(n))
    return Lc @ rng.normal(size=(n, 3)) + rng.normal(0.0, nugget, (n, 3)), x


@pytest.mark.parametrize(("length", "std"), [(0.08, 0.3e-3), (0.25, 1.0e-3)])
def test_the_fit_recovers_a_known_length_and_std(length, std):
    """Twelve independent 'bags' of 500 places each: the fitted length, field std and nugget are the generating
    ones (to 25 %, 15 %, 25 %: the empirical semivariogram of a finite field scatters)."""
    rng = np.random.default_rng(4)
    parts = [_field(rng, 500, length, std, 0.05e-3, 1.0) for _ in range(12)]
    h, g, n = semivariogram(parts)
    assert np.all(np.diff(g[n >= 200]) > -0.15 * g[n >= 200][1:])   # rises (to its scatter) with distance
    nug, sf, L = fit_semivariogram(h, g, n)
    assert L == pytest.approx(length, rel=0.25)
    assert sf == pytest.approx(std, rel=0.15)
    assert nug == pytest.approx(0.05e-3, rel=0.25)


def test_semivariogram_counts_pairs_within_a_bag_only():
    """Two bags with different constant offsets: no pair spans them, so gamma is 0 (an offset between bags -- each
    bag's own link calibration -- is not a change over distance)."""
    x = np.linspace(0, 0.3, 50)[:, None] * [1.0, 0.0, 0.0]
    h, g, n = semivariogram([(np.full((50, 3), 1e-3), x), (np.full((50, 3), -1e-3), x + 0.01)])
    assert n.sum() == 2 * 50 * 49 / 2 - np.count_nonzero(np.linalg.norm(x[:, None] - x[None], axis=2) >= 1.0)
    np.testing.assert_array_equal(g, 0.0)


def test_differences_interpolate_the_omc_to_the_vega_stamp():
    """OMC at 120 Hz, the Vega at 40 Hz with stamps between OMC frames, both on a straight 0.1 m/s path, the OMC
    1 mm off in x: e is that offset exactly (the OMC linearly interpolated), x the local chain's position; a Vega
    sample in an OMC gap longer than MAX_BRACKET_S, or outside the OMC's span, is left out."""
    def T(p):
        M = np.eye(4)
        M[:3, 3] = p
        return M

    def path(t):
        return np.array([0.1 * t, 0.02, 0.5])

    samples = [("omc", int(k * 1e9 / 120), None, T(path(k / 120) + [1e-3, 0, 0])) for k in range(240)
               if not 120 <= k < 126]                      # a 58 ms OMC gap at 1.0-1.05 s
    samples += [("ots", int((k / 40 + 0.003) * 1e9), None, T(path(k / 40 + 0.003))) for k in range(81)]
    samples.sort(key=lambda s: s[1])
    t, e, x = differences(samples)
    assert len(t) == 81 - 2 - 1           # 1.003 s (OMC gap), 2.003 s (after the last OMC frame) left out
    assert 1.003 not in np.round(t, 6) and (MAX_BRACKET_S * 1e9) < 58e6
    np.testing.assert_allclose(e, np.tile([1e-3, 0, 0], (len(t), 1)), atol=1e-12)
    np.testing.assert_allclose(x, np.array([path(s) for s in t]), atol=1e-12)
