"""Pins the closed-form single-pose conversions (make_T, T_to_pq, R_to_quat) to scipy's Rotation.

They replaced scipy on the per-sample path (issue 16: ~a third of the fusion node's CPU per fused pose); they must
give scipy's results to rounding -- in practice bit for bit, as they use scipy's formulas and branch rules -- on
random rotations and on the edge cases of Shepperd's method (180 deg turns, ties between diagonal entries, w < 0).
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import R_to_quat, T_to_pq, make_T, quat_to_R_rows

TOL = 1e-12


def _scipy_T(p, q) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()
    T[:3, 3] = p
    return T


def _scipy_pq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return T[:3, 3].copy(), -q if q[3] < 0 else q


def _edge_quats() -> list[np.ndarray]:
    s = math.sqrt(0.5)
    qs = [[0, 0, 0, 1], [0, 0, 0, -1], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, -1, 0],   # 0 / 180 deg
          [s, s, 0, 0], [0, s, s, 0], [s, 0, s, 0], [0.5, 0.5, 0.5, 0.5], [0.5, -0.5, 0.5, -0.5],   # ties
          [s, 0, 0, s], [0, s, 0, -s], [0, 0, s, s], [1e-9, 0, 1, 1e-9], [0.3, -0.4, 0.5, -0.7]]
    return [np.asarray(q, dtype=float) for q in qs]


def test_make_T_equals_scipy_on_random_and_edge_quaternions():
    rng = np.random.default_rng(16)
    quats = [rng.normal(size=4) for _ in range(3000)] + _edge_quats()   # random scale: make_T normalises
    for q in quats:
        p = rng.normal(size=3)
        T = make_T(p, q)
        assert T.shape == (4, 4) and T.dtype == float
        assert np.max(np.abs(T - _scipy_T(p, q))) <= TOL, q
        assert np.array_equal(T[3], [0, 0, 0, 1])


def test_make_T_accepts_lists_and_keeps_scipy_errors():
    assert np.max(np.abs(make_T([1, 2, 3], [0, 0, 1, 1]) - _scipy_T([1, 2, 3], [0, 0, 1, 1]))) <= TOL
    with pytest.raises(ValueError):
        make_T([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError):
        make_T([0, 0, 0], [0, 0, 1])
    assert np.array_equal(make_T([1, 2, 3]), np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]]))


def test_T_to_pq_equals_scipy_with_w_nonnegative():
    rng = np.random.default_rng(17)
    Ts = [_scipy_T(rng.normal(size=3), rng.normal(size=4)) for _ in range(3000)]
    Ts += [_scipy_T([0.1, 0.2, 0.3], q) for q in _edge_quats()]
    for T in Ts:
        p, q = T_to_pq(T)
        ps, qs = _scipy_pq(T)
        assert np.array_equal(p, ps)
        assert np.max(np.abs(q - qs)) <= TOL, T
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) <= TOL
        p[0] += 1.0   # a copy, not a view of T
        assert T[0, 3] == ps[0]


def test_T_to_pq_round_trips_make_T_including_w_negative():
    rng = np.random.default_rng(18)
    for q in [rng.normal(size=4) for _ in range(500)] + _edge_quats():
        qn = q / np.linalg.norm(q)
        _, q2 = T_to_pq(make_T([0, 0, 0], q))
        assert min(np.max(np.abs(q2 - qn)), np.max(np.abs(q2 + qn))) <= 1e-12   # same rotation, w >= 0
        assert q2[3] >= 0


def test_T_to_pq_defers_to_scipy_off_orthogonal_and_rejects_reflections():
    rng = np.random.default_rng(19)
    for eps in (1e-13, 1e-11, 1e-6, 1e-3):
        for _ in range(200):
            T = _scipy_T([0, 0, 0], rng.normal(size=4))
            T[:3, :3] += eps * rng.normal(size=(3, 3))   # scipy projects (SVD) beyond ~1e-12: the same result
            assert np.max(np.abs(T_to_pq(T)[1] - _scipy_pq(T)[1])) <= TOL
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])
    assert R_to_quat(reflection[:3, :3].tolist()) is None
    with pytest.raises(ValueError):
        T_to_pq(reflection)
    assert R_to_quat(np.diag([1.0, 1.0, 1.0 + 1e-9]).tolist()) is not None   # diagonal: scipy's isclose rtol
    assert R_to_quat([[1.0, 1e-9, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) is None   # off-diagonal: 1e-12


def test_quat_to_R_rows_nan_inf_and_tiny_like_scipy():
    for q in ([math.nan, 0.0, 0.0, 1.0], [1e-200, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]):
        with pytest.raises(ValueError, match="zero norm"):
            Rotation.from_quat(q)
        with pytest.raises(ValueError, match="zero norm"):
            quat_to_R_rows(*q)
    rows = quat_to_R_rows(math.inf, 0.0, 0.0, 1.0)
    assert all(math.isnan(v) for r in rows for v in r)
    assert np.all(np.isnan(Rotation.from_quat([np.inf, 0, 0, 1]).as_matrix()))
