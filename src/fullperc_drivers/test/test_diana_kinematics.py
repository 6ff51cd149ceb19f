"""Diana 7 FK against reference/diana_eval.md and against an independent plain-numpy DH product."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fullperc_drivers.diana_kinematics import DIANA7_MDH, DianaKinematics


def _mdh_product(q, rows):
    """Craig modified DH written out directly: RotX(alpha) TransX(a) RotZ(theta+q) TransZ(d)."""
    T = np.eye(4)
    for (alpha, a, d, theta), qi in zip(rows, q, strict=True):
        ca, sa = np.cos(alpha), np.sin(alpha)
        ct, stt = np.cos(theta + qi), np.sin(theta + qi)
        rx = np.array([[1, 0, 0, 0], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1.0]])
        tx = np.eye(4)
        tx[0, 3] = a
        rz = np.array([[ct, -stt, 0, 0], [stt, ct, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        tz = np.eye(4)
        tz[2, 3] = d
        T = T @ rx @ tx @ rz @ tz
    return T


# Table typed in from reference/diana_eval.md §1.1 (alpha_{i-1}, a_{i-1}, d_i, theta_i) — not imported from
# the module under test, so a typo in DIANA7_MDH fails here.
_DOC_TABLE = [
    (np.pi, 0, -0.2856, 0), (np.pi / 2, 0, 0, 0), (-np.pi / 2, 0, -0.4586, 0), (np.pi / 2, 0.065, 0, 0),
    (-np.pi / 2, -0.0528, -0.4554, 0), (-np.pi / 2, -0.0122, 0, np.pi), (-np.pi / 2, 0.087, -0.1169, 0),
]


def test_table_matches_reference_doc():
    assert np.allclose(DIANA7_MDH, np.array(_DOC_TABLE, dtype=float))


def test_zero_pose_flange_position_from_reference():
    # reference/diana_eval.md: "At q = 0 the arm points straight up: flange at (-0.087, 0, 1.3165) m".
    T = DianaKinematics().fk(np.zeros(7))
    assert np.allclose(T[:3, 3], [-0.087, 0.0, 1.3165], atol=1e-9)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_shoulder_to_wrist_reach_from_reference():
    # reference/diana_eval.md: max shoulder (z = 0.2856) -> joint-6 origin distance = 0.9232 m. It depends on q4 only.
    kin = DianaKinematics()
    lo, hi = kin.joint_limits
    dists = []
    for q4 in np.linspace(lo[3], hi[3], 3501):
        o = kin.joint_origins([0, 0, 0, q4, 0, 0, 0])
        dists.append(np.linalg.norm(o[5] - [0, 0, 0.2856]))
    assert max(dists) == pytest.approx(0.9232, abs=5e-5)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-3.1, 3.1), min_size=7, max_size=7))
def test_pinocchio_model_equals_plain_dh_product(q):
    assert np.allclose(DianaKinematics().fk(q), _mdh_product(q, _DOC_TABLE), atol=1e-12)


def test_tool_offset_and_batch():
    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
    off[:3, 3] = [0.01, -0.02, 0.15]
    kin = DianaKinematics(tool_offset=off)
    rng = np.random.default_rng(1)
    lo, hi = kin.joint_limits
    Q = rng.uniform(lo, hi, size=(20, 7))
    flange = kin.fk_many(Q)
    tool = kin.fk_many(Q, tool=True)
    for k, q in enumerate(Q):
        assert np.allclose(flange[k], _mdh_product(q, _DOC_TABLE), atol=1e-12)
        assert np.allclose(tool[k], _mdh_product(q, _DOC_TABLE) @ off, atol=1e-12)
        assert np.allclose(kin.fk_tool(q), tool[k])
    # 7-number form: x y z qx qy qz qw
    kin7 = DianaKinematics(tool_offset=[0.01, -0.02, 0.15, *Rotation.from_matrix(off[:3, :3]).as_quat()])
    assert np.allclose(kin7.fk_tool(Q[0]), tool[0], atol=1e-12)


def test_batch_fk_is_the_single_fk_bit_for_bit_and_refuses_nan():
    """fk_many validates the batch once (not per row, issue 38 item 5): the same poses as fk row by row, also for a
    strided batch, and the same error for a NaN anywhere."""
    kin = DianaKinematics()
    rng = np.random.default_rng(2)
    lo, hi = kin.joint_limits
    Q = rng.uniform(lo, hi, size=(50, 7))
    for batch in (Q, np.asfortranarray(Q), Q[::2]):
        want = np.stack([kin.fk(q) for q in batch])
        assert kin.fk_many(batch).tobytes() == want.tobytes()
        assert kin.fk_many(batch, tool=True).tobytes() == np.stack([kin.fk_tool(q) for q in batch]).tobytes()
    bad = Q.copy()
    bad[30, 4] = np.nan
    with pytest.raises(ValueError, match="NaN/inf"):
        kin.fk_many(bad)


def test_getdh_arrays_build_same_model_and_change_fk():
    a, alpha, d, theta = DIANA7_MDH[:, 1], DIANA7_MDH[:, 0], DIANA7_MDH[:, 2], DIANA7_MDH[:, 3]
    q = np.array([0.3, -0.4, 0.5, 1.0, -0.2, 0.7, 0.1])
    assert np.allclose(DianaKinematics.from_getdh(a, alpha, d, theta).fk(q), DianaKinematics().fk(q))
    d2 = d.copy()
    d2[0] -= 0.001  # a 1 mm longer base (d1 is negative along a flipped z)
    moved = DianaKinematics.from_getdh(a, alpha, d2, theta).fk(q)[:3, 3] - DianaKinematics().fk(q)[:3, 3]
    assert np.linalg.norm(moved) == pytest.approx(0.001, abs=1e-9)


def test_joint_limits_and_bad_input():
    kin = DianaKinematics()
    lo, hi = kin.joint_limits
    assert lo.shape == hi.shape == (7,) and np.all(lo < hi)
    assert lo[3] == 0.0 and hi[3] == pytest.approx(np.deg2rad(175))
    assert hi[1] == pytest.approx(np.pi / 2) and hi[0] == pytest.approx(3.1241, abs=1e-4)
    assert kin.within_limits(np.zeros(7)) and not kin.within_limits([0, 0, 0, -0.1, 0, 0, 0])
    with pytest.raises(ValueError):
        kin.fk(np.zeros(6))
    with pytest.raises(ValueError):
        kin.fk([0, 0, np.nan, 0, 0, 0, 0])
    with pytest.raises(ValueError):
        DianaKinematics(dh=np.zeros((6, 4)))
    with pytest.raises(ValueError):
        DianaKinematics(tool_offset=np.ones((4, 4)))
