"""Pins the quaternion orders and transform conventions every package relies on."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import (
    apply_T,
    inv_T,
    is_finite_pose,
    make_T,
    mean_T,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
)


def test_ndi_wxyz_to_ros_xyzw():
    # 90 deg about z: NDI sends q0=cos45, qz=sin45 first-scalar; ROS wants (0, 0, s, c)
    c = np.sqrt(0.5)
    assert np.allclose(quat_wxyz_to_xyzw([c, 0, 0, c]), [0, 0, c, c])
    assert np.allclose(quat_xyzw_to_wxyz([0, 0, c, c]), [c, 0, 0, c])
    # and the result means a 90 deg z rotation in scipy's (x y z w) convention
    R = Rotation.from_quat(quat_wxyz_to_xyzw([c, 0, 0, c])).as_matrix()
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])


def test_round_trip_order_vectorised():
    q = Rotation.random(5, random_state=1).as_quat()
    assert np.allclose(quat_wxyz_to_xyzw(quat_xyzw_to_wxyz(q)), q)


def test_T_maps_b_into_a_and_inverse():
    T = make_T([1, 2, 3], Rotation.from_euler("z", 90, degrees=True).as_quat())
    assert np.allclose(apply_T(T, [1, 0, 0]), [1, 3, 3])
    assert np.allclose(inv_T(T) @ T, np.eye(4))


def test_mean_T_is_rotation_mean_not_component_average():
    Rs = Rotation.from_euler("z", [[-170], [170]], degrees=True)
    Ts = [make_T([0, 0, 0], q) for q in Rs.as_quat()]
    M = mean_T(Ts)
    # the two rotations straddle 180 deg; their mean is 180 deg, a component average would be ~0
    assert np.allclose(Rotation.from_matrix(M[:3, :3]).magnitude(), np.pi, atol=1e-9)


def test_mean_T_empty_raises():
    with pytest.raises(ValueError):
        mean_T([])


@pytest.mark.parametrize(
    "p,q,ok",
    [
        ([0, 0, 0], [0, 0, 0, 1], True),
        ([np.nan, 0, 0], [0, 0, 0, 1], False),
        ([0, 0, 0], [0, 0, 0, 2], False),
        ([0, np.inf, 0], [0, 0, 0, 1], False),
    ],
)
def test_is_finite_pose(p, q, ok):
    assert is_finite_pose(p, q) is ok
