"""Algorithm 1 against geometry computed by hand, the labels, and vectorized vs single-point agreement."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_fusion.margin import view_margin as M
from fullperc_fusion.margin.geometry import look_at_R, look_at_R_ndi
from fullperc_fusion.margin.layout import default_layout_path, load_layout, parse_layout

P = np.array([0.0, 0.0, 1.0])  # the test point


def cam(name, azimuth_deg, dist=2.0, elev_deg=0.0, target=P, yaw_off_deg=0.0, pitch_off_deg=0.0, **kw):
    """A camera at ``dist`` from P, at ``azimuth`` around it, looking at ``target`` (optionally turned away)."""
    a, e = math.radians(azimuth_deg), math.radians(elev_deg)
    pos = P + dist * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
    R = look_at_R(pos, target)
    # turn about the camera's own y (yaw, horizontal FOV) / x (pitch, vertical FOV) axes
    R = R @ Rotation.from_euler("yx", [yaw_off_deg, pitch_off_deg], degrees=True).as_matrix()
    return {"name": name, "position": pos.tolist(), "orientation": Rotation.from_matrix(R).as_quat().tolist(), **kw}


def layout(*cams, **top):
    d = {"cameras": list(cams), "threshold": {"mode": "explicit", "deg": 100.0}}
    d.update(top)
    return parse_layout(d)


def both_paths(L, p=P):
    """Margin by the vectorized and the single-point path; asserts they agree, returns the single-point triple."""
    r = M.compute_margin(L, np.asarray(p, float)[None])
    s = M.margin_at(L, p)
    assert r.margin_deg[0] == pytest.approx(s[0], abs=1e-9)
    assert (int(r.valid_pairs[0]), int(r.cameras_seeing[0])) == s[1:]
    return s


def test_region_constants_match_the_message():
    from fullperc_msgs.msg import Region

    assert (M.UNKNOWN, M.BVV, M.GVV, M.PVV) == (Region.UNKNOWN, Region.BVV, Region.GVV, Region.PVV)


@pytest.mark.parametrize("beta", [41.0, 60.0, 90.0, 120.0, 139.0])
def test_two_cameras_give_180_minus_beta(beta):
    L = layout(cam("a", 0.0), cam("b", beta))
    assert both_paths(L) == (pytest.approx(180.0 - beta, abs=1e-9), 1, 2)


def test_pair_angle_is_between_view_vectors_in_3d():
    # a level with P at azimuth 0, b at the same azimuth but 89 deg up: view vectors (-1, 0, 0) and
    # -(cos 89, 0, sin 89) -> cos beta = cos 89 -> beta = 89, margin 91
    L = layout(cam("a", 0.0), cam("b", 0.0, elev_deg=89.0))
    assert both_paths(L) == (pytest.approx(91.0, abs=1e-9), 1, 2)


def test_three_cameras_sum_only_valid_pairs():
    # pairs: (0, 90) -> 90 valid, margin 90; (90, 200) -> 110 valid, margin 70; (0, 200) -> 160 invalid
    L = layout(cam("a", 0.0), cam("b", 90.0), cam("c", 200.0))
    assert both_paths(L) == (pytest.approx(160.0, abs=1e-9), 2, 3)


@pytest.mark.parametrize("beta", [20.0, 160.0, 0.5, 179.5])
def test_convergence_outside_band_counts_zero(beta):
    L = layout(cam("a", 0.0), cam("b", beta))
    assert both_paths(L) == (0.0, 0, 2)


def test_band_is_configurable():
    L = layout(cam("a", 0.0), cam("b", 20.0), convergence_deg=[10.0, 170.0])
    assert both_paths(L)[0] == pytest.approx(160.0)


def test_out_of_range_counts_zero():
    near = layout(cam("a", 0.0, dist=3.9), cam("b", 90.0, dist=3.9))
    assert both_paths(near) == (pytest.approx(90.0), 1, 2)
    far = layout(cam("a", 0.0, dist=4.1), cam("b", 90.0, dist=3.9))
    assert both_paths(far) == (0.0, 0, 1)
    longer = layout(cam("a", 0.0, dist=4.1, range_m=4.5), cam("b", 90.0, dist=3.9))
    assert both_paths(longer) == (pytest.approx(90.0), 1, 2)


@pytest.mark.parametrize("yaw, pitch, sees", [
    (27.0, 0.0, True), (29.0, 0.0, False), (-29.0, 0.0, False),  # horizontal half FOV 28 deg
    (0.0, 22.0, True), (0.0, 24.0, False), (0.0, -24.0, False),  # vertical half FOV 23 deg
])
def test_outside_field_of_view_counts_zero(yaw, pitch, sees):
    L = layout(cam("a", 0.0, yaw_off_deg=yaw, pitch_off_deg=pitch), cam("b", 90.0))
    assert L.cameras[0].fov_h_deg == 56.0 and L.cameras[0].fov_v_deg == 46.0  # the defaults
    assert both_paths(L) == ((pytest.approx(90.0), 1, 2) if sees else (0.0, 0, 1))


def test_behind_the_camera_counts_zero():
    L = layout(cam("a", 0.0, yaw_off_deg=180.0), cam("b", 90.0))
    assert both_paths(L) == (0.0, 0, 1)


def test_occluder_hides_one_camera():
    box = {"name": "wall", "min": [1.0, -0.2, 0.8], "max": [1.2, 0.2, 1.2]}  # between camera a (x = 2) and P
    L = layout(cam("a", 0.0), cam("b", 90.0), occluders=[box])
    assert both_paths(L) == (0.0, 0, 1)
    # a point lying on the occluder's +x face, seen by two cameras on the +x side (60 deg apart): not hidden
    onface = np.array([1.2, 0.0, 1.0])
    cams = []
    for name, az in (("a", 0.0), ("c", 60.0)):
        pos = onface + 2.0 * np.array([math.cos(math.radians(az)), math.sin(math.radians(az)), 0.0])
        q = Rotation.from_matrix(look_at_R(pos, onface)).as_quat().tolist()
        cams.append({"name": name, "position": pos.tolist(), "orientation": q})
    L2 = parse_layout({"cameras": cams, "occluders": [box]})
    assert both_paths(L2, onface) == (pytest.approx(120.0, abs=1e-9), 1, 2)
    # ... while camera b (azimuth 90 around P) would look at that point through the box
    L3 = parse_layout({"cameras": cams + [cam("b", 90.0, target=onface)], "occluders": [box]})
    assert both_paths(L3, onface)[2] == 2


def test_labels_bvv_gvv_pvv():
    ots_pos = np.array([0.0, -2.0, 1.0])
    q = Rotation.from_matrix(look_at_R_ndi(ots_pos, P)).as_quat().tolist()
    L = layout(cam("a", 0.0), cam("b", 90.0), cam("c", 180.0),
               ots={"position": ots_pos.tolist(), "orientation": q},
               threshold={"mode": "explicit", "deg": 150.0})
    # P: pairs (a,b) 90 and (b,c) 90 valid -> margin 180 >= 150, and P is 2 m in front of the OTS -> BVV
    inside, outside_gvv = P, P + np.array([0.0, 0.5, 0.0])  # 2.5 m from the OTS: beyond its 2.4 m far plane
    pts = np.array([inside, outside_gvv, [0.0, 0.0, -5.0]])
    labels, res = M.label_points(L, pts)
    assert labels.tolist() == [M.BVV, M.GVV, M.PVV]
    assert res.margin_deg[2] == 0.0
    for p, lab in zip(pts, labels, strict=True):
        pl = M.label_point(L, p)
        assert pl.label == lab and pl.in_local_volume == (lab == M.BVV)
    # threshold is inclusive: margin == threshold is GVV
    assert M.labels_from(np.array([150.0, 149.999]), np.array([False, False]), 150.0).tolist() == [M.GVV, M.PVV]


def _ots_layout(occluders=(), threshold=150.0):
    """Three cameras around P (margin 180 there) and an OTS 2 m from P along -y, looking at P."""
    ots_pos = np.array([0.0, -2.0, 1.0])
    q = Rotation.from_matrix(look_at_R_ndi(ots_pos, P)).as_quat().tolist()
    return layout(cam("a", 0.0), cam("b", 90.0), cam("c", 180.0),
                  ots={"position": ots_pos.tolist(), "orientation": q},
                  threshold={"mode": "explicit", "deg": threshold}, occluders=list(occluders))


# A box across the segment OTS (0, -2, 1) -> P (0, 0, 1), 1 m in front of the OTS: it touches none of the three
# cameras' segments to P (they come from +x, +y, -x) and lies before the frustum's near plane (0.95 m).
SCREEN = {"name": "screen", "min": [-0.1, -1.1, 0.9], "max": [0.1, -1.0, 1.1]}


def test_box_between_ots_and_point_is_not_bvv():
    L = _ots_layout([SCREEN])
    assert L.ots.contains_omc(P[None])[0]  # P is inside the frustum ...
    assert not M.ots_line_of_sight(L, P[None])[0] and not M.in_bvv(L, P[None])[0]  # ... but hidden from the OTS
    labels, res = M.label_points(L, P[None])
    assert labels.tolist() == [M.GVV] and res.margin_deg[0] == pytest.approx(180.0)  # the cameras still see it
    pl = M.label_point(L, P)
    assert (pl.label, pl.in_local_volume, pl.ots_line_of_sight) == (M.GVV, True, False)
    assert pl.margin_deg == pytest.approx(180.0)
    # with a threshold above the margin the hidden point is PVV, not BVV
    L2 = _ots_layout([SCREEN], threshold=200.0)
    assert M.label_points(L2, P[None])[0].tolist() == [M.PVV] and M.label_point(L2, P).label == M.PVV
    # without the box, or with the box moved off the segment, P is BVV again
    for occ in ([], [{**SCREEN, "min": [0.3, -1.1, 0.9], "max": [0.5, -1.0, 1.1]}]):
        L3 = _ots_layout(occ)
        assert M.label_points(L3, P[None])[0].tolist() == [M.BVV]
        pl = M.label_point(L3, P)
        assert (pl.label, pl.in_local_volume, pl.ots_line_of_sight) == (M.BVV, True, True)


def test_shadow_of_a_box_in_the_frustum_is_cut_out_of_bvv():
    """Points inside the frustum behind the box (seen from the OTS) are not BVV; beside the shadow they are."""
    L = _ots_layout([SCREEN])
    # the shadow cone of the 0.2 x 0.2 m screen at 1 m, seen from (0, -2, 1): half width 0.1 * d / 1.0 at depth d
    behind = np.array([[0.0, 0.0, 1.0], [0.15, 0.0, 1.1], [-0.15, 0.3, 0.9], [0.1, -0.5, 1.0]])
    beside = np.array([[0.3, 0.0, 1.0], [0.0, 0.0, 1.35], [-0.3, 0.3, 0.9], [0.2, -0.5, 1.0]])
    pts = np.vstack([behind, beside])
    assert L.ots.contains_omc(pts).all()
    want = [False] * 4 + [True] * 4
    assert M.in_bvv(L, pts).tolist() == want
    assert [M.label_point(L, p).ots_line_of_sight for p in pts] == want
    assert [M.label_point(L, p).label == M.BVV for p in pts] == want
    # a point on the screen's face that looks at the OTS is visible to it (surface points are not hidden)
    face = np.array([0.0, -1.1, 1.0])
    assert M.ots_line_of_sight(L, face[None])[0] and M.label_point(L, face).ots_line_of_sight


def test_no_ots_means_no_bvv():
    L = layout(cam("a", 0.0), cam("b", 90.0))
    labels, _ = M.label_points(L, P[None])
    assert labels.tolist() == [M.PVV]  # margin 90 < 100


@pytest.mark.parametrize("seed", [0, 1])
def test_vectorized_and_single_point_agree_on_random_points(seed):
    L = load_layout(default_layout_path())
    rng = np.random.default_rng(seed)
    pts = rng.uniform(L.room_min, L.room_max, size=(3000, 3))
    res = M.compute_margin(L, pts, chunk=257)  # odd chunk size: exercises the chunk boundaries
    single = np.array([M.margin_at(L, p) for p in pts])
    assert np.allclose(res.margin_deg, single[:, 0], rtol=0, atol=1e-8)
    assert np.array_equal(res.valid_pairs, single[:, 1]) and np.array_equal(res.cameras_seeing, single[:, 2])
    assert (res.valid_pairs > 0).mean() > 0.1  # the sample is not trivially all zero
    labels, _ = M.label_points(L, pts)
    assert [M.label_point(L, p).label for p in pts[:500]] == labels[:500].tolist()


def test_default_layout_bvv_paths_agree_where_the_vega_is_blocked():
    """In the default room the table, patient and light hide parts of the Vega's frustum: both paths agree there."""
    L = load_layout(default_layout_path())
    rng = np.random.default_rng(3)
    # points spread over the frustum's bounding box (the Vega looks at the robot side of the table)
    c = L.ots.frustum.corners().reshape(-1, 3) @ L.ots.T_omc_ots[:3, :3].T + L.ots.T_omc_ots[:3, 3]
    pts = rng.uniform(np.maximum(c.min(0), L.room_min), np.minimum(c.max(0), L.room_max), size=(4000, 3))
    inside = M.in_local_volume(L, pts)
    bvv = M.in_bvv(L, pts)
    hidden = inside & ~bvv
    assert hidden.sum() > 20 and bvv.sum() > 200  # the sample has both kinds
    single = [M.label_point(L, p) for p in pts]
    assert [s.in_local_volume for s in single] == inside.tolist()
    assert [s.in_local_volume and s.ots_line_of_sight for s in single] == bvv.tolist()
    labels, _ = M.label_points(L, pts)
    assert [s.label for s in single] == labels.tolist()
    # independent check of the hidden ones: some box meets the segment Vega -> point (sampled densely along it)
    ots = L.ots.position
    for p in pts[hidden][:50]:
        seg = ots + np.linspace(0.0, 1.0, 4001)[:-1, None] * (p - ots)
        assert any(np.any(np.all((seg >= b.lo) & (seg <= b.hi), axis=1)) for b in L.occluders), p


def test_random_layouts_without_occluders_agree():
    rng = np.random.default_rng(7)
    for _ in range(5):
        cams = []
        for k in range(rng.integers(2, 9)):
            pos = rng.uniform([-3, -3, 1.5], [3, 3, 3])
            R = look_at_R(pos, rng.uniform([-1, -1, 0], [1, 1, 1.5]))
            cams.append({"name": f"c{k}", "position": pos.tolist(),
                         "orientation": Rotation.from_matrix(R).as_quat().tolist(),
                         "fov_h_deg": float(rng.uniform(40, 90)), "fov_v_deg": float(rng.uniform(30, 70)),
                         "range_m": float(rng.uniform(2.5, 5))})
        L = parse_layout({"cameras": cams, "convergence_deg": [float(rng.uniform(10, 50)),
                                                               float(rng.uniform(120, 170))]})
        pts = rng.uniform([-3, -3, 0], [3, 3, 3], size=(500, 3))
        res = M.compute_margin(L, pts)
        single = np.array([M.margin_at(L, p) for p in pts])
        assert np.allclose(res.margin_deg, single[:, 0], atol=1e-8)
        assert np.array_equal(res.valid_pairs, single[:, 1])


def test_default_layout_has_all_regions_within_robot_reach():
    """The simulator places tasks crossing BVV/GVV/PVV: all three must exist within reach of the designed robot."""
    L = load_layout(default_layout_path())
    shoulder = np.array(L.scene["robot_base"]) + [0.0, 0.0, 0.2856]
    g = np.mgrid[-1.0:1.0:0.05, -1.6:0.4:0.05, 0.0:2.2:0.05].reshape(3, -1).T
    r = np.linalg.norm(g - shoulder, axis=1)
    g = g[(r >= 0.3) & (r <= 0.8)]
    for b in L.occluders:  # the target cannot be inside the table or the patient
        g = g[~np.all((g >= b.lo) & (g <= b.hi), axis=1)]
    labels, _ = M.label_points(L, g)
    frac = {name: float(np.mean(labels == v)) for name, v in (("BVV", M.BVV), ("GVV", M.GVV), ("PVV", M.PVV))}
    assert all(f > 0.03 for f in frac.values()), frac
    # the Vega looks at the arm's side of the table: most of the reach inside its frustum is really in its view
    inside = M.in_local_volume(L, g)
    assert inside.sum() > 100 and (labels[inside] == M.BVV).mean() > 0.8


def test_bad_points_are_rejected():
    L = layout(cam("a", 0.0), cam("b", 90.0))
    with pytest.raises(ValueError, match="NaN"):
        M.compute_margin(L, np.array([[0.0, np.nan, 1.0]]))
    with pytest.raises(ValueError, match="shape"):
        M.compute_margin(L, np.zeros((4, 2)))
    with pytest.raises(ValueError):
        M.margin_at(L, [0.0, np.inf, 1.0])
    with pytest.raises(ValueError):
        M.margin_at(L, [0.0, 1.0])
