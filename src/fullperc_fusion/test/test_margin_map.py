"""The float32 room-map kernel against the float64 reference path, and the PNG heatmap."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fullperc_fusion.margin import view_margin as M
from fullperc_fusion.margin.layout import default_layout_path, load_layout
from fullperc_fusion.margin.map import TABLE_BINS, compute_margin_map, grid_axis, margin_table, save_heatmap_png

# Half a table bin in cos(beta), converted to beta at the steepest point of the 40-140 deg band (1/sin 40).
PER_PAIR_TOL_DEG = math.degrees(1.0 / TABLE_BINS / math.sin(math.radians(40.0))) + 1e-3


@pytest.fixture(scope="module")
def layout():
    return load_layout(default_layout_path())


@pytest.fixture(scope="module")
def coarse(layout):
    return compute_margin_map(layout, 0.15)


def test_grid_axis_includes_both_ends():
    assert np.allclose(grid_axis(-3.0, 3.0, 0.02)[[0, -1]], [-3.0, 3.0])
    assert len(grid_axis(-3.0, 3.0, 0.02)) == 301
    assert len(grid_axis(0.0, 1.0, 0.3)) == 4  # 0, 0.3, 0.6, 0.9
    with pytest.raises(ValueError):
        grid_axis(0.0, 1.0, 0.0)


def test_margin_table_entries():
    t = margin_table(40.0, 140.0)
    c = -1.0 + (np.arange(TABLE_BINS + 1) + 0.5) * (2.0 / TABLE_BINS)
    beta = np.degrees(np.arccos(np.clip(c, -1, 1)))
    inside = (beta >= 40.0) & (beta <= 140.0)
    assert np.all(t[~inside] == 0.0)
    assert np.allclose(t[inside], 180.0 - beta[inside], atol=1e-4)
    assert t[TABLE_BINS // 2] == pytest.approx(90.0, abs=0.01)  # cos beta ~ 0


def test_map_matches_reference_path(layout, coarse):
    pts = coarse.points()
    ref = M.compute_margin(layout, pts)
    seeing = coarse.cameras_seeing.ravel().astype(int)
    pairs = coarse.valid_pairs.ravel().astype(int)
    margin = coarse.margin_deg.ravel().astype(float)
    # 1) cameras seeing: equal except where the point sits on a visibility boundary (float32 vs float64 ties):
    #    there a displacement of 1e-4 m changes the float64 answer.
    bad = np.flatnonzero(seeing != ref.cameras_seeing)
    assert len(bad) <= 0.005 * len(pts)
    for k in bad:
        counts = {int(M.compute_margin(layout, (pts[k] + d)[None]).cameras_seeing[0])
                  for d in np.vstack([np.eye(3), -np.eye(3)]) * 1e-4}
        assert len(counts | {int(ref.cameras_seeing[k])}) > 1, pts[k]
    ok = seeing == ref.cameras_seeing
    # 2) valid pairs: equal except where some pair's beta is within the table resolution of a band edge.
    pair_bad = np.flatnonzero(ok & (pairs != ref.valid_pairs))
    for k in pair_bad:
        see, u = M.camera_visibility(layout, pts[k][None])
        b = np.degrees(np.arccos(np.clip(u[0] @ u[0].T, -1, 1)))[np.ix_(see[0], see[0])]
        assert np.min(np.abs(np.concatenate([b.ravel() - 40.0, b.ravel() - 140.0]))) < 0.01, pts[k]
    same = ok & (pairs == ref.valid_pairs)
    # 3) margin: within the table resolution per valid pair
    err = np.abs(margin[same] - ref.margin_deg[same])
    assert np.all(err <= PER_PAIR_TOL_DEG * np.maximum(ref.valid_pairs[same], 1) + 0.01), err.max()
    assert same.mean() > 0.99
    assert (ref.valid_pairs > 0).mean() > 0.2  # a meaningful comparison, not all zeros


def test_map_labels(layout, coarse):
    pts = coarse.points()
    inside = M.in_bvv(layout, pts)  # frustum and the Vega's line of sight
    lab = coarse.labels.ravel()
    assert np.array_equal(lab == M.BVV, inside)
    hidden = layout.ots.contains_omc(pts) & ~inside  # in the frustum, behind the table/patient as seen from the Vega
    assert hidden.any() and not np.any(lab[hidden] == M.BVV)
    thr = layout.threshold_deg
    m = coarse.margin_deg.ravel()
    assert np.all(lab[~inside & (m >= thr)] == M.GVV) and np.all(lab[~inside & (m < thr)] == M.PVV)
    fr = coarse.fractions()
    assert all(fr[k] > 0 for k in ("BVV", "GVV", "PVV")) and sum(fr.values()) == pytest.approx(1.0)


def test_threads_and_blocks_do_not_change_the_result(layout):
    lo, hi = np.array([-1.0, -1.0, 0.3]), np.array([1.0, 0.5, 1.8])
    a = compute_margin_map(layout, 0.1, lo, hi, block=4, threads=1)
    b = compute_margin_map(layout, 0.1, lo, hi, block=7, threads=2)
    assert a.shape == b.shape == (21, 16, 16)
    for name in ("margin_deg", "valid_pairs", "cameras_seeing", "labels"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_map_axes_and_points_are_consistent(layout):
    m = compute_margin_map(layout, 0.5, [0.0, 0.0, 0.0], [1.0, 0.5, 1.0])
    xs, ys, zs = m.axes()
    assert m.shape == (3, 2, 3) and np.allclose(xs, [0, 0.5, 1.0]) and np.allclose(ys, [0, 0.5])
    pts = m.points()
    assert np.allclose(pts[1], [0.0, 0.0, 0.5]) and np.allclose(pts[3], [0.0, 0.5, 0.0])


def test_bad_bounds(layout):
    with pytest.raises(ValueError):
        compute_margin_map(layout, 0.1, [0, 0, 1], [1, 1, 0])


@pytest.mark.parametrize("axis, value", [("z", 0.6), ("y", -0.4), ("x", None)])
def test_heatmap_png(layout, coarse, tmp_path, axis, value):
    out = save_heatmap_png(coarse, tmp_path / f"slice_{axis}.png", axis=axis, value=value, layout=layout)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_map_cuts_the_ots_shadow_out_of_bvv():
    """Hand-made geometry: a box 1 m in front of the OTS; the map's BVV is the frustum minus the box's shadow."""
    from scipy.spatial.transform import Rotation

    from fullperc_fusion.margin.layout import look_at_R_ndi, parse_layout

    ots_pos, aim = np.array([0.0, -2.0, 1.0]), np.array([0.0, 0.0, 1.0])
    q = Rotation.from_matrix(look_at_R_ndi(ots_pos, aim)).as_quat().tolist()
    cams = [{"name": n, "position": p, "orientation": [0.0, 0.0, 0.0, 1.0]} for n, p in (("a", [3, 0, 3]),
                                                                                        ("b", [-3, 0, 3]))]
    # box sides not commensurate with the 5 cm grid, so no grid point's ray grazes an edge exactly
    lo_b, hi_b = np.array([-0.0975, -1.1, 0.9025]), np.array([0.1025, -1.0, 1.0975])
    box = {"name": "screen", "min": lo_b.tolist(), "max": hi_b.tolist()}
    with_box = parse_layout({"cameras": cams, "ots": {"position": ots_pos.tolist(), "orientation": q},
                             "occluders": [box]})
    lo, hi = [-0.5, -0.9, 0.5], [0.5, 0.5, 1.5]
    m = compute_margin_map(with_box, 0.05, lo, hi)
    pts = m.points()
    frustum = with_box.ots.contains_omc(pts)
    # shadow, independently of the slab test: sample each segment OTS -> p densely where it crosses the box's y slab
    s = (np.linspace(lo_b[1], hi_b[1], 201)[None, :] - ots_pos[1]) / (pts[:, 1] - ots_pos[1])[:, None]  # (N, 201)
    hit = ots_pos[None, None, :] + s[:, :, None] * (pts - ots_pos)[:, None, :]
    in_shadow = np.any(np.all((hit >= lo_b) & (hit <= hi_b), axis=2), axis=1)
    bvv = m.labels.ravel() == M.BVV
    assert (frustum & in_shadow).sum() > 10
    assert np.array_equal(bvv, frustum & ~in_shadow)
