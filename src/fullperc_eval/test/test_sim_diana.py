"""Diana 7 model as used by the simulator: FK reference values, arcs, link capsules."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_drivers.diana_kinematics import DianaKinematics
from fullperc_eval.sim.trajectories import JointArc, arm_geometry, link_capsules, min_jerk


def test_fk_at_zero_matches_reference():
    # reference/diana_eval.md §1.1: at q = 0 the arm points straight up, flange at (-0.087, 0, 1.3165) m
    origins, flange = arm_geometry(DianaKinematics(), np.zeros((1, 7)))
    np.testing.assert_allclose(flange[0, :3, 3], [-0.087, 0.0, 1.3165], atol=1e-9)
    np.testing.assert_allclose(origins[0, 0], [0, 0, 0.2856], atol=1e-9)  # base -> shoulder 285.6 mm


def test_batch_geometry_equals_shared_fk():
    dk = DianaKinematics()
    Q = np.random.default_rng(0).uniform(dk.lower, dk.upper, size=(20, 7))
    _, flange = arm_geometry(dk, Q)
    for q, T in zip(Q, flange, strict=True):
        np.testing.assert_allclose(T, dk.fk(q), atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], dk.joint_origins(q)[-1], atol=1e-12)


def test_min_jerk_profile_is_smooth():
    u = np.linspace(0, 1, 1001)
    s, ds = min_jerk(u)
    assert s[0] == 0 and s[-1] == pytest.approx(1.0) and ds[0] == 0 and ds[-1] == pytest.approx(0.0)
    np.testing.assert_allclose(np.gradient(s, u), ds, atol=1e-3)
    assert ds.max() == pytest.approx(1.875)


def test_arc_moves_one_joint_with_consistent_velocity():
    q0 = (0.1, 0.5, -0.2, 1.2, 0.3, 0.4, 0.0)
    arc = JointArc(q0, joint=1, start=0.5, end=-0.3, move=10.0, hold_start=1.0, hold_end=2.0)
    t = np.linspace(0, arc.duration, 2601)
    Q, dQ = arc.sample(t)
    assert arc.duration == 13.0
    others = np.delete(np.arange(7), 1)
    np.testing.assert_array_equal(Q[:, others], np.tile(np.asarray(q0)[others], (len(t), 1)))
    assert Q[0, 1] == pytest.approx(0.5) and Q[-1, 1] == pytest.approx(-0.3)
    assert np.all(Q[t <= 1.0, 1] == 0.5) and np.all(dQ[t >= 11.0] == 0)
    np.testing.assert_allclose(np.gradient(Q[:, 1], t), dQ[:, 1], atol=2e-4)
    assert np.abs(dQ[:, 1]).max() == pytest.approx(arc.peak_velocity, rel=1e-3)


def test_link_capsules_follow_the_arm_and_spare_the_flange():
    dk = DianaKinematics()
    T = np.eye(4)
    T[:3, 3] = [0.2, -0.65, 0.8]
    origins, flange = arm_geometry(dk, np.zeros((1, 7)))
    a, b, r = link_capsules(origins, T)
    assert a.shape == b.shape == (1, len(r), 3)
    np.testing.assert_allclose(a[0, 0], T[:3, 3])  # the base column starts at the base
    fl = T[:3, 3] + flange[0, :3, 3]
    assert np.linalg.norm(b[0, -1] - fl) >= r[-1]  # the last capsule's cap ends short of the flange face
