"""Our ``kf`` against filterpy's KalmanFilter, the reference most Python users know (issue 18 item 3).

filterpy (R. Labbe, "Kalman and Bayesian Filters in Python") is an independent implementation of the textbook
filter: ``predict(F, Q)`` gives x' = F x, P' = F P F^T + Q and ``update(z, R, H)`` the gain K = P' H^T S^-1 and
the Joseph-form covariance (I - K H) P' (I - K H)^T + K R K^T -- the same equations as paper_family.py eq. (9)-(13) for
the kind without bias and shrinkage. Fed the same F, Q, H (lag row included) and R from paper_family.py's own
functions, filterpy must give the same state and covariance at every step as

* ``FusionFilter("kf")`` -- the general form, and
* ``make_filter("kf")`` -- what the node and the evaluator run (paper_fast's closed form per axis),

over long random streams: global only, local only, pairs with either sample older (the lag row), device
covariances (isotropic, anisotropic, correlated), and gaps beyond ``max_gap_s`` (which re-initialise p and v from
the next sample: filterpy has no such rule, so the reference re-creates its state there exactly as the docstring of
paper_family.py says). Tolerance 1e-12 absolute in SI units (m, m/s) and of the largest entry of P.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.paper_family import (
    FilterParams,
    FusionFilter,
    measurement_matrix,
    process_noise,
    transition,
)
from fullperc_fusion.filters.registry import make_filter

S = 1_000_000_000
TOL = 1e-12


def _cov(rng, mode: str) -> np.ndarray | None:
    if mode == "none" or rng.random() < 0.5:
        return None
    C = np.eye(6) * 1e-4
    if mode == "iso":
        C[0:3, 0:3] = rng.uniform(1e-8, 1e-6) * np.eye(3)
    elif mode == "diag":
        C[0:3, 0:3] = np.diag(rng.uniform(1e-8, 1e-6, 3))
    else:
        A = rng.normal(size=(3, 3)) * 3e-4
        C[0:3, 0:3] = A @ A.T + 1e-8 * np.eye(3)
    return C


def _stream(seed: int, n: int, cov_mode: str) -> list[list[Measurement]]:
    """Items of one or two measurements; the newer stamp is the item's stamp, the older one lags by < 4 ms."""
    rng = np.random.default_rng(seed)
    t, items = S, []
    for k in range(n):
        t += int(rng.integers(2_000_000, 12_000_000)) + (S if rng.random() < 0.005 else 0)
        p = np.array([0.4 + 0.08 * np.sin(k / 90), -0.1 + 0.05 * np.cos(k / 60), 0.9 + 0.03 * np.sin(k / 25)])
        mode = int(rng.integers(3))   # 0 global, 1 local, 2 pair
        older = int(rng.integers(2))
        ms = []
        if mode != 1:
            lag = int(rng.integers(0, 4_000_000)) if mode == 2 and older == 0 else 0
            ms.append(Measurement(t - lag, SOURCE_GLOBAL, p + [2e-3, -1e-3, 1e-3] + rng.normal(0, 3e-4, 3),
                                  cov=_cov(rng, cov_mode)))
        if mode != 0:
            lag = int(rng.integers(0, 4_000_000)) if mode == 2 and older == 1 else 0
            ms.append(Measurement(t - lag, SOURCE_LOCAL, p + rng.normal(0, 1.5e-4, 3), cov=_cov(rng, cov_mode)))
        items.append(ms)
    return items


class FilterpyKF:
    """filterpy's KalmanFilter driven with paper_family.py's F, Q, H and R, plus the one rule it lacks (re-initialise
    p, v from the next sample before the first sample and after a gap longer than max_gap_s)."""

    def __init__(self, params: FilterParams) -> None:
        self.pr = params
        self.kf = KalmanFilter(dim_x=6, dim_z=3)
        self.t: int | None = None

    def step(self, ms: list[Measurement]) -> tuple[np.ndarray, np.ndarray]:
        pr = self.pr
        t = max(m.t_ns for m in ms)
        if self.t is None or (t - self.t) * 1e-9 > pr.max_gap_s:
            mg = next((m for m in ms if m.source == SOURCE_GLOBAL), None)
            ml = next((m for m in ms if m.source == SOURCE_LOCAL), None)
            self.kf.x = np.concatenate([(ml or mg).p, np.zeros(3)]).reshape(6, 1)
            self.kf.P = np.diag([pr.init_pos_std**2] * 3 + [pr.init_vel_std**2] * 3)
            self.t = t
            return self.kf.x.ravel().copy(), self.kf.P.copy()
        dt = (t - self.t) * 1e-9
        self.kf.predict(F=transition(dt, False), Q=process_noise(dt, pr.accel_noise, pr.bias_walk, False))
        H = np.vstack([measurement_matrix(m.source, False, (t - m.t_ns) * 1e-9) for m in ms])
        R = np.zeros((3 * len(ms), 3 * len(ms)))
        for i, m in enumerate(ms):
            std = pr.global_std if m.source == SOURCE_GLOBAL else pr.local_std
            R[3 * i:3 * i + 3, 3 * i:3 * i + 3] = std**2 * np.eye(3) if m.cov is None else m.cov[0:3, 0:3]
        self.kf.dim_z = 3 * len(ms)
        self.kf.update(np.concatenate([m.p for m in ms]).reshape(-1, 1), R=R, H=H)
        self.t = t
        return self.kf.x.ravel().copy(), self.kf.P.copy()


@pytest.fixture(scope="module")
def filterpy_run():
    """(items, filterpy's (x, P) after each item) per covariance mode, made once per module: both of our forms
    (general, registry) are compared step by step with the same reference run (filterpy's state depends only on the
    items, which are read-only here: a filter that changed one in place would raise, not alter the other's input)."""
    runs: dict[str, tuple] = {}

    def get(cov_mode: str):
        if cov_mode not in runs:
            items = _stream(7 + len(cov_mode), 3000, cov_mode)
            for m in (m for ms in items for m in ms):
                for a in (m.p, m.cov):
                    if a is not None:
                        a.flags.writeable = False
            ref = FilterpyKF(FilterParams())
            runs[cov_mode] = items, [ref.step(ms) for ms in items]
        return runs[cov_mode]
    return get


@pytest.mark.parametrize("cov_mode", ["none", "iso", "diag", "correlated"])
@pytest.mark.parametrize("which", ["general", "registry"])
def test_kf_matches_filterpy(which: str, cov_mode: str, filterpy_run) -> None:
    params = FilterParams()
    ours = FusionFilter("kf", params) if which == "general" else make_filter("kf", params)
    items, reference = filterpy_run(cov_mode)
    resets = 0
    for k, (ms, (x, P)) in enumerate(zip(items, reference, strict=True)):
        ours.predict(max(m.t_ns for m in ms))
        st = ours.update(*ms)
        resets += st.reset
        assert np.max(np.abs(st.p - x[0:3])) <= TOL, f"step {k}: position differs"
        assert np.max(np.abs(st.v - x[3:6])) <= TOL, f"step {k}: velocity differs"
        assert np.max(np.abs(st.P - P)) <= TOL * np.max(np.abs(P)), f"step {k}: covariance differs"
    assert resets >= 3, "the stream must exercise the gap rule"


def test_reference_is_sensitive() -> None:
    """The comparison can fail: the same filterpy run with a 10 % larger local noise is far off in P."""
    params = FilterParams()
    wrong = FilterParams(local_std=params.local_std * 1.1)
    ours, ref = make_filter("kf", params), FilterpyKF(wrong)
    worst = 0.0
    for ms in _stream(3, 300, "none"):
        ours.predict(max(m.t_ns for m in ms))
        st = ours.update(*ms)
        _, P = ref.step(ms)
        worst = max(worst, float(np.max(np.abs(st.P - P)) / np.max(np.abs(P))))
    assert worst > 1e-3
