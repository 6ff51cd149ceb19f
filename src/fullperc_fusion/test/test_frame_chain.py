"""Frame chain (paper eq. 1 and 2), static-link estimation, pose validation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion.pipeline.frame_chain import BadSample, ChainConfig, FrameChain, pose_to_T

MS = 1_000_000


def _rand_T(rng, scale=2.0):
    return make_T(rng.uniform(-scale, scale, 3), Rot.random(random_state=rng).as_quat())


@pytest.fixture
def scene():
    """A consistent scene: every device pose derived from true omc-frame poses."""
    rng = np.random.default_rng(42)
    s = {"T_omc_base": _rand_T(rng), "T_omc_rig": _rand_T(rng), "T_rig_ots": _rand_T(rng, 0.2),
         "T_omc_tool": _rand_T(rng)}
    s["T_omc_ots"] = s["T_omc_rig"] @ s["T_rig_ots"]
    s["T_ots_tool"] = inv_T(s["T_omc_ots"]) @ s["T_omc_tool"]
    s["T_ots_base"] = inv_T(s["T_omc_ots"]) @ s["T_omc_base"]
    s["T_base_tool"] = inv_T(s["T_omc_base"]) @ s["T_omc_tool"]
    return s


def _feed_init(ch, s, n, t0=0):
    for k in range(n):
        t = t0 + k * 10 * MS
        ch.observe_omc("base", t, s["T_omc_base"])
        ch.observe_omc("ots_rig", t, s["T_omc_rig"])
        ch.observe_ots("base", t, s["T_ots_base"])


def test_global_measurement_is_inv_omc_base_times_omc_tool(scene):
    ch = FrameChain(ChainConfig(init_samples=3))
    assert ch.global_T(scene["T_omc_tool"]) is None and "T_omc_base" in ch.why_not
    _feed_init(ch, scene, 3)
    assert np.allclose(ch.global_T(scene["T_omc_tool"]), scene["T_base_tool"])


@pytest.mark.parametrize("mode,eq", [("static", "static"), ("tracked", "eq1"), ("direct", "eq2")])
def test_every_local_chain_gives_the_true_pose(scene, mode, eq):
    ch = FrameChain(ChainConfig(local_chain=mode, init_samples=3))
    _feed_init(ch, scene, 3)
    T, used = ch.local_T(20 * MS, scene["T_ots_tool"])   # stamp 20 ms = a fed OTS base frame
    assert used == eq
    assert np.allclose(T, scene["T_base_tool"])
    if mode == "tracked":   # T_rig_ots estimated from co-observation of the base marker
        assert np.allclose(ch.links.T_rig_ots, scene["T_rig_ots"])


def test_eq1_with_given_hand_eye_calibration(scene):
    # The OTS never sees the base marker: eq. (1) with the given T_rig_ots and the averaged OMC rig pose
    ch = FrameChain(ChainConfig(init_samples=3, T_rig_ots=scene["T_rig_ots"]))
    for k in range(3):
        ch.observe_omc("base", k, scene["T_omc_base"])
        ch.observe_omc("ots_rig", k, scene["T_omc_rig"])
    T, used = ch.local_T(0, scene["T_ots_tool"])
    assert used == "static" and np.allclose(T, scene["T_base_tool"])


def test_direct_mode_falls_back_to_static_link_without_a_same_frame_base_sample(scene):
    ch = FrameChain(ChainConfig(local_chain="direct", init_samples=3))
    _feed_init(ch, scene, 3)
    T, used = ch.local_T(25 * MS, scene["T_ots_tool"])   # no OTS base sample at 25 ms
    assert used == "static" and np.allclose(T, scene["T_base_tool"])


def test_tracked_mode_uses_nearest_rig_pose_and_refuses_stale_one(scene):
    ch = FrameChain(ChainConfig(local_chain="tracked", init_samples=3, rig_max_age_ns=5 * MS))
    _feed_init(ch, scene, 3)            # rig samples at 0, 10, 20 ms
    moved = scene["T_omc_rig"] @ make_T([0.1, 0, 0])
    ch.observe_omc("ots_rig", 30 * MS, moved)
    T, _ = ch.local_T(29 * MS, scene["T_ots_tool"])   # nearest rig sample: the moved one at 30 ms
    want = inv_T(scene["T_omc_base"]) @ moved @ scene["T_rig_ots"] @ scene["T_ots_tool"]
    assert np.allclose(T, want)
    T, _ = ch.local_T(100 * MS, scene["T_ots_tool"])
    assert T is None and "ots_rig" in ch.why_not


def test_local_link_waits_for_its_own_observations_global_does_not(scene):
    ch = FrameChain(ChainConfig(init_samples=5))
    for k in range(5):
        ch.observe_omc("base", k, scene["T_omc_base"])
    assert ch.links.global_ready and not ch.links.local_ready
    T, _ = ch.local_T(0, scene["T_ots_tool"])
    assert T is None and "T_base_ots" in ch.why_not
    for k in range(5):
        ch.observe_ots("base", k, scene["T_ots_base"])
    assert ch.links.local_ready


def test_static_link_uses_a_rotation_mean_not_a_component_average():
    # base marker observed at +-60 deg about z (an extreme spread): the entry-wise average of the
    # two matrices has cos 60 = 0.5 on the diagonal -- not a rotation. The rotation mean is identity.
    Ts = [make_T([0.1, 0, 0], Rot.from_euler("z", a, degrees=True).as_quat()) for a in (60, -60)]
    ch = FrameChain(ChainConfig(init_samples=2))
    for k, T in enumerate(Ts):
        ch.observe_omc("base", k, T)
    R = ch.links.T_omc_base[:3, :3]
    assert np.allclose(R, np.eye(3), atol=1e-9)
    assert not np.allclose(np.mean([T[:3, :3] for T in Ts], axis=0) @ np.mean([T[:3, :3] for T in Ts], axis=0).T,
                           np.eye(3))


def test_averaging_reduces_noise_of_the_static_link():
    rng = np.random.default_rng(0)
    T_true = make_T([0.5, -0.2, 1.0], Rot.from_euler("xyz", [10, 20, 30], degrees=True).as_quat())
    ch = FrameChain(ChainConfig(init_samples=400))
    for k in range(400):
        noise = make_T(rng.normal(0, 1e-3, 3), Rot.from_rotvec(rng.normal(0, 2e-3, 3)).as_quat())
        ch.observe_omc("base", k, T_true @ noise)
    T = ch.links.T_omc_base
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 3 * 1e-3 * np.sqrt(3) / np.sqrt(400) * 2
    ang = Rot.from_matrix(T[:3, :3].T @ T_true[:3, :3]).magnitude()
    assert ang < 2e-3 / 5


def test_reinitialize_keeps_old_links_until_new_ones_are_ready(scene):
    ch = FrameChain(ChainConfig(init_samples=3, static_links="average"))
    _feed_init(ch, scene, 3)
    old = ch.links.T_omc_base.copy()
    gen = ch.links.generation
    ch.reinitialize()
    moved = scene["T_omc_base"] @ make_T([0, 0, 0.05])
    for k in range(2):
        ch.observe_omc("base", 100 + k, moved)
    assert np.array_equal(ch.links.T_omc_base, old)          # still the old link
    ch.observe_omc("base", 200, moved)
    assert np.allclose(ch.links.T_omc_base, moved) and ch.links.generation > gen


@pytest.mark.parametrize("bad,why", [
    (([np.nan, 0, 0], [0, 0, 0, 1]), "non-finite"),
    (([np.inf, 0, 0], [0, 0, 0, 1]), "non-finite"),
    (([0, 0, 0], [0, 0, 0, 2.0]), "non-unit"),
    (([0, 0, 0], [0, 0, 0, 0.0]), "non-unit"),
    (([0, 0], [0, 0, 0, 1.0]), "shapes"),
    (np.diag([1, 1, 2, 1.0]), "not a rotation"),
    (np.diag([1, 1, -1, 1.0]), "not a rotation"),
])
def test_bad_poses_are_rejected_with_a_reason(bad, why):
    with pytest.raises(BadSample, match=why):
        pose_to_T(bad)


def test_nearly_unit_quaternion_is_renormalised():
    q = np.array([0, 0, np.sin(0.3), np.cos(0.3)]) * 1.004
    T = pose_to_T(([1, 2, 3], q))
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    assert np.allclose(T[:3, 3], [1, 2, 3])


def test_invalid_chain_config_is_named():
    with pytest.raises(ValueError, match="local_chain"):
        ChainConfig(local_chain="magic")
    with pytest.raises(ValueError, match="init_samples"):
        ChainConfig(init_samples=0)


def test_pose_to_T_equals_scipy_and_keeps_the_unit_threshold():
    """The float fast path of pose_to_T (issue 16) against scipy; the 1e-2 unit-norm threshold unchanged."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(20)
    for _ in range(2000):
        q = rng.normal(size=4)
        q *= (1.0 + rng.uniform(-0.0099, 0.0099)) / np.linalg.norm(q)
        if rng.uniform() < 0.5:
            q[3] = -abs(q[3])
        p = rng.normal(size=3)
        T = pose_to_T((p, q))
        ref = np.eye(4)
        ref[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
        ref[:3, 3] = p
        assert np.max(np.abs(T - ref)) <= 1e-12
    q = np.array([0.0, 0.0, np.sin(0.3), np.cos(0.3)])
    pose_to_T(([0, 0, 0], q * 1.0099))
    pose_to_T(([0, 0, 0], q * 0.9901))
    for f in (1.0101, 0.9899):
        with pytest.raises(BadSample, match="non-unit"):
            pose_to_T(([0, 0, 0], q * f))
    with pytest.raises(BadSample, match="non-finite"):
        pose_to_T(([0, 0, 0], [0, 0, np.nan, 1.0]))
    assert np.array_equal(pose_to_T(([1, 2, 3], (0, 0, 0, 1))),
                          [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])


def test_cached_inverse_of_the_global_link_follows_a_replaced_link():
    """global_T caches inv(T_omc_base) per link array (issue 16); a new link estimate must be used at once."""
    ch = FrameChain(ChainConfig())
    T = make_T([0.3, 0.1, 0.2], Rot.from_euler("xyz", [10, 20, 30], degrees=True).as_quat())
    for k in range(3):
        A = make_T([k, 0.5, -1.0], Rot.from_euler("z", 40 * k, degrees=True).as_quat())
        ch.links.T_omc_base = A
        assert np.array_equal(ch.global_T(T), inv_T(A) @ T)
        assert np.array_equal(ch.global_T(T), inv_T(A) @ T)   # from the cache: the same bits
