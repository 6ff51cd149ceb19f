"""The fast ``fullperc`` filter (filters.fullperc) against its general form, the reference (fullperc_reference).

Agreement, stated once, checked after every step of long randomised streams: position, velocity, bias (b + g), the
global position innovation and the orientation quaternion to 1e-12 absolute (m, m/s, unit quaternion); every
covariance entry (the full 21x21 P and the 6x6 pose covariance) to 1e-11 of sqrt(P_ii P_jj), i.e. relative to the
scale of that entry (P spans 1e-10 m^2 to 0.25 rad^2/s^2, so one absolute figure would say little); hop, reset,
sources, stamp and the hop counters exactly. NIS, NIS_global and the log-likelihood to 1e-10 of max(1, |value|): NIS
divides by a 0.1 mm sigma, so the ~1e-15 m by which two implementations' positions differ after thousands of steps
is ~1e-11 of it, doubled by the square (measured: <= 1.4e-11). Streams: global only / local only / pairs (either
sample up to 4 ms older), with and without orientation (a position-only start included), fixed noise / diagonal /
full 6x6 covariances with position-rotation terms (the lever-arm form of measurement_models.local_covariance),
``sys_var`` extras (valid and invalid), gaps beyond ``max_gap_s`` (re-initialisation), position hops and rotation
jumps, fast turns (rotations past 120 deg: the other branch of the quaternion conversion), snapshot/restore, the
frame changing every 250 items (``express_in``, with and without a local sample in the item), the global rotation-
noise scale mu (``rot_noise_scale``) learnt both below and above 1. The fast form's SO(3) on floats (so3_float)
against the shared ``fullperc_common.so3``.
"""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_common import so3
from fullperc_common.so3 import R_to_quat, so3_exp
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.fullperc_reference import FullpercReference
from fullperc_fusion.filters.registry import make_filter
from fullperc_fusion.filters.so3_float import R9_to_quat, exp9, log9, mul9, mul9_t, quat_to_R9

S = 1_000_000_000
TOL = 1e-12
COV_TOL = 1e-11     # covariances: measured <= 6.3e-12 (the other-noise settings; 3.6e-12 there without beta's
                    # spatial decay, whose factor exp(-d / L) takes d from positions that agree to ~1e-16 m)


def _cov(rng, mode: str | None) -> np.ndarray | None:
    if mode is None:
        return None
    vp, vr = rng.uniform(1e-9, 1e-7), rng.uniform(1e-6, 4e-5)
    if mode == "diag":
        return np.diag([*rng.uniform(0.5, 2.0, 3) * vp, *rng.uniform(0.5, 2.0, 3) * vr])
    # a device covariance plus a static link's through a lever arm (position-rotation and cross-axis terms)
    C = np.diag([vp] * 3 + [vr] * 3)
    A = np.diag([3e-5] * 3 + [3e-4] * 3) @ rng.normal(size=(6, 6))
    link = A @ A.T + np.diag([1e-9] * 3 + [1e-7] * 3)          # correlated, ~0.05 mm and ~0.5 mrad
    lx, ly, lz = rng.normal(0, 0.5, 3)
    J = np.eye(6)
    J[0:3, 3:6] = -so3.skew(np.array([lx, ly, lz]))
    C = C + J @ link @ J.T
    return 0.5 * (C + C.T)


def _items(seed: int, n: int, cov_modes=(None, "diag", "full"), start_position_only: bool = True,
           outages: bool = False):
    """Random items (module docstring). Truth: a slow position path, orientation turning at a varying rate.
    ``outages``: no local sample in items 150-299 of every 300 (the Vega loses the tool: beta's and b's spatial
    decay)."""
    rng = np.random.default_rng(seed)
    t, out = S, []
    R, w = so3_exp(rng.normal(size=3)), np.zeros(3)
    beta = rng.normal(0, 0.01, 3)
    for k in range(n):
        step = int(rng.integers(4_000_001, 12_000_000)) + (S if rng.random() < 0.004 else 0)
        t += step
        if rng.random() < 0.02:
            w = rng.normal(0, 2.0, 3)              # a fast turn now and then
        R = so3_exp(w * step * 1e-9) @ R
        z = np.array([0.5 + 0.05 * np.sin(k / 100), 0.2 - 0.1 * np.cos(k / 70), 0.3 + 0.02 * np.sin(k / 30)])
        mode = int(rng.integers(3))                   # 0 global, 1 local, 2 pair
        if outages and k % 300 >= 150:
            mode = 0
        older = SOURCE_GLOBAL if rng.random() < 0.5 else SOURCE_LOCAL
        with_q = not (start_position_only and k < 20) and rng.random() > 0.05
        ms = []
        if mode != 1:
            zg = z + [3e-3, -2e-3, 1e-3] + rng.normal(0, 3e-4, 3)
            Rg = so3_exp(beta + rng.normal(0, 3e-3, 3)) @ R
            if rng.random() < 0.03:
                zg = zg + rng.normal(0, 5e-3, 3)       # a position hop
            if rng.random() < 0.02:
                Rg = so3_exp(rng.normal(0, 0.03, 3)) @ Rg   # a rotation jump
            lag = int(rng.integers(0, 4_000_000)) if mode == 2 and older == SOURCE_GLOBAL else 0
            extras = {}
            u = rng.random()
            if u < 0.4:
                extras["sys_var"] = rng.uniform(1e-8, 1e-6)
            elif u < 0.45:
                extras["sys_var"] = float(rng.choice([np.nan, -1.0, 0.0]))
            ms.append(Measurement(t - lag, SOURCE_GLOBAL, zg, R_to_quat(Rg) if with_q else None,
                                  _cov(rng, cov_modes[int(rng.integers(len(cov_modes)))]), extras=extras))
        if mode != 0:
            lag = int(rng.integers(0, 4_000_000)) if mode == 2 and older == SOURCE_LOCAL else 0
            Rl = so3_exp(rng.normal(0, 2e-3, 3)) @ R
            ms.append(Measurement(t - lag, SOURCE_LOCAL, z + rng.normal(0, 1e-4, 3), R_to_quat(Rl) if with_q else None,
                                  _cov(rng, cov_modes[int(rng.integers(len(cov_modes)))])))
        out.append(ms)
    return out


def _frozen(items):
    """The items with read-only arrays, for a stream that several runs share: a filter that changed a measurement
    in place would raise instead of changing the input of the runs after it."""
    for ms in items:
        for m in ms:
            for a in (m.p, m.q, m.cov):
                if a is not None:
                    a.flags.writeable = False
    return items


@pytest.fixture(scope="module")
def stream_23():
    """``_items(23, 1500)``, made once per module: every setting of the parametrised test below runs this same
    stream (it used to generate it once per setting)."""
    return _frozen(_items(23, 1500))


def _scaled(A: np.ndarray, B: np.ndarray) -> float:
    """max |A_ij - B_ij| / sqrt(B_ii B_jj): each covariance entry's error relative to its own scale."""
    d = np.sqrt(np.abs(np.diag(B)))
    return float((np.abs(A - B) / np.maximum(np.outer(d, d), 1e-300)).max())


def _agree(a, b) -> None:
    assert (a.t_ns, a.sources, a.reset, a.hop) == (b.t_ns, b.sources, b.reset, b.hop)
    for f in ("p", "v", "b", "innovation"):
        assert np.abs(getattr(a, f) - getattr(b, f)).max() <= TOL, f
    assert (a.q is None) == (b.q is None) and (a.pose_cov is None) == (b.pose_cov is None)
    if a.q is not None:
        assert np.abs(a.q - b.q).max() <= TOL, "q"
        assert _scaled(a.pose_cov, b.pose_cov) <= COV_TOL, "pose_cov"
    assert _scaled(a.P, b.P) <= COV_TOL, "P"
    assert abs(a.nis - b.nis) <= 100 * TOL * max(1.0, b.nis)
    assert abs(a.nis_global - b.nis_global) <= 100 * TOL * max(1.0, b.nis_global)
    assert abs(a.log_lik - b.log_lik) <= 100 * TOL * max(1.0, abs(b.log_lik)), "log_lik"


def _frames(seed: int):
    """A new frame every 250 items: a transform within ~2 mrad and ~1 mm of the identity (a link re-estimated)."""
    rng = np.random.default_rng(seed)
    frame = np.eye(4)
    k = 0
    while True:
        if k % 250 == 0:
            frame = np.eye(4)
            frame[:3, :3] = so3_exp(rng.normal(0, 2e-3, 3))
            frame[:3, 3] = rng.normal(0, 1e-3, 3)
        yield frame
        k += 1


def _run(items, params=None):
    fast, ref = FullpercFilter(params), FullpercReference(params)
    fast.likelihood = True   # Step.log_lik, which the reference always fills (motion: auto's model weights)
    seen = {"hop": 0, "reset": 0, "pair": 0, "lag": 0, "q": 0, "full": 0, "rot_hop": 0, "scaled": 0, "moved": 0,
            "mu_low": 0, "mu_high": 0}
    frames = _frames(7)
    for ms in items:
        frame, local = next(frames), any(m.source == SOURCE_LOCAL for m in ms)
        Ma, Mb = fast.express_in(frame, local), ref.express_in(frame, local)
        assert (Ma is None) == (Mb is None) and (Ma is None or np.array_equal(Ma, Mb))
        seen["moved"] += Mb is not None
        t = max(m.t_ns for m in ms)
        fast.predict(t)
        ref.predict(t)
        a, b = fast.update(*ms), ref.update(*ms)
        _agree(a, b)
        assert fast.time_ns == ref.time_ns and fast.hop_counts == ref.hop_counts
        assert np.abs(fast.rot_bias - ref.rot_bias).max() <= TOL
        assert abs(fast.state.noise_scale - ref.s.noise_scale) <= 100 * TOL * ref.s.noise_scale
        seen["scaled"] += ref.s.noise_scale > 1.0
        assert abs(fast.state.rot_scale - ref.s.rot_scale) <= 100 * TOL * ref.s.rot_scale
        seen["mu_low"] += ref.s.rot_scale < 0.9
        seen["mu_high"] += ref.s.rot_scale > 1.1
        seen["hop"] += b.hop
        seen["reset"] += b.reset
        seen["pair"] += len(ms) == 2
        seen["lag"] += any(m.t_ns < t for m in ms)
        seen["q"] += b.q is not None
        seen["full"] += any(m.cov is not None and m.cov[0, 4] != 0 for m in ms)
    seen["rot_hop"] = ref.hop_counts["rotation"]
    return fast, ref, seen


@pytest.mark.parametrize("seed", [21, 22])
def test_fast_form_equals_the_reference(seed):
    fast, ref, seen = _run(_items(seed, 3000))
    # the stream exercised every branch
    assert seen["hop"] >= 30 and seen["rot_hop"] >= 10 and seen["reset"] >= 5 and seen["pair"] >= 600
    assert seen["lag"] >= 400 and seen["full"] >= 1000 and 0 < seen["q"] < 3000
    assert 100 <= seen["scaled"] < 3000      # the global noise scale was above 1 for part of the stream
    assert seen["moved"] >= 8                # the estimate was moved with its frame (11 frame changes)
    assert seen["mu_low"] >= 100 and seen["mu_high"] >= 100   # the rotation-noise scale went both ways


@pytest.mark.parametrize("params", [
    FullpercParams(hop_to_bias=False),
    FullpercParams(accel_noise=2.0, bias_walk=1e-4, global_std=1e-3, local_std=5e-4, hop_gate=9.0, max_gap_s=0.05,
                   ang_accel_noise=5.0, rot_bias_walk=1e-4, sys_time=0.5, sys_std=1e-3),
    FullpercParams(rot_sys_time=0.0),
    FullpercParams(rot_sys_time=0.4, rot_sys_std=0.05),
    FullpercParams(hop_into="g"),
    FullpercParams(hop_needs_local="never"),
    FullpercParams(hop_needs_local="always"),
    FullpercParams(noise_adapt_time=0.0),
    FullpercParams(noise_adapt_time=0.05, noise_adapt_max=4.0),
    FullpercParams(rot_noise_adapt_time=0.0),
    FullpercParams(rot_noise_adapt_time=0.1, rot_noise_adapt_min=0.5, rot_noise_adapt_max=2.0, rot_noise_length=0.0),
], ids=["no-hop-to-bias", "other-noise", "beta-random-walk", "beta-fast-gauss-markov", "hop-into-g", "cbkf-hop-rule",
        "hop-while-local", "no-noise-scale",
        "fast-noise-scale", "no-rot-noise-scale", "fast-rot-noise-scale-held"])
def test_fast_form_equals_the_reference_for_other_settings(params, stream_23):
    _run(stream_23, params)


def test_fast_form_equals_the_reference_when_the_vega_loses_the_tool():
    """Streams with the local source gone for half of every 300 items, the path moving meanwhile: beta's and b's
    spatial decay (``rot_bias_length``, ``bias_length``) act, and the two forms agree at every step; with short
    lengths and long ones, and b's alone."""
    items = _frozen(_items(24, 1500, outages=True))     # one stream for every setting
    for params in (FullpercParams(), FullpercParams(rot_bias_length=0.005, local_lost_s=0.02),
                   FullpercParams(bias_length=0.01, bias_field_std=0.5e-3, local_lost_s=0.02),
                   FullpercParams(bias_length=0.3, bias_field_std=0.3e-3, rot_bias_length=0.0)):
        fast, ref, _ = _run(items, params)
        assert ref.s.rot_dmax > 0.0 and fast.state.rot_dmax == pytest.approx(ref.s.rot_dmax, abs=TOL)


def test_fixed_noise_and_position_only_streams():
    """The benchmark's kind of input: no covariance, and a stream without any orientation."""
    _run(_items(24, 1500, cov_modes=(None,)))
    items = [[Measurement(m.t_ns, m.source, m.p) for m in ms] for ms in _items(25, 1500, cov_modes=(None,))]
    fast, _, seen = _run(items)
    assert seen["q"] == 0


def test_snapshot_and_restore_replay_identically_and_agree():
    items = _items(26, 600)
    fast, ref = FullpercFilter(), FullpercReference()
    fast.likelihood = True
    for ms in items[:200]:
        t = max(m.t_ns for m in ms)
        for f in (fast, ref):
            f.predict(t)
        fast.update(*ms)
        ref.update(*ms)
    snap_f, snap_r = fast.snapshot(), ref.snapshot()
    first = []
    for ms in items[200:]:
        fast.predict(max(m.t_ns for m in ms))
        first.append(fast.update(*ms))
    for _ in range(2):       # the snapshot stays usable
        fast.restore(snap_f)
        ref.restore(snap_r)
        for ms, a in zip(items[200:], first, strict=True):
            t = max(m.t_ns for m in ms)
            fast.predict(t)
            ref.predict(t)
            s, r = fast.update(*ms), ref.update(*ms)
            assert np.array_equal(s.p, a.p) and np.array_equal(s.P, a.P) and np.array_equal(s.q, a.q)
            _agree(s, r)
    with pytest.raises(TypeError):
        fast.restore(snap_r)


def test_the_states_a_step_returned_are_not_changed_by_later_steps():
    """The fast form shares arrays between its state, its snapshots and the Steps (nothing is changed in place):
    a Step's P and pose_cov, and a snapshot, must still be those of their own moment after later steps."""
    items = _items(27, 300)
    f = FullpercFilter()
    kept = []
    for ms in items:
        f.predict(max(m.t_ns for m in ms))
        st = f.update(*ms)
        kept.append((st, st.P.copy(), None if st.pose_cov is None else st.pose_cov.copy(), f.snapshot(),
                     f.state.P.copy()))
    for st, P, pc, snap, Ps in kept:
        assert np.array_equal(st.P, P) and (pc is None or np.array_equal(st.pose_cov, pc))
        f.restore(snap)
        assert np.array_equal(f.state.P, Ps)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_refusals_and_resets_are_the_references():
    for cls in (FullpercFilter, FullpercReference):
        f = cls()
        f.update(Measurement(S, SOURCE_GLOBAL, [0.1, 0.2, 0.3], [0, 0, 0, 1]))
        with pytest.raises(ValueError, match="time went backwards"):
            f.predict(S - 1)
        with pytest.raises(ValueError, match="at most one global"):
            f.update(Measurement(2 * S, SOURCE_GLOBAL, [0, 0, 0]), Measurement(2 * S, SOURCE_GLOBAL, [0, 0, 0]))
        f.predict(S + S // 10)
        with pytest.raises(ValueError, match="older than the filter time"):
            f.update(Measurement(S // 2, SOURCE_LOCAL, [0.1, 0.2, 0.3]))
        with pytest.raises(FloatingPointError, match="non-finite"):   # a hop (the Vega sees it) of 1e400 m^2
            f.update(Measurement(S + S // 5, SOURCE_GLOBAL, [1e200, 0.2, 0.3]),
                     Measurement(S + S // 5, SOURCE_LOCAL, [0.1, 0.2, 0.3]))
        assert f.time_ns is None   # reset


def test_the_registry_serves_the_fast_form():
    f = make_filter("fullperc", FullpercParams(rot_global_std=1e-3))
    assert isinstance(f, FullpercFilter) and f.params.rot_global_std == 1e-3


ULP_TOL = 1e-14   # ~45 ulp of 1.0: far below any formula error, above rounding differences between CPUs


def test_float_so3_equals_the_shared_module():
    """so3_float, the fast form's copy of fullperc_common.so3 on 9-tuples, gives the shared functions' results: Exp
    on both sides of its series threshold, Log near 0, in general and near pi (delegated), both branches of the
    quaternion conversion (trace > 0 and <= 0), the products -- to a few units in the last place: numpy's
    matmul and trigonometry round differently on different CPUs (an Exp entry 5 ulp off on one CI machine)."""
    rng = np.random.default_rng(3)
    ws = [rng.normal(size=3) / np.sqrt(3) * s for s in (1e-10, 1e-7, 1e-3, 0.5, 2.0, 3.1) for _ in range(25)]
    ws += [np.array([np.pi - 1e-5, 0.0, 0.0]), np.array([0.0, -(np.pi - 2e-5), 0.0]), np.zeros(3)]
    for w in ws:
        R = so3.so3_exp(w)
        R9 = exp9(*w.tolist())
        np.testing.assert_allclose(np.array(R9).reshape(3, 3), R, rtol=0, atol=ULP_TOL)
        R = np.array(R9).reshape(3, 3)
        np.testing.assert_allclose(log9(R9), so3.so3_log(R), rtol=0, atol=ULP_TOL)
        q = so3.R_to_quat(R)
        np.testing.assert_allclose(R9_to_quat(R9), q, rtol=0, atol=ULP_TOL)
        np.testing.assert_allclose(quat_to_R9(q * 1.7), so3.quat_to_R(q * 1.7).ravel(), rtol=0, atol=ULP_TOL)
        B = so3.so3_exp(rng.normal(size=3))
        B9 = tuple(B.ravel().tolist())
        np.testing.assert_allclose(mul9(R9, B9), (R @ B).ravel(), rtol=0, atol=ULP_TOL)
        np.testing.assert_allclose(mul9_t(R9, B9), (R @ B.T).ravel(), rtol=0, atol=ULP_TOL)
    assert sum(np.trace(so3.so3_exp(w)) <= 0 for w in ws) >= 20    # the other quaternion branch was exercised
