"""Layout file parsing, camera/OTS geometry helpers, the OTS frustum and eq. (17), against hand-computed values."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fullperc_fusion.margin import geometry, layout
from fullperc_fusion.margin.geometry import NDI_PYRAMID_PLANES, Box, eq17_theta_prime_deg, look_at_R, look_at_R_ndi
from fullperc_fusion.margin.layout import LayoutError, default_layout_path, load_layout, parse_layout


def minimal(**over) -> dict:
    d = {
        "frame_id": "omc",
        "cameras": [
            {"name": "a", "position": [2.0, 0.0, 1.0], "orientation": [0.0, 0.0, 0.0, 1.0]},
            {"name": "b", "position": [0.0, 2.0, 1.0], "orientation": [0.0, 0.0, 0.0, 1.0]},
        ],
    }
    d.update(over)
    return d


def write(tmp_path: Path, data: dict, name: str = "layout.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


# ------------------------------------------------------------------------------------------ default layout
def test_default_layout_path_is_the_shared_share_lookup():
    from fullperc_common.share import share_path

    assert default_layout_path() == share_path("fullperc_fusion", "config", "or_layout.yaml")


def test_default_layout_is_the_designed_room():
    L = load_layout(default_layout_path())
    assert L.frame_id == "omc" and L.n_cameras == 12
    assert len({c.name for c in L.cameras}) == 12
    for c in L.cameras:
        assert np.allclose(c.R.T @ c.R, np.eye(3), atol=1e-5) and np.linalg.det(c.R) > 0.9999
        assert 30.0 <= c.tilt_deg <= 45.0  # mounted 30-45 deg down (issue text)
        assert c.position[2] == pytest.approx(2.6)
        assert np.all(np.abs(c.position[:2]) <= [3.0, 2.5])  # inside the 6 x 5 m room
        assert c.range_m == 4.0
        # every camera looks at the table centre region: the optical axis passes within 5 cm of (0, 0, 0.6)
        to_aim = np.array([0.0, 0.0, 0.6]) - c.position
        assert np.linalg.norm(np.cross(c.forward, to_aim)) < 0.05
    az = sorted(math.degrees(math.atan2(c.position[1], c.position[0])) % 360 for c in L.cameras)
    assert np.allclose(np.diff(az), 30.0, atol=0.01)  # evenly spaced: theta = 360/N
    assert L.ots is not None and L.ots.volume == "pyramid"
    assert L.threshold.mode == "eq17"
    assert L.threshold.deg == pytest.approx(L.threshold.k * eq17_theta_prime_deg(30.0, 36.5))
    # the Vega on a stand at the foot end, robot side (y < 0), head 1.6-2.0 m high, tilted down onto the space
    # beside the table where the arm works: the point 1.73 m along its axis is beside the robot-side table edge
    v = L.ots.position
    axis = -L.ots.T_omc_ots[:3, 2]  # NDI: the volume lies along -z
    assert 1.6 <= v[2] <= 2.0 and v[1] < -0.3 and v[0] > 1.0  # beyond the table's foot end (x = 1.0)
    assert 20.0 <= math.degrees(math.asin(-axis[2])) <= 40.0  # looking down
    look = v + 1.73 * axis
    assert L.ots.contains_omc(look[None])[0]
    assert -0.45 <= look[1] <= -0.25 and 0.85 <= look[2] <= 1.05 and abs(look[0]) <= 0.3
    for d in (1.2, 2.2):  # 1.2-2.2 m from the field: the whole range lies in the measurement volume
        assert L.ots.contains_omc((v + d * axis)[None])[0]


# ------------------------------------------------------------------------------------------ geometry helpers
def test_look_at_R_is_opencv_camera():
    pos, tgt = np.array([3.0, 0.0, 2.0]), np.array([0.0, 0.0, 2.0])
    R = look_at_R(pos, tgt)
    assert np.allclose(R[:, 2], [-1, 0, 0])  # z forward
    assert np.allclose(R[:, 1], [0, 0, -1])  # y down
    assert np.allclose(R[:, 0], [0, 1, 0])  # x right when looking along -x with z up
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_look_at_R_ndi_looks_along_minus_z_with_y_up():
    pos, tgt = np.array([0.0, 0.0, 1.0]), np.array([0.0, 2.0, 1.0])
    R = look_at_R_ndi(pos, tgt)
    assert np.allclose(R[:, 2], [0, -1, 0])
    assert np.allclose(R[:, 1], [0, 0, 1])
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_pyramid_frustum_hand_points():
    L = parse_layout(minimal(ots={"position": [0, 0, 0], "orientation": [0, 0, 0, 1]}))
    f = L.ots.frustum
    assert (f.near_m, f.far_m) == (0.95, 2.4)
    inside = [(0, 0, -1.0), (0, 0, -2.4), (0.39, 0, -1.532), (0, 0.56, -1.532), (-0.53, 0, -2.0)]
    outside = [(0, 0, -0.9), (0, 0, -2.5), (0, 0, 1.5), (0.41, 0, -1.532), (0, -0.58, -1.532), (0.545, 0, -2.0)]
    # at depth 2.0 the half width is 0.398 + (0.656 - 0.398) * (2.0 - 1.532) / (2.4 - 1.532) = 0.5371 m
    assert f.contains(np.array(inside)).all()
    assert not f.contains(np.array(outside)).any()


def test_frustum_depth_axis_plus_z_and_custom_planes():
    L = parse_layout(minimal(ots={"position": [0, 0, 0], "orientation": [0, 0, 0, 1], "volume": "custom",
                                  "depth_axis": "+z", "planes": [[1.0, 0.5, 0.5], [2.0, 1.0, 1.0]]}))
    f = L.ots.frustum
    assert f.contains(np.array([[0.7, 0.0, 1.5]]))[0]  # half width at 1.5 m: 0.75
    assert not f.contains(np.array([[0.8, 0.0, 1.5]]))[0]
    assert not f.contains(np.array([[0.0, 0.0, -1.5]]))[0]


def test_extended_volume_reaches_3m():
    L = parse_layout(minimal(ots={"position": [0, 0, 0], "orientation": [0, 0, 0, 1], "volume": "extended"}))
    assert L.ots.frustum.far_m == 3.0
    assert L.ots.contains(np.array([[0.0, 0.0, -2.9]]))[0]
    assert np.allclose(L.ots.frustum.planes[:3], NDI_PYRAMID_PLANES)


@pytest.mark.parametrize("ots", [
    {"volume": "pyramid"}, {"volume": "extended"},
    {"volume": "custom", "depth_axis": "+z", "planes": [[0.5, 0.2, 0.1], [1.0, 0.3, 0.4], [2.0, 0.35, 0.9]]},
])
def test_single_point_frustum_test_agrees(ots):
    L = parse_layout(minimal(ots={"position": [0, 0, 0], "orientation": [0, 0, 0, 1], **ots}))
    f = L.ots.frustum
    pts = np.random.default_rng(5).uniform([-1.0, -1.0, -3.2], [1.0, 1.0, 3.2], size=(20000, 3))
    vec = f.contains(pts)
    assert 0.02 < vec.mean() < 0.5
    assert vec.tolist() == [f.contains_one(*p) for p in pts.tolist()]


def test_single_point_omc_frustum_test_agrees():
    R = look_at_R_ndi([1.25, -0.75, 1.8], [-0.2, -0.35, 0.95])
    q = __import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation.from_matrix(R).as_quat()
    L = parse_layout(minimal(ots={"position": [1.25, -0.75, 1.8], "orientation": q.tolist()}))
    pts = np.random.default_rng(9).uniform([-1.5, -2.0, 0.0], [1.5, 1.0, 2.5], size=(20000, 3))
    vec = L.ots.contains_omc(pts)
    assert 0.02 < vec.mean() < 0.5
    assert vec.tolist() == [L.ots.contains_one_omc(*p) for p in pts.tolist()]


def test_ots_pose_moves_the_volume():
    R = look_at_R_ndi([1.0, 1.0, 1.0], [1.0, 3.0, 1.0])
    q = __import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation.from_matrix(R).as_quat()
    L = parse_layout(minimal(ots={"position": [1.0, 1.0, 1.0], "orientation": q.tolist()}))
    assert L.ots.contains_omc(np.array([[1.0, 2.5, 1.0]]))[0]  # 1.5 m in front
    assert not L.ots.contains_omc(np.array([[1.0, -0.5, 1.0]]))[0]  # 1.5 m behind


# ----------------------------------------------------------------------------------------------- eq. (17)
@pytest.mark.parametrize("theta, phi, expected", [
    (50.0, 0.0, 50.0),  # cameras level with the point: theta' = theta
    (90.0, 45.0, 60.0),  # arccos(1 + 0 - 1/2)
    (180.0, 45.0, 90.0),  # arccos(1 - 1/2 - 1/2)
    (60.0, 60.0, math.degrees(math.acos(0.875))),  # 1 + 0.5 * 0.25 - 0.25
    (30.0, 90.0, 0.0),  # all cameras straight overhead
])
def test_eq17_hand_values(theta, phi, expected):
    assert eq17_theta_prime_deg(theta, phi) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("theta, phi", [(30.0, 36.5), (51.4, 30.0), (72.0, 45.0)])
def test_eq17_is_the_angle_between_two_tilted_view_vectors(theta, phi):
    t, p = math.radians(theta), math.radians(phi)
    v1 = np.array([math.cos(p), 0.0, -math.sin(p)])
    v2 = np.array([math.cos(p) * math.cos(t), math.cos(p) * math.sin(t), -math.sin(p)])
    assert eq17_theta_prime_deg(theta, phi) == pytest.approx(math.degrees(math.acos(v1 @ v2)), abs=1e-9)


def test_threshold_modes():
    L = parse_layout(minimal(threshold={"mode": "eq17", "theta_deg": 90.0, "phi_deg": 45.0, "k": 5}))
    assert L.threshold_deg == pytest.approx(300.0)  # 5 x 60 deg
    L = parse_layout(minimal(threshold={"mode": "explicit", "deg": 123.0}))
    assert L.threshold_deg == 123.0 and L.threshold.mode == "explicit"
    # defaults: theta = 360/N, phi = mean tilt, k = 6; both test cameras look along +z (tilt -90) -> phi given
    L = parse_layout(minimal(threshold={"mode": "eq17", "phi_deg": 0.0}))
    assert L.threshold.theta_deg == 180.0 and L.threshold.k == 6.0
    assert L.threshold_deg == pytest.approx(6 * 180.0)
    assert L.with_threshold(10.0).threshold_deg == 10.0


# -------------------------------------------------------------------------------------------- occluders
def test_box_blocks_hand_cases():
    b = Box("b", np.array([-0.5, -0.5, 0.0]), np.array([0.5, 0.5, 1.0]))
    cam = np.array([0.0, 0.0, 3.0])
    pts = np.array([
        [0.0, 0.0, -1.0],  # straight through the box
        [0.0, 0.0, 2.0],  # in front of the box
        [0.0, 0.0, 1.0],  # on the top face: not hidden by it
        [0.0, 0.0, 0.5],  # inside
        [3.0, 0.0, -1.0],  # ray passes beside the box
    ])
    assert b.blocks(cam, pts).tolist() == [True, False, False, True, False]
    # broadcasting: many cameras, one point; a camera with a zero direction component stays finite
    cams = np.array([[0.0, 0.0, 3.0], [0.0, 3.0, 0.5], [0.0, 3.0, 5.0]])
    assert b.blocks(cams, np.array([0.0, -3.0, 0.5])).tolist() == [False, True, False]


# ---------------------------------------------------------------------------------------------- bad input
def test_missing_field_names_file_and_field(tmp_path):
    d = minimal()
    del d["cameras"][1]["position"]
    p = write(tmp_path, d)
    with pytest.raises(LayoutError) as e:
        load_layout(p)
    assert str(p) in str(e.value) and "cameras[1].position" in str(e.value) and "missing" in str(e.value)


def test_zero_length_orientation(tmp_path):
    d = minimal()
    d["cameras"][0]["orientation"] = [0, 0, 0, 0]
    p = write(tmp_path, d)
    with pytest.raises(LayoutError, match=r"cameras\[0\]\.orientation.*zero-length") as e:
        load_layout(p)
    assert str(p) in str(e.value)


def test_negative_range(tmp_path):
    d = minimal()
    d["cameras"][1]["range_m"] = -4.0
    p = write(tmp_path, d)
    with pytest.raises(LayoutError, match=r"cameras\[1\]\.range_m.*must be > 0") as e:
        load_layout(p)
    assert str(p) in str(e.value)


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.update(camera_defaults={"range_m": 0}), r"cameras\[0\]\.range_m"),
    (lambda d: d["cameras"][0].update(fov_h_deg=190), r"cameras\[0\]\.fov_h_deg"),
    (lambda d: d["cameras"][0].update(orientation=[0, 0, 0, 2]), r"cameras\[0\]\.orientation.*not unit"),
    (lambda d: d["cameras"][0].update(position=[0, 0]), r"cameras\[0\]\.position"),
    (lambda d: d["cameras"][0].update(position=[0, float("nan"), 0]), r"cameras\[0\]\.position\[1\].*finite"),
    (lambda d: d["cameras"][0].update(fov_v_deg="wide"), r"cameras\[0\]\.fov_v_deg.*number"),
    (lambda d: d["cameras"][0].update(rnage_m=3), r"cameras\[0\].*unknown key.*rnage_m"),
    (lambda d: d["cameras"][1].update(name="a"), r"'cameras'.*duplicate"),
    (lambda d: d.update(cameras=d["cameras"][:1]), r"'cameras'.*at least two"),
    (lambda d: d.update(convergence_deg=[140, 40]), r"convergence_deg"),
    (lambda d: d.update(threshold={"mode": "magic"}), r"threshold\.mode"),
    (lambda d: d.update(threshold={"mode": "explicit"}), r"threshold\.deg.*missing"),
    (lambda d: d.update(ots={"position": [0, 0, 0], "orientation": [0, 0, 0, 1], "volume": "cube"}),
     r"ots\.volume"),
    (lambda d: d.update(ots={"orientation": [0, 0, 0, 1]}), r"ots\.position.*missing"),
    (lambda d: d.update(ots={"position": [0, 0, 0], "orientation": [0, 0, 0, 1], "volume": "custom",
                             "planes": [[2, 1, 1], [1, 1, 1]]}), r"ots\.planes.*increase"),
    (lambda d: d.update(occluders=[{"name": "t", "min": [0, 0, 1], "max": [1, 1, 0]}]), r"occluders\[0\]"),
    (lambda d: d.update(room={"min": [0, 0, 0], "max": [1, 1, 0]}), r"'room'"),
    (lambda d: d.update(extra_key=1), r"unknown key.*extra_key"),
])
def test_bad_fields(tmp_path, mutate, field):
    d = minimal()
    mutate(d)
    p = write(tmp_path, d)
    with pytest.raises(LayoutError, match=field) as e:
        load_layout(p)
    assert str(p) in str(e.value)


def test_unreadable_and_non_yaml_files(tmp_path):
    with pytest.raises(LayoutError, match="cannot read"):
        load_layout(tmp_path / "nope.yaml")
    p = tmp_path / "bad.yaml"
    p.write_text("cameras: [unclosed\n")
    with pytest.raises(LayoutError, match="not valid YAML"):
        load_layout(p)
    p.write_text("- just\n- a list\n")
    with pytest.raises(LayoutError, match="expected a mapping"):
        load_layout(p)


def test_the_geometry_stays_importable_from_layout():
    """The view-margin model, the simulator and the emulators import the geometry's names from ``layout`` (the file
    they load it with): the same objects as :mod:`~fullperc_fusion.margin.geometry`'s, and every name ``layout``
    exports exists."""
    for name in ("SEGMENT_END", "NDI_PYRAMID_PLANES", "Box", "Frustum", "Camera", "Ots", "look_at_R", "look_at_R_ndi"):
        assert getattr(layout, name) is getattr(geometry, name), name
    assert all(hasattr(layout, name) for name in layout.__all__)
