"""The fast forms of the IMM and of the model covariances, held bit for bit to the plain formulas they replace.

``fullperc``'s IMM (filters/fullperc_imm.py), its arithmetic (filters/motion.py), the float SO(3) helpers
(filters/so3_float.py) and the model covariances (filters/measurement_models.py) compute some values with fewer or
cheaper calls than the plain formulas: batched matrix products, float lists, templates written with ``put``. Each
must give the very same bits as the plain form (``==``, not a tolerance), so the node's outputs do not move. Each
plain form is written out here as the straightforward numpy, and both run on random inputs.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.so3 import R_to_quat, so3_exp
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement, Step
from fullperc_fusion.filters.fullperc_imm import FullpercImm
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_state import POSE_FLAT, TH
from fullperc_fusion.filters.measurement_models import (
    LocalModelParams,
    OmcModelParams,
    link_covariance_at,
    local_covariance,
    omc_covariance,
    omc_systematic_var,
    omc_variances,
    rotate_cov,
    rotate_diag_cov,
    vega_covariance,
)
from fullperc_fusion.filters.motion import mix, mix_each, mixing, posterior, transition
from fullperc_fusion.filters.so3_float import R9_to_quat, exp9, log9, mul9, mul9_t

S = 1_000_000_000


def _same(a, b) -> bool:
    """Equal entry for entry (a NaN equals a NaN)."""
    return np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float), equal_nan=True)


# ---- motion.py --------------------------------------------------------------------------------------------------
def _transition_plain(dt: float, n: int, dwell: float) -> np.ndarray:
    if n == 1:
        return np.ones((1, 1))
    stay = math.exp(-max(dt, 0.0) / dwell)
    T = np.full((n, n), (1.0 - stay) / (n - 1))
    np.fill_diagonal(T, stay)
    return T


def _posterior_plain(c: np.ndarray, log_lik) -> tuple[np.ndarray, float]:
    ll = np.asarray(log_lik, dtype=float)
    top = float(ll.max())
    a = c * np.exp(ll - top)
    s = float(a.sum())
    return a / s, top + math.log(s)


def test_transition_posterior_and_mixing_are_the_plain_formulas_bit_for_bit():
    rng = np.random.default_rng(0)
    for _ in range(300):
        n = int(rng.integers(1, 5))
        dt, dwell = float(rng.uniform(-0.01, 0.5)), float(rng.uniform(0.1, 5.0))
        assert _same(transition(dt, n, dwell), _transition_plain(dt, n, dwell))
    cases = [[-2000.0, -2000.0 - np.log(3.0)], [1.0, float("-inf"), 3.0], [float("nan"), 1.0, 2.0],
             [float("inf"), 1.0, 2.0], [-5.0, -5.0, -5.0]]
    cases += [list(rng.normal(0, 10 ** rng.uniform(-3, 3), size=int(rng.integers(1, 5)))) for _ in range(500)]
    for ll in cases:
        c = rng.dirichlet(np.ones(len(ll)))
        with np.errstate(invalid="ignore"):
            mu, log_l = posterior(c, ll)
            mu0, log_l0 = _posterior_plain(c, ll)
        assert _same(mu, mu0) and (log_l == log_l0 or (math.isnan(log_l) and math.isnan(log_l0))), ll
    for _ in range(300):   # mixing's W in floats: the element-wise numpy formula's bits
        n = int(rng.integers(1, 5))
        mu, T = rng.dirichlet(np.ones(n)), _transition_plain(float(rng.uniform(0, 0.5)), n, 2.0)
        c, W = mixing(mu, T)
        assert _same(c, mu @ T) and _same(W, (T * mu[:, None]) / c[None, :])


@pytest.mark.parametrize("n", [2, 3, 4])
def test_mix_each_is_one_mix_per_column_bit_for_bit(n):
    """The stacked products run the same BLAS calls as mix(W[:, j]) -- with W's strided column as mix gets it."""
    rng = np.random.default_rng(n)
    for _ in range(200):
        _, W = mixing(rng.dirichlet(np.ones(n)), _transition_plain(float(rng.uniform(0, 0.05)), n, 2.0))
        D = rng.normal(size=(n, 21)) * 10.0 ** rng.uniform(-6, 0, size=(n, 21))
        A = rng.normal(size=(n, 21, 21))
        Ps = A @ A.transpose(0, 2, 1)
        dx0, P0 = mix_each(W, D, Ps)
        for j in range(n):
            d, P = mix(W[:, j], list(D), list(Ps))
            assert _same(dx0[j], d) and _same(P0[j], P)


# ---- fullperc_imm.py --------------------------------------------------------------------------------------------
def _walk_items(seed: int) -> list[list[Measurement]]:
    """A target that stands, walks and turns, at 100 Hz with jittered stamps: OMC pose, Vega pose every other frame."""
    rng = np.random.default_rng(seed)
    items, t = [], 1_000 * S
    for k in range(400):
        t += int(rng.integers(8_000_000, 12_000_000))
        u = k / 400
        p = np.array([0.5 * math.sin(3 * u), 0.2 * u, 1.0]) + rng.normal(0, 3e-4, 3)
        q = R_to_quat(so3_exp(np.array([0.1 * u, 0.0, 0.3 + 0.8 * u]) + rng.normal(0, 1e-3, 3)))
        ms = [Measurement(t, SOURCE_GLOBAL, p + 1e-3, q=q)]
        if k % 2:
            ms.append(Measurement(t - 2_000_000, SOURCE_LOCAL, p + rng.normal(0, 1e-4, 3), q=q))
        items.append(ms)
    return items


def _offsets_plain(ref, models) -> list[np.ndarray]:
    xr = np.array(ref._x)
    out = []
    for f in models:
        d = np.array(f._x) - xr
        d[TH] = log9(mul9_t(f._R, ref._R))
        out.append(d)
    return out


def _advance_plain(imm: FullpercImm, t_ns: int) -> tuple[np.ndarray, list[tuple]]:
    """The interaction step with mixing, transition and one mix per model, as written before the fast form."""
    fs = imm.models
    c, W = mixing(imm._mu, _transition_plain((t_ns - fs[0]._t) * 1e-9, len(fs), imm.params.motion_dwell))
    ref = fs[int(np.argmax(imm._mu))]
    D, Ps, xr = np.array(_offsets_plain(ref, fs)), np.array([f._P for f in fs]), np.array(ref._x)
    out = []
    for j in range(len(fs)):
        dx0, P0 = mix(W[:, j], D, Ps)
        x = (xr + dx0).tolist()
        x[9] = x[10] = x[11] = 0.0
        out.append((x, mul9(exp9(*dx0[TH].tolist()), ref._R), P0))
    return c, out


def _combine_plain(imm: FullpercImm, steps: list[Step], log_l: float) -> Step:
    mu = imm._mu
    k = int(np.argmax(mu))
    ref, top = imm.models[k], steps[k]
    dx, P = mix(mu, _offsets_plain(ref, imm.models), [s.P for s in steps])
    x = np.array(ref._x) + dx
    q = R9_to_quat(mul9(exp9(*dx[TH].tolist()), ref._R))
    return Step(top.t_ns, x[0:3], x[3:6], x[6:9] + x[18:21], P, top.sources, q=q,
                pose_cov=P.ravel()[POSE_FLAT].reshape(6, 6), log_lik=log_l)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_imm_interaction_and_output_are_the_plain_formulas_bit_for_bit(seed):
    """At every sample of a stream (and with random model weights, so every model is the reference in turn):
    _advance gives each model the state the plain interaction gives, _combine the plain mixture."""
    rng = np.random.default_rng(seed)
    imm = FullpercImm(FullpercParams(motion="auto"))
    checked = 0
    for ms in _walk_items(seed):
        t = max(m.t_ns for m in ms)
        fs = imm.models
        if fs[0]._t is not None and all(f._pend is None for f in fs):
            if rng.random() < 0.5:
                imm._mu = rng.dirichlet(np.full(len(fs), 0.3))
            c0, want = _advance_plain(imm, t)
            imm._advance(t)
            assert _same(imm._mu, c0)
            for f, (x, R, P) in zip(fs, want, strict=True):
                assert f._x == x and f._R == R and _same(f._P, P)
            checked += 1
        imm.predict(t)
        steps = [f.update(*ms) for f in imm.models]
        if not any(s.reset for s in steps):
            imm._mu = rng.dirichlet(np.ones(len(fs)))
            got, want = imm._combine(steps, -1.5), _combine_plain(imm, steps, -1.5)
            for name in ("p", "v", "b", "P", "q", "pose_cov"):
                assert _same(getattr(got, name), getattr(want, name)), name
    assert checked > 300


def test_the_transition_cache_gives_the_transition_of_the_step():
    imm = FullpercImm(replace(FullpercParams(motion="auto"), motion_dwell=1.7))
    items = _walk_items(3)
    for ms in items[:50]:
        imm.predict(ms[0].t_ns)
        imm.update(*ms)
    assert imm._tcache
    for dns, T in imm._tcache.items():
        assert _same(T, _transition_plain(dns * 1e-9, len(imm.models), 1.7))


# ---- so3_float.py -----------------------------------------------------------------------------------------------
def _exp9_plain(a: float, b: float, c: float) -> tuple:
    th = math.sqrt(a * a + b * b + c * c)
    if th < 1e-8:
        s, k = 1.0, 0.5
    else:
        s, k = math.sin(th) / th, (1.0 - math.cos(th)) / (th * th)
    aa, bb, cc, ab, ac, bc = a * a, b * b, c * c, a * b, a * c, b * c
    return (1.0 - k * (bb + cc), -s * c + k * ab, s * b + k * ac,
            s * c + k * ab, 1.0 - k * (aa + cc), -s * a + k * bc,
            -s * b + k * ac, s * a + k * bc, 1.0 - k * (aa + bb))


def _log9_plain(R: tuple) -> list[float]:
    c = max(-1.0, min(1.0, 0.5 * (R[0] + R[4] + R[8] - 1.0)))
    v = [R[7] - R[5], R[2] - R[6], R[3] - R[1]]
    th = math.acos(c)
    if th < 1e-6:
        return [0.5 * v[0], 0.5 * v[1], 0.5 * v[2]]
    if th > math.pi - 1e-4:
        return log9(R)   # the shared so3_log's branch, unchanged
    f = th / (2.0 * math.sin(th))
    return [f * v[0], f * v[1], f * v[2]]


def test_exp9_and_log9_are_the_plain_formulas_bit_for_bit():
    rng = np.random.default_rng(5)
    for _ in range(20000):
        w = rng.normal(size=3) * 10.0 ** rng.uniform(-12, 0.5)
        a, b, c = w.tolist()
        R = exp9(a, b, c)
        assert R == _exp9_plain(a, b, c)
        assert log9(R) == _log9_plain(R)
        S9 = tuple((np.array(R) * (1 + rng.normal(0, 1e-7, 9))).tolist())   # not quite a rotation
        assert log9(S9) == _log9_plain(S9)
    for R in [(1.0 + 1e-9, 0.0, 0.0, 0.0, 1.0 + 1e-9, 0.0, 0.0, 0.0, 1.0 + 1e-9),   # the clamp at 1
              (-1.0 - 1e-9, 0.0, 0.0, 0.0, -1.0 - 1e-9, 0.0, 0.0, 0.0, -1.0 - 1e-9)]:   # and at -1
        assert log9(R) == _log9_plain(R)
    nan = log9((float("nan"),) * 9)
    assert all(math.isnan(v) for v in nan) and all(math.isnan(v) for v in _log9_plain((float("nan"),) * 9))


# ---- measurement_models.py --------------------------------------------------------------------------------------
def _omc_plain(fit_error, margin_deg, params: OmcModelParams) -> tuple[np.ndarray, tuple[float, float]]:
    """omc_systematic_var and omc_covariance as np.isfinite / np.diag wrote them."""
    e = params.default_fit if fit_error is None or not np.isfinite(fit_error) or fit_error < 0 else float(fit_error)
    f = 1.0 if margin_deg is None or not np.isfinite(margin_deg) else float(
        params.margin_ref / max(float(margin_deg), params.margin_min))
    sp = params.sys_floor**2 + (params.fit_gain * e) ** 2 + params.margin_std**2 * f
    sr = params.rot_sys_floor**2 + (params.fit_gain * e / params.marker_lever) ** 2 + params.rot_margin_std**2 * f
    vp = params.white_std**2 + (params.white_fit_gain * e) ** 2 + params.white_margin_std**2 * f
    vr = vp / params.marker_lever**2 + sr
    return np.diag([vp, vp, vp, vr, vr, vr]), (sp, sr)


def _rotate_plain(cov: np.ndarray, R: np.ndarray) -> np.ndarray:
    J = np.zeros((6, 6))
    J[0:3, 0:3] = J[3:6, 3:6] = R
    out = J @ cov @ J.T
    return 0.5 * (out + out.T)


def _link_plain(link_cov: np.ndarray, lever_arm) -> np.ndarray:
    x, y, z = (float(v) for v in lever_arm)
    J = np.array([[1.0, 0.0, 0.0, 0.0, z, -y], [0.0, 1.0, 0.0, -z, 0.0, x], [0.0, 0.0, 1.0, y, -x, 0.0],
                  [0.0, 0.0, 0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]])
    out = J @ np.asarray(link_cov, dtype=float) @ J.T
    return 0.5 * (out + out.T)


def _local_plain(T_base_ots, T_ots_tool, link_cov, device_cov=None) -> np.ndarray:
    params = LocalModelParams()
    R = T_base_ots[:3, :3]
    p = T_ots_tool[:3, 3]
    if device_cov is None:
        s = (max(float(np.linalg.norm(p)), 0.1) / params.d_ref) ** params.exponent
        vp, vr = (params.std_ref * s) ** 2, (params.rot_std_ref * s) ** 2
        C_dev = np.diag([vp, vp, vp, vr, vr, vr])
    else:
        C_dev = device_cov
    C = _rotate_plain(C_dev, R)
    if link_cov is not None:
        C = C + _link_plain(link_cov, R @ p)
    return 0.5 * (C + C.T)


def _T(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rot.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(0, 1.0, 3)
    return T


def test_the_omc_model_is_the_plain_formula_bit_for_bit():
    rng = np.random.default_rng(7)
    models = [OmcModelParams(), replace(OmcModelParams(), margin_std=4.4e-3, rot_margin_std=13.5e-3, fit_gain=0.72)]
    fits = [None, -1.0, float("nan"), float("inf"), 0.0, 0.29e-3] + list(rng.uniform(0, 1e-3, 40))
    margins = [None, float("nan"), 0.0, 10.0, 300.0, 1e9] + list(rng.uniform(0, 900, 40))
    for params in models:
        for e, m in zip(fits, margins, strict=True):
            C0, sv0 = _omc_plain(e, m, params)
            vp, vr, sv = omc_variances(e, m, params)
            assert sv == sv0 and omc_systematic_var(e, m, params) == sv0
            assert _same(omc_covariance(e, m, params), C0) and _same(omc_covariance(e, m, params, sv), C0)
            assert _same(np.diag([vp, vp, vp, vr, vr, vr]), C0)
            R = Rot.random(random_state=rng).as_matrix()
            assert _same(rotate_diag_cov(vp, vr, R), _rotate_plain(C0, R))
            T = _T(rng)   # a rotation block of a 4x4 (strided), as the pipeline passes it
            assert _same(rotate_diag_cov(vp, vr, T[:3, :3]), _rotate_plain(C0, T[:3, :3]))


def test_the_local_model_and_the_link_term_are_the_plain_formulas_bit_for_bit():
    rng = np.random.default_rng(8)
    for _ in range(500):
        A, T_dev = _T(rng), _T(rng)
        T_dev[:3, 3] *= rng.uniform(0.01, 2.5)
        B = rng.normal(size=(6, 6))
        link = B @ B.T * 10.0 ** rng.uniform(-12, -6)
        dev = link * 3.0
        lever = rng.normal(0, 1.5, 3)
        assert _same(link_covariance_at(link, lever), _link_plain(link, lever))
        assert _same(link_covariance_at(link, lever.tolist()), _link_plain(link, lever))
        assert _same(link_covariance_at(link, A[:3, 3]), _link_plain(link, A[:3, 3]))   # a strided view
        for lc in (None, link):
            assert _same(local_covariance(A, T_dev, lc), _local_plain(A, T_dev, lc))
            assert _same(local_covariance(A, T_dev, lc, device_cov=dev), _local_plain(A, T_dev, lc, device_cov=dev))
        d = float(rng.uniform(0.0, 3.0))
        s = (max(d, 0.1) / LocalModelParams().d_ref) ** 2.0
        pr = LocalModelParams()
        assert _same(vega_covariance(d), np.diag([(pr.std_ref * s) ** 2] * 3 + [(pr.rot_std_ref * s) ** 2] * 3))
        assert _same(rotate_cov(dev, A[:3, :3]), _rotate_plain(dev, A[:3, :3]))
