"""The fusion core's faster forms of a computation give the very numbers of the plain form (issue 38 item 5).

Each speed-up of the offline evaluation's hot paths keeps the arithmetic of what it replaces; these tests pin each one
to its plain form bit for bit (``tobytes`` / ``==`` on floats, not a tolerance), on random inputs and on the edge
cases where the fast form hands over to the plain one:

* :mod:`.calibration.so3_stack` against scipy's public ``Rotation`` calls (the robust SE(3) means);
* the robust mean's pieces (``_median0``, ``_mean_T_of``, the medoid's indices and medians, ``cov_rows``,
  ``stack_and_quats``) against numpy / ``mean_T`` / ``as_pose_stack``;
* the batched robust means (:mod:`.calibration.se3_batch`) against ``robust_se3_mean`` window by window, the static
  check through them against its former window-by-window loop, and the link monitor's deferred evaluations
  (``LinkMonitor.defer`` / ``resolve``) against evaluating each when it falls due;
* the stacked inverse of the eq. 2 link's sightings and the occluder test with its segments computed once;
* :func:`.calibration.poses.pose_to_T`'s 4x4 test on floats against the numpy expression, near its tolerance;
* the synchronizer's nearest-sample rule and its poll shortcut against a brute-force rule and a plain drain
  (the filter kernel's: test_paper_kernel_exact.py).
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import inv_T, make_T, mean_T
from fullperc_fusion.calibration import so3_stack
from fullperc_fusion.calibration.links import inv_T_stack
from fullperc_fusion.calibration.monitor import LinkMonitor, MonitorParams
from fullperc_fusion.calibration.poses import BadSample, pose_to_T
from fullperc_fusion.calibration.se3_batch import robust_se3_means
from fullperc_fusion.calibration.se3_stats import (
    _MEDOID_MAX,
    CalibrationError,
    StaticThresholds,
    _mean_T_of,
    _median0,
    as_pose_stack,
    cov_rows,
    medoid_medians,
    robust_se3_mean,
    se3_residuals,
    se3_retract,
    stack_and_quats,
)
from fullperc_fusion.calibration.static_check import check_static, hotelling_threshold
from fullperc_fusion.margin.geometry import Box, segments
from fullperc_fusion.pipeline.synchronizer import ApproxSync


def _rotations(rng: np.random.Generator, n: int, spread: float = 0.01) -> np.ndarray:
    """n rotation matrices near a random one (the robust mean's inputs: sightings of one still body)."""
    R0 = Rotation.random(rng=rng).as_matrix()
    return Rotation.from_rotvec(rng.normal(size=(n, 3)) * spread).as_matrix() @ R0


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


# ------------------------------------------------------------------------------------------- so3_stack
def test_the_scipy_backend_is_used_here():
    """The numbers below are only interesting where the fast path runs: the installed scipy has its backend (without
    it so3_stack takes scipy's public calls: the same numbers, the robust means ~2x slower)."""
    assert so3_stack.HAVE_BACKEND, "scipy's Cython Rotation backend is missing: so3_stack runs its slow fallback"


@pytest.mark.parametrize("seed", range(6))
def test_quats_and_rotvecs_equal_scipy(seed):
    rng = np.random.default_rng(seed)
    for n, spread in ((1, 0.01), (60, 0.003), (300, 0.05), (17, 3.0)):
        R = _rotations(rng, n, spread)
        # products like the residuals' R_i R_ref^T: orthogonal to rounding, not exactly
        R = R @ Rotation.random(rng=rng).as_matrix().T
        assert _same(so3_stack.quats(R), Rotation.from_matrix(R).as_quat())
        assert _same(so3_stack.rotvecs(R), Rotation.from_matrix(R).as_rotvec())
        assert _same(so3_stack.rotvecs(R[:, :, :]), Rotation.from_matrix(R).as_rotvec())   # a strided view too


def test_quats_hand_other_matrices_to_scipy():
    """Not (nearly) orthogonal, a reflection, NaN: scipy's own result or error, whatever it is."""
    rng = np.random.default_rng(7)
    R = _rotations(rng, 20)
    off = R.copy()
    off[3] *= 1.0 + 1e-9                        # past the 1e-13 the fast path vouches for: scipy's SVD path
    off[5, 0, 1] += 2e-12
    assert _same(so3_stack.quats(off), Rotation.from_matrix(off).as_quat())
    near = R.copy()
    near[4, 0, 0] += 5e-14                      # within it: scipy's own tests pass too
    assert _same(so3_stack.quats(near), Rotation.from_matrix(near).as_quat())
    bad = R.copy()
    bad[2] = -bad[2]                            # det -1
    with pytest.raises(ValueError):
        Rotation.from_matrix(bad)
    with pytest.raises(ValueError):
        so3_stack.quats(bad)
    nan = R.copy()
    nan[1, 2, 2] = np.nan
    with np.errstate(invalid="ignore"):
        try:
            want: object = Rotation.from_matrix(nan).as_quat()
        except Exception as e:  # noqa: BLE001 - whatever scipy does, the fast path does the same
            want = type(e)
        try:
            got: object = so3_stack.quats(nan)
        except Exception as e:  # noqa: BLE001
            got = type(e)
    assert (got is want) if isinstance(want, type) else _same(got, want)


@pytest.mark.parametrize("seed", range(4))
def test_mean_rotation_of_rows_equals_scipys_mean_of_the_subset(seed):
    rng = np.random.default_rng(10 + seed)
    R = _rotations(rng, 80, 0.02)
    q = so3_stack.quats(R)
    for rows in (np.ones(80, bool), rng.random(80) < 0.7, np.flatnonzero(rng.random(80) < 0.3)):
        want = Rotation.from_matrix(R[rows]).mean().as_matrix()
        assert _same(so3_stack.mean_rotation(R, q, rows), want)


# ------------------------------------------------------------------------------- robust mean's pieces
def test_median0_is_numpys_median():
    rng = np.random.default_rng(3)
    for shape in ((1, 3), (2, 6), (59, 6), (60, 6), (61, 3), (256, 256)):
        x = rng.normal(size=shape)
        assert _same(_median0(x), np.median(x, axis=0))
    x = rng.normal(size=(9, 4))
    x[4, 1] = np.nan                            # NaN columns: np.median's own answer
    assert np.array_equal(_median0(x), np.median(x, axis=0), equal_nan=True)
    x = np.round(rng.normal(size=(40, 3)), 1)   # ties
    assert _same(_median0(x), np.median(x, axis=0))


def test_mean_of_a_mask_is_mean_T_of_the_subset():
    rng = np.random.default_rng(4)
    Ts = np.zeros((70, 4, 4))
    Ts[:, :3, :3] = _rotations(rng, 70, 0.01)
    Ts[:, :3, 3] = rng.normal(size=(70, 3)) * 1e-3 + [0.3, -1.2, 2.0]
    Ts[:, 3, 3] = 1.0
    q = so3_stack.quats(Ts[:, :3, :3])
    for mask in (np.ones(70, bool), rng.random(70) < 0.6):
        assert _same(_mean_T_of(Ts, q, mask), mean_T(list(Ts[mask])))


def test_medoid_indices_are_every_sample_up_to_the_cap():
    for n in range(1, _MEDOID_MAX + 1):
        spaced = np.unique(np.linspace(0, n - 1, min(n, _MEDOID_MAX)).round().astype(int))
        assert np.array_equal(spaced, np.arange(n))


def test_robust_mean_is_deterministic_across_subsets_and_views():
    """The quaternions of the stack are converted once and reused: the estimate of a stack does not depend on
    whether it arrives as a view, a copy or as (positions, quaternions)."""
    rng = np.random.default_rng(5)
    Ts = np.zeros((120, 4, 4))
    Ts[:, :3, :3] = _rotations(rng, 120, 0.002)
    Ts[:, :3, 3] = rng.normal(size=(120, 3)) * 2e-4
    Ts[:, 3, 3] = 1.0
    Ts[::17, :3, 3] += 0.01                     # outliers
    a = robust_se3_mean(Ts)
    b = robust_se3_mean(np.ascontiguousarray(Ts[::1]))
    for k in ("position", "quat_xyzw", "cov", "inliers"):
        assert _same(getattr(a, k), getattr(b, k))
    assert a.n_inliers < 120


def _poses(rng: np.random.Generator, n: int, spread: float = 0.003, noise: float = 2e-4,
           outliers: float = 0.0) -> np.ndarray:
    """n sightings (n, 4, 4) of one still body, a share of them ``outliers`` (a step of 1 cm)."""
    Ts = np.zeros((n, 4, 4))
    Ts[:, :3, :3] = _rotations(rng, n, spread)
    Ts[:, :3, 3] = rng.normal(size=(n, 3)) * noise + rng.normal(size=3)
    Ts[:, 3, 3] = 1.0
    out = rng.random(n) < outliers
    Ts[out, :3, 3] += 0.01
    return Ts


def test_medoid_medians_are_the_medians_of_the_angles():
    rng = np.random.default_rng(12)
    for m in (1, 2, 3, 60, 61, 256):
        q = so3_stack.quats(_rotations(rng, m, rng.choice([1e-4, 0.01, 1.0])))
        want = _median0(2.0 * np.arccos(np.clip(np.abs(q @ q.T), 0.0, 1.0)))
        assert _same(medoid_medians(q), want)
        qs = np.stack([q, q[::-1].copy(), q * -1.0])                  # stacked: each window its own medians
        got = medoid_medians(qs)
        assert got is not None
        for w in range(3):
            assert _same(got[w], _median0(2.0 * np.arccos(np.clip(np.abs(qs[w] @ qs[w].T), 0.0, 1.0))))
    q[3] = np.nan
    assert medoid_medians(q) is None                                 # np.median's own path then


def test_cov_rows_is_numpys_cov():
    rng = np.random.default_rng(13)
    for shape in ((2, 6), (3, 3), (59, 6), (60, 6), (1201, 6)):
        r = rng.normal(size=shape) * rng.choice([1e-6, 1e-3, 1.0])
        assert _same(cov_rows(r), np.cov(r, rowvar=False, ddof=1))
        assert _same(cov_rows(r[::2] if len(r) > 3 else r), np.cov(r[::2] if len(r) > 3 else r, rowvar=False, ddof=1))


def _outcome(f, *args):
    """The stack ``f`` returns (its bytes and shape), or the message of the CalibrationError it raises."""
    try:
        out = f(*args)
    except CalibrationError as e:
        return str(e)
    return out.shape, out.tobytes()


def test_stack_and_quats_is_as_pose_stack_then_quats():
    rng = np.random.default_rng(14)
    Ts = _poses(rng, 40)
    got, q = stack_and_quats(Ts, "x")
    assert got is Ts and _same(q, so3_stack.quats(Ts[:, :3, :3]))
    rounded = Ts.copy()
    rounded[:, :3, :3] = np.round(rounded[:, :3, :3], 4)              # rotations to 1e-4 only: the full test runs
    got, q = stack_and_quats(rounded, "x")
    assert _same(got, as_pose_stack(rounded, "x")) and _same(q, so3_stack.quats(rounded[:, :3, :3]))
    for bad in (Ts[:, :3], Ts[:1], np.zeros((0, 4, 4))):
        assert _outcome(lambda b: stack_and_quats(b, "x")[0], bad) == _outcome(lambda b: as_pose_stack(b, "x"), bad)
    for k, edit in enumerate(("nan", "reflection", "sheared", "short")):
        b = Ts.copy() if edit != "short" else Ts[:1].copy()
        if edit == "nan":
            b[3, 1, 3] = np.nan
        elif edit == "reflection":
            b[5, :3, :3] *= -1.0
        elif edit == "sheared":
            b[7, 0, 1] += 0.05
        else:
            b[0, :3, :3] *= -1.0                                    # one pose, not a rotation: that error first
        want = _outcome(lambda x: as_pose_stack(x, "x"), b)
        assert _outcome(lambda x: stack_and_quats(x, "x")[0], b) == want and isinstance(want, str), k
    p, qq = Ts[:, :3, 3], so3_stack.quats(Ts[:, :3, :3])             # (positions, quaternions): as_pose_stack's
    got, q = stack_and_quats((p, qq), "x")
    assert _same(got, as_pose_stack((p, qq), "x")) and _same(q, so3_stack.quats(got[:, :3, :3]))


def _plain(Ts: np.ndarray) -> tuple[bytes, bytes] | None:
    try:
        e = robust_se3_mean(Ts)
    except CalibrationError:
        return None
    return e.T.tobytes(), np.asarray(e.inliers).tobytes()


@pytest.mark.parametrize("seed", range(4))
def test_batched_robust_means_equal_robust_se3_mean(seed):
    rng = np.random.default_rng(20 + seed)
    cases = 0
    for n, outliers in ((2, 0.0), (3, 0.4), (10, 0.3), (60, 0.05), (61, 0.5), (60, 0.8), (300, 0.1)):
        M = n + int(rng.integers(0, 200))
        Ts = _poses(rng, M, rng.choice([1e-4, 3e-3, 0.05]), rng.choice([1e-5, 2e-4, 1e-3]), outliers)
        if seed == 1:
            Ts[:, :3, 3] = np.round(Ts[:, :3, 3], 5)                    # quantised: ties in the medians
        if seed == 2:
            Ts[: M // 3] = Ts[0]                                        # many equal sightings
        W = int(rng.integers(1, 8))
        rows = rng.integers(0, M - n + 1, size=W)[:, None] + np.arange(n)
        if seed == 3:
            rows = np.stack([np.sort(rng.choice(M, n, replace=False)) for _ in range(W)])   # any indices
        for row, got in zip(rows, robust_se3_means(Ts, rows), strict=True):
            want = _plain(Ts[row])
            assert (got is None and want is None) or (got is not None and want is not None
                                                      and (got[0].tobytes(), got[1].tobytes()) == want)
            cases += want is not None
    assert cases > 10
    Ts = _poses(rng, 80)
    Ts[40, :3, :3] *= -1.0                                              # not a stack of poses: window by window
    rows = np.array([np.arange(0, 30), np.arange(30, 60)])
    got = robust_se3_means(Ts, rows)
    assert got[1] is None and got[0] is not None and (got[0][0].tobytes(), got[0][1].tobytes()) == _plain(Ts[:30])
    assert robust_se3_means(Ts, np.zeros((0, 5), int)) == [] and robust_se3_means(Ts, [[3]]) == [None]


def _check_static_plain(label, stamps_ns, poses, th: StaticThresholds, alpha: float) -> None:
    """check_static as it was written before the batched means: robust_se3_mean window by window (the reference)."""
    Ts = as_pose_stack(poses, label)
    t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    t0, span = int(t.min()), int(t.max()) - int(t.min())
    nw = int(th.n_windows)
    w = np.minimum((t - t0) * nw // max(span, 1), nw - 1) if span > 0 else np.zeros(len(t), dtype=int)
    wins, resid = [], []
    for k in range(nw):
        sel = w == k
        if sel.sum() >= max(th.min_window_samples, 2):
            try:
                e = robust_se3_mean(Ts[sel], alpha=alpha, what=label)
            except CalibrationError:
                continue
            r = se3_residuals(e.T, Ts[sel][e.inliers])
            resid.append(r - r.mean(axis=0))
            wins.append((k, e))
    if len(wins) < 2:
        raise CalibrationError("too few windows")
    R = np.vstack(resid)
    dof = len(R) - len(wins)
    C = R.T @ R / dof + np.diag(np.repeat(np.square((1e-6, 1e-6)), 3))
    q = hotelling_threshold(th.alpha, dof)
    worst = None
    for i in range(len(wins)):
        for j in range(i + 1, len(wins)):
            (ka, a), (kb, b) = wins[i], wins[j]
            d = se3_residuals(a.T, b.T[None])[0]
            S = C * (1.0 / a.n_inliers + 1.0 / b.n_inliers)
            dt, dr = float(np.linalg.norm(d[:3])), float(np.linalg.norm(d[3:]))
            moved = (dt > th.max_drift_m and d[:3] @ np.linalg.solve(S[:3, :3], d[:3]) > q) or \
                (dr > th.max_drift_rad and d[3:] @ np.linalg.solve(S[3:, 3:], d[3:]) > q)
            score = max(dt / th.max_drift_m, dr / th.max_drift_rad)
            if moved and (worst is None or score > worst[0]):
                worst = (score, ka, kb, dt, dr)
    if worst is not None:
        raise CalibrationError(f"moved {worst[1:]}")


def test_static_check_through_the_batched_means_decides_as_window_by_window():
    rng = np.random.default_rng(15)
    th = StaticThresholds()
    verdicts = set()
    for k in range(60):
        n = int(rng.integers(8, 700))
        t = np.sort(rng.integers(0, 10**10, n)) if k % 3 else np.arange(n) * 8_333_333
        Ts = _poses(rng, n, rng.choice([1e-4, 2e-3]), rng.choice([1e-5, 3e-4, 2e-3]), rng.choice([0.0, 0.2]))
        if k % 4 == 0:
            Ts[n // 2:, :3, 3] += rng.normal(size=3) * 3e-3                      # moved half-way
        try:
            _check_static_plain("x", t, Ts, th, 1e-3)
            want = "still"
        except CalibrationError as e:
            want = "moved" if str(e).startswith("moved") else "refused"
        try:
            check_static("x", t, Ts, th, 1e-3)
            got = "still"
        except CalibrationError as e:
            got = "moved" if "moved during the collection" in str(e) else "refused"
        assert got == want, k
        verdicts.add(got)
    assert verdicts == {"still", "moved", "refused"}


def _run_monitor(deferred: bool, data, params: MonitorParams, refs) -> tuple:
    mon = LinkMonitor(params)
    if deferred:
        mon.defer()
    checks = []
    for k, (t, T) in enumerate(data):
        if k in refs:
            mon.set_reference(refs[k])
        c = mon.add(t, T)
        if c is not None:
            checks.append(c)
    if deferred:
        assert not checks and not mon.n_checks   # nothing computed before resolve
        checks = mon.resolve()
    return checks, (mon.n_checks, mon.n_bumped_checks, mon.bumped, mon.first_bump_ns, mon.last)


@pytest.mark.parametrize("seed", range(3))
def test_deferred_link_checks_equal_the_checks_as_they_fall_due(seed):
    """Deferred (the batched evaluator) against plain: every check (stamp, bumped, sizes, counts), the state after,
    across bumps, a marker put back, references set and cleared mid-stream, and windows of changing length."""
    rng = np.random.default_rng(30 + seed)
    T_ref = make_T([0.2, -0.1, -1.9], Rotation.from_euler("xyz", [170.0, 10.0, 30.0], degrees=True).as_quat())
    sig = np.array([0.1e-3, 0.1e-3, 0.3e-3, 3e-3, 3e-3, 3e-3])
    data, t = [], 10**18
    for k in range(1500):
        t += int(rng.choice([16_666_667, 15_000_000, 40_000_000]))
        d = rng.normal(size=6) * sig
        if 400 <= k < 700:
            d[0] += 3e-3                                 # a bump, then put back
        if rng.random() < 0.02:
            d[:3] += 0.05                                # outliers
        data.append((t, se3_retract(T_ref, d)))
    refs = {0: T_ref, 900: T_ref @ make_T([1e-3, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]), 1100: None, 1150: T_ref}
    for k, params in enumerate((MonitorParams(), MonitorParams(window_s=0.5, min_samples=25),
                                MonitorParams(enabled=False))):
        plain, plain_state = _run_monitor(False, data, params, refs)
        got, got_state = _run_monitor(True, data, params, refs)
        assert got == plain and got_state == plain_state
        assert len(plain) > (40, 10, -1)[k]
        if k == 0:
            assert any(c.bumped for c in plain) and not all(c.bumped for c in plain)


def test_inverse_of_a_stack_is_inv_T_of_each():
    rng = np.random.default_rng(16)
    for n in (1, 2, 60, 601):
        Ts = _poses(rng, n, 1.0, 3.0)
        Ts[:, :3, :3] += rng.normal(size=(n, 3, 3)) * 1e-6 * (n % 2)     # not orthogonal to rounding either
        assert _same(inv_T_stack(Ts), np.stack([inv_T(T) for T in Ts]))


def test_box_blocks_with_its_segments_computed_once():
    rng = np.random.default_rng(17)
    cams, pts = rng.uniform(-3.0, 3.0, (1, 12, 3)), rng.uniform(-2.0, 2.0, (500, 1, 3))
    pts[0, 0] = cams[0, 0]                               # at a camera (d = 0)
    seg = segments(cams, pts)
    for _ in range(20):
        lo = rng.uniform(-1.0, 0.5, 3)
        box = Box("b", lo, lo + rng.uniform(0.05, 1.0, 3))
        assert np.array_equal(box.blocks(None, None, seg), box.blocks(cams, pts))


# -------------------------------------------------------------------------------------------- pose_to_T
def _numpy_rotation_test(T: np.ndarray, tol: float) -> bool:
    R = T[:3, :3]
    return not (np.max(np.abs(R.T @ R - np.eye(3))) > tol or np.linalg.det(R) < 0)


def test_pose_to_T_4x4_decides_as_the_numpy_expression():
    rng = np.random.default_rng(6)
    for k in range(4000):
        T = make_T(rng.normal(size=3), R=Rotation.random(rng=rng).as_matrix())
        kind = k % 5
        if kind == 1:
            T[:3, :3] *= 1.0 + rng.choice([-1.0, 1.0]) * 0.005 * (1.0 + rng.normal() * 1e-12)   # |err| ~ tol
        elif kind == 2:
            T[:3, 0] *= math.sqrt(1.0 + 1e-2 * (1.0 + rng.normal() * 1e-10))               # err right at tol
        elif kind == 3:
            T[:3, :3] = -T[:3, :3]                                                         # det -1
        elif kind == 4:
            T[0, :3] += rng.normal(size=3) * 1e-2
        for tol in (1e-2, 1e-3, 0.3):
            ok = _numpy_rotation_test(T, tol)
            try:
                out = pose_to_T(T, tol)
                assert ok and out is T
            except BadSample as e:
                assert not ok and "not a rotation" in str(e)


def test_pose_to_T_4x4_rejections_in_order():
    T = np.eye(4)
    T[1, 2] = np.nan
    with pytest.raises(BadSample, match="non-finite"):
        pose_to_T(T)
    T = np.eye(4)
    T[3, 0] = 1e-17
    with pytest.raises(BadSample, match="last row"):
        pose_to_T(T)
    T = np.eye(4)
    T[3, 1] = -0.0                               # -0.0 == 0.0, as in the numpy comparison
    assert pose_to_T(T) is T


def test_pose_to_T_quaternion_norm_is_numpys():
    rng = np.random.default_rng(8)
    for _ in range(2000):
        q = rng.normal(size=4)
        q = (q / np.linalg.norm(q) * (1.0 + rng.uniform(-5e-3, 5e-3))).astype(np.float32).astype(float)
        x, y, z, w = (q / float(np.linalg.norm(q))).tolist()
        want = make_T([0.1, 0.2, 0.3], [x, y, z, w])   # quat_to_R_rows normalises again, as pose_to_T does
        assert _same(pose_to_T(([0.1, 0.2, 0.3], q)), want)


# ------------------------------------------------------------------------------------------ synchronizer
def test_nearest_is_the_brute_force_rule():
    rng = random.Random(2)
    s = ApproxSync()
    for _ in range(3000):
        ts = sorted(set(rng.randint(0, 60) for _ in range(rng.randint(1, 8))))
        s._t = (ts, [])
        t = rng.randint(-5, 65)
        want = min(range(len(ts)), key=lambda j: (abs(ts[j] - t), ts[j]))
        assert s._nearest(0, t) == want


def _items(items):
    return [(i.t_ns, i.glob and (i.glob.t_ns, i.glob.payload), i.local and (i.local.t_ns, i.local.payload), i.source)
            for i in items]


def test_poll_equals_a_plain_drain():
    """poll's shortcut (nothing final, no overflow: no drain) gives what draining with its rule gives."""
    rng = random.Random(3)
    for _ in range(500):
        slop, delay, maxp = rng.choice([0, 2, 5]), rng.choice([0, 7, 30]), rng.choice([2, 4096])
        a, b = ApproxSync(slop, delay, max_pending=maxp), ApproxSync(slop, delay, max_pending=maxp)
        t = [0, 0]
        for k in range(60):
            st = rng.randint(0, 1)
            t[st] = max(1, t[st] + rng.randint(-4, 15))
            assert a.push(st, t[st], k) == b.push(st, t[st], k)
            now = a.watermark_ns if rng.random() < 0.7 else rng.randint(0, 400)
            got = a.poll(now)
            lag = 2 * b.slop + b.delay
            want = [] if now is None else b._drain(lambda x, n=now, lag=lag: n >= x + lag)
            assert _items(got) == _items(want)
        assert _items(a.flush()) == _items(b.flush()) and a.counts == b.counts
