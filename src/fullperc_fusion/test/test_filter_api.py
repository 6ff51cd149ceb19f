"""The filter seam (filter_api): Measurement and its covariance check, predict / update, the registry.

The paper's filters with an explicit covariance equal to their fixed noise must be bit-identical to the fixed
noise; a different covariance must change the gain exactly as eq. (12) says (hand-computed below).
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_fusion.filters.api import (
    SOURCE_GLOBAL,
    SOURCE_LOCAL,
    BadMeasurement,
    Filter,
    Measurement,
    check_covariance,
)
from fullperc_fusion.filters.paper_family import FILTER_KINDS, FilterParams, FusionFilter, PassThrough
from fullperc_fusion.filters.registry import FILTERS, make_filter
from fullperc_fusion.pipeline.ordered import FILTER_NAMES

S = 1_000_000_000
I3 = np.eye(3)


def pose_cov(pos_var, rot_var=1e-4) -> np.ndarray:
    """A 6x6 covariance with the position block ``pos_var`` (scalar, (3,) diagonal or 3x3) and rot_var I."""
    C = np.zeros((6, 6))
    C[0:3, 0:3] = np.diag(np.broadcast_to(pos_var, 3)) if np.ndim(pos_var) < 2 else pos_var
    C[3:6, 3:6] = rot_var * I3
    return C


def stream(n=1500, seed=2):
    """(z_global, t_global, z_local, t_local) items: global-only, local-only, and pairs with a lag, plus a gap."""
    rng = np.random.default_rng(seed)
    t, items = S, []
    for k in range(n):
        t += int(rng.integers(4_000_000, 9_000_000)) + (S if k == n // 2 else 0)   # one gap > max_gap_s
        z = np.r_[0.5 + 0.05 * np.sin(k / 100), 0.2, 0.3]
        zg, zl = z + [3e-3, -2e-3, 1e-3] + rng.normal(0, 3e-4, 3), z + rng.normal(0, 1e-4, 3)
        mode = k % 3
        items.append((zg if mode != 1 else None, t - (2_000_000 if mode == 2 else 0) if mode != 1 else None,
                      zl if mode != 0 else None, t if mode != 0 else None))
    return items


# ------------------------------------------------------------------------------------------ covariance check

def test_check_covariance_accepts_a_valid_one_and_the_ros_36_vector():
    C = pose_cov([1e-8, 2e-8, 3e-8])
    C[0, 1] = C[1, 0] = 0.5e-8
    assert np.array_equal(check_covariance(C), C)
    assert np.array_equal(check_covariance(C.ravel().tolist()), C)   # PoseWithCovariance.covariance order
    D = C.copy()
    D[0, 1] += 1e-9 * 1e-8 * 0.5     # asymmetry below SYMMETRY_RTOL of the largest entry: rounding, accepted
    check_covariance(D)


@pytest.mark.parametrize("why, mutate", [
    ("non-finite", lambda C: C.__setitem__((2, 2), np.nan)),
    ("non-finite", lambda C: C.__setitem__((4, 4), np.inf)),
    ("not symmetric", lambda C: C.__setitem__((0, 1), 1e-9)),
    ("not positive definite", lambda C: C.__setitem__((1, 1), -1e-8)),
    ("not positive definite", lambda C: C.__setitem__((slice(3, 6), slice(3, 6)), 0.0)),   # semi-definite
    ("not positive definite", lambda C: C.__setitem__((slice(0, 2), slice(0, 2)), 1e-8)),  # rank-deficient
])
def test_check_covariance_rejects_with_the_reason(why, mutate):
    C = pose_cov(1e-8)
    mutate(C)
    with pytest.raises(BadMeasurement, match=why):
        check_covariance(C)


def test_check_covariance_rejects_a_wrong_shape():
    with pytest.raises(BadMeasurement, match="6x6"):
        check_covariance(np.eye(3))
    with pytest.raises(BadMeasurement, match="numeric"):
        check_covariance([["a"] * 6] * 6)


def test_a_bad_measurement_never_reaches_the_state():
    f = FusionFilter("cbkf")
    f.update(Measurement(S, SOURCE_GLOBAL, [0.1, 0.2, 0.3]))
    x, P = f.x.copy(), f.P.copy()
    bad = pose_cov(1e-8)
    bad[0, 0] = -1.0
    with pytest.raises(BadMeasurement):
        f.update(Measurement(2 * S, SOURCE_GLOBAL, [0.1, 0.2, 0.3], cov=bad))
    with pytest.raises(BadMeasurement, match="non-finite"):
        Measurement(2 * S, SOURCE_LOCAL, [np.nan, 0, 0])
    with pytest.raises(BadMeasurement, match="source"):
        Measurement(2 * S, 3, [0, 0, 0])
    with pytest.raises(ValueError, match="non-finite"):   # the step() path refuses it the same way
        f.step(z_global=[0.1, 0.2, 0.3], t_global=2 * S, cov_global=bad * np.nan)
    assert np.array_equal(f.x, x) and np.array_equal(f.P, P) and f.t_ns == S


# ------------------------------------------------------------------------------------------ R from the covariance

@pytest.mark.parametrize("kind", FILTER_KINDS)
def test_covariance_equal_to_the_fixed_noise_is_bit_identical(kind):
    prm = FilterParams()
    cg, cl = pose_cov(prm.global_std**2, 3e-5), pose_cov(prm.local_std**2, 7e-6)   # rotation part: unused
    a, b = FusionFilter(kind, prm), FusionFilter(kind, prm)
    for zg, tg, zl, tl in stream():
        sa = a.step(zg, tg, zl, tl)
        sb = b.step(zg, tg, zl, tl, cov_global=None if zg is None else cg, cov_local=None if zl is None else cl)
        assert np.array_equal(sa.p, sb.p) and np.array_equal(sa.P, sb.P) and sa.nis == sb.nis
        assert np.array_equal(a.x, b.x)
    assert a.t_ns == b.t_ns


def test_passthrough_reports_the_covariance_of_its_measurement():
    prm = FilterParams()
    a, b = PassThrough(prm), PassThrough(prm)
    sa = a.step(z_global=[1, 2, 3], t_global=S)
    sb = b.step(z_global=[1, 2, 3], t_global=S, cov_global=pose_cov(prm.global_std**2))
    assert np.array_equal(sa.P, sb.P)
    sc = b.step(z_global=[1, 2, 3], t_global=2 * S, cov_global=pose_cov([1e-6, 2e-6, 3e-6]))
    assert np.array_equal(np.diag(sc.pos_cov), [1e-6, 2e-6, 3e-6])


def _kf_at_rest():
    """kf with per-axis p = 0, v = 0, P = diag(4, 1), Q = 0, at t = 0 (as test_filters._filter_at)."""
    f = FusionFilter("kf", FilterParams(accel_noise=0.0, global_std=1.0, local_std=1.0, hop_gate=1e9,
                                        max_gap_s=10.0))
    f.x, f.P, f.t_ns = np.zeros(6), np.kron(np.diag([4.0, 1.0]), I3), 0
    return f


def test_a_different_covariance_changes_the_gain_as_eq12_says():
    # dt = 1 s: P' per axis pp = 4 + 1 = 5, pv = 1, vv = 1; H = [1 0], z = 10.
    # G = P' H^T / (5 + r): G_p = 5 / (5 + r), G_v = 1 / (5 + r); p = 10 G_p, v = 10 G_v.
    r = np.array([1.0, 5.0, 15.0])          # per-axis R = cov[:3, :3] (fixed noise would be 1 on every axis)
    f = _kf_at_rest()
    st = f.update(Measurement(S, SOURCE_GLOBAL, [10, 10, 10], cov=pose_cov(r)))
    assert np.allclose(st.p, 10 * 5 / (5 + r)) and np.allclose(st.v, 10 / (5 + r))
    assert np.allclose(st.p, [50 / 6, 5.0, 2.5])
    # posterior position variance 5 - 25 / (5 + r), NIS = sum y^2 / S
    assert np.allclose(np.diag(st.P)[0:3], 5 - 25 / (5 + r))
    assert st.nis == pytest.approx(np.sum(100 / (5 + r)))
    ref = _kf_at_rest().update(Measurement(S, SOURCE_GLOBAL, [10, 10, 10]))
    assert np.allclose(ref.p, 50 / 6)       # fixed noise r = 1: the first axis only agrees


def test_a_correlated_covariance_enters_as_a_full_block():
    # R = [[1, 0.5], [0.5, 1]] on (x, y), z = 1: G_p = 5 (5 I + R)^-1 on (x, y)
    R = np.diag([1.0, 1.0, 1.0])
    R[0, 1] = R[1, 0] = 0.5
    st = _kf_at_rest().update(Measurement(S, SOURCE_GLOBAL, [10, 10, 10], cov=pose_cov(R)))
    Sxy = 5 * np.eye(2) + R[0:2, 0:2]
    assert np.allclose(st.p[0:2], 5 * np.linalg.solve(Sxy, [10, 10]))   # = 50 / 6.5 each
    assert np.allclose(st.p[0:2], 50 / 6.5) and st.p[2] == pytest.approx(50 / 6)


def test_only_the_position_block_is_used_by_the_paper_filters():
    a, b = _kf_at_rest(), _kf_at_rest()
    sa = a.update(Measurement(S, SOURCE_GLOBAL, [10, 10, 10], cov=pose_cov(2.0, rot_var=1e-6)))
    C = pose_cov(2.0, rot_var=5.0)
    C[0:3, 3:6] = C[3:6, 0:3] = 0.1 * I3
    sb = b.update(Measurement(S, SOURCE_GLOBAL, [10, 10, 10], cov=C))
    assert np.array_equal(sa.p, sb.p) and np.array_equal(sa.P, sb.P)


# ------------------------------------------------------------------------------------------ predict / update

@pytest.mark.parametrize("kind", FILTER_KINDS)
def test_explicit_predict_then_update_is_step(kind):
    a, b = FusionFilter(kind), FusionFilter(kind)
    for zg, tg, zl, tl in stream(600):
        sa = a.step(zg, tg, zl, tl)
        ms = [Measurement(t, s, z) for z, t, s in ((zl, tl, SOURCE_LOCAL), (zg, tg, SOURCE_GLOBAL)) if z is not None]
        b.predict(max(m.t_ns for m in ms))
        sb = b.update(*ms)                  # order of the arguments does not matter: global rows first
        assert np.array_equal(sa.p, sb.p) and np.array_equal(a.P, b.P) and sa.reset == sb.reset


def test_predict_refuses_time_going_backwards_and_a_gap_defers_to_the_next_update():
    f = FusionFilter("ckf")
    f.predict(S)                            # no state yet: only the stamp is kept
    assert not f.initialized and f.time_ns == S
    st = f.update(Measurement(S, SOURCE_GLOBAL, [0.1, 0.2, 0.3]))
    assert st.reset and f.t_ns == S
    f.x[6:9] = [1e-3, 2e-3, 3e-3]
    with pytest.raises(ValueError, match="backwards"):
        f.predict(S - 1)
    f.predict(2 * S)                        # 1 s > max_gap_s: the state stays, the update re-initialises
    assert f.t_ns == S and f.time_ns == 2 * S
    with pytest.raises(ValueError, match="backwards"):
        f.predict(2 * S - 1)
    st = f.update(Measurement(2 * S, SOURCE_GLOBAL, [0.1, 0.2, 0.3]))
    assert st.reset and np.allclose(st.b, [1e-3, 2e-3, 3e-3]) and f.t_ns == 2 * S


def test_update_refuses_two_of_a_source_and_a_measurement_older_than_the_gap():
    f = FusionFilter("kf")
    f.update(Measurement(S, SOURCE_GLOBAL, [0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match="at most one global"):
        f.update(Measurement(2 * S, SOURCE_GLOBAL, [0, 0, 0]), Measurement(2 * S, SOURCE_GLOBAL, [0, 0, 0]))
    f.predict(S + S // 10)
    with pytest.raises(ValueError, match="older than the filter time"):
        f.update(Measurement(S - S, SOURCE_LOCAL, [0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match="needs a global or a local"):
        f.update()


# ------------------------------------------------------------------------------------------ registry

def test_the_registry_is_the_one_list():
    assert FILTER_NAMES == tuple(FILTERS) == ("cbkf", "ckf", "bkf", "kf", "omc", "fullperc")
    for name in FILTERS:
        f = make_filter(name, FilterParams(global_std=1e-3))
        assert isinstance(f, Filter) and f.kind == name and f.params.global_std == 1e-3
    with pytest.raises(ValueError, match="not one of"):
        make_filter("ukf")


def test_each_filter_gets_its_own_parameter_dataclass():
    """A target's one parameter object (fullperc's dataclass, a superset) reaches each filter as its registry entry's
    own dataclass: the paper's filters get a FilterParams with the same values of their fields, fullperc the object."""
    import dataclasses

    from fullperc_fusion.filters.fullperc_params import FullpercParams
    from fullperc_fusion.filters.registry import own_params

    p = FullpercParams(global_std=2e-3, local_std=3e-4)
    for name, entry in FILTERS.items():
        f = make_filter(name, p)
        assert type(f.params) is entry.params, name
        assert all(getattr(f.params, k.name) == getattr(p, k.name) for k in dataclasses.fields(entry.params)), name
    assert make_filter("fullperc", p).params is p
    assert own_params("cbkf", None) is None
    base = FilterParams(global_std=1e-3)
    assert own_params("cbkf", base) is base
