"""region_filter: hysteresis of the region label (margin band, minimum dwell), on made-up label sequences and on
the shipped layout with a noisy crossing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fullperc_fusion.margin.hysteresis import HysteresisParams, RegionFilter
from fullperc_fusion.margin.layout import default_layout_path, load_layout
from fullperc_fusion.margin.view_margin import BVV, GVV, PVV, PointLabel, label_point

MS = 1_000_000
THR = 1000.0


def pl(label: int, margin: float = 0.0) -> PointLabel:
    """A labelled point; BVV points are inside the OTS volume with line of sight."""
    if label in (GVV, PVV) and margin == 0.0:
        margin = THR + 100 if label == GVV else THR - 100
    inside = label == BVV
    return PointLabel(label, margin, 10, 6, inside, inside)


def run(f: RegionFilter, seq, dt_ms: float = 8.0, t0_ms: float = 0.0):
    """Feed (PointLabel) samples every dt_ms; returns the Filtered results."""
    return [f.update(int(round((t0_ms + k * dt_ms) * MS)), p, THR) for k, p in enumerate(seq)]


def changes(results) -> list[int]:
    return [k for k in range(1, len(results)) if results[k].label != results[k - 1].label]


def assert_consistent(r) -> None:
    """What a Region message carries: label vs evidence (margin, OTS volume) vs threshold in force."""
    ev = r.evidence
    in_bvv = ev.in_local_volume and ev.ots_line_of_sight
    if r.label == BVV:
        assert in_bvv
    elif r.label == GVV:
        assert not in_bvv and ev.margin_deg >= r.threshold_deg
    else:
        assert r.label == PVV and not in_bvv and ev.margin_deg < r.threshold_deg


def test_defaults_are_the_documented_ones():
    assert HysteresisParams() == HysteresisParams(margin_band_deg=1.0, min_dwell_s=0.2)


@pytest.mark.parametrize("kw", [dict(margin_band_deg=-1.0), dict(min_dwell_s=-0.1), dict(min_dwell_s=math.nan),
                                dict(margin_band_deg=math.inf), dict(min_dwell_s=True)])
def test_bad_parameters_are_refused(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        HysteresisParams(**kw).validate()


def test_without_hysteresis_the_label_is_the_models():
    f = RegionFilter(HysteresisParams(0.0, 0.0))
    seq = [pl(GVV), pl(PVV), pl(GVV), pl(BVV), pl(PVV)]
    assert [r.label for r in run(f, seq)] == [GVV, PVV, GVV, BVV, PVV]


def test_noise_around_a_boundary_gives_one_change():
    """Issue 14 item 9: 5 changes in 57 ms. The model flickers G/B/G/B/G/B for 57 ms and then stays B: one change."""
    f = RegionFilter()
    seq = [pl(GVV)] * 20 + [pl(BVV), pl(GVV), pl(BVV), pl(GVV), pl(GVV), pl(BVV), pl(GVV), pl(BVV)] + [pl(BVV)] * 40
    res = run(f, seq)
    assert changes(res) == [20]                      # the first flip, immediately
    assert f.raw_changes == 7 and f.changes == 1
    for r in res:
        assert_consistent(r)
    held = [r for r in res if r.held]
    assert held and all(r.label == BVV and r.raw_label == GVV for r in held)


def test_noise_that_ends_on_the_old_side_changes_there_and_back_once():
    f = RegionFilter(HysteresisParams(min_dwell_s=0.2))
    seq = [pl(GVV)] * 10 + [pl(PVV), pl(GVV)] * 5 + [pl(GVV)] * 50      # 80 ms of noise, then G again
    res = run(f, seq)
    assert [res[k].label for k in changes(res)] == [PVV, GVV]
    back = changes(res)[1]
    assert (back - 10) * 8 * MS >= 0.2e9 - 8 * MS    # not before the dwell ended


def test_a_real_crossing_changes_once_delayed_by_at_most_the_dwell():
    dwell = 0.2
    f = RegionFilter(HysteresisParams(min_dwell_s=dwell))
    # a change G -> P at 40 ms, then the real crossing P -> B at 160 ms: held until 240 ms
    seq = [pl(GVV)] * 5 + [pl(PVV)] * 15 + [pl(BVV)] * 60
    res = run(f, seq, dt_ms=8.0)
    ch = changes(res)
    assert [res[k].label for k in ch] == [PVV, BVV]
    t_first_b = 20 * 8.0                             # ms: the model says B from here
    t_change = ch[1] * 8.0
    assert 0 <= t_change - t_first_b <= dwell * 1e3  # delayed, by at most the dwell
    assert t_change - ch[0] * 8.0 >= dwell * 1e3     # and the label dwelt min_dwell in P
    # far from the previous change a crossing is not delayed at all
    res2 = run(f, [pl(BVV)] * 50 + [pl(GVV)] * 5, t0_ms=1000.0)
    assert changes(res2) == [50]
    for r in res + res2:
        assert_consistent(r)


def test_held_messages_carry_the_evidence_of_the_held_label():
    f = RegionFilter(HysteresisParams(margin_band_deg=0.0, min_dwell_s=0.2))
    g = pl(GVV, THR + 50)
    p = pl(PVV, THR - 400)
    run(f, [pl(GVV), pl(PVV), pl(PVV)])   # G, then the change to P at 8 ms
    r1 = f.update(100 * MS, g, THR)       # G again 92 ms later: within the dwell, P held
    assert r1.held and r1.label == PVV and r1.evidence.margin_deg == THR - 100
    r2 = f.update(210 * MS, g, THR)
    assert r2.changed and r2.label == GVV and r2.evidence is g
    r3 = f.update(220 * MS, p, THR)       # a flick back within the dwell: G held, with g's margin
    assert r3.held and r3.label == GVV and r3.raw_label == PVV and r3.evidence is g
    for r in (r1, r2, r3):
        assert_consistent(r)


def test_margin_band_keeps_the_label_within_the_band_and_reports_the_threshold_in_force():
    f = RegionFilter(HysteresisParams(margin_band_deg=5.0, min_dwell_s=0.0))
    margins = [THR + 20, THR + 3, THR - 3, THR + 2, THR - 4.9, THR - 6, THR - 2, THR + 4, THR + 6]
    res = [f.update(k * 10 * MS, pl(GVV if m >= THR else PVV, m), THR) for k, m in enumerate(margins)]
    assert [r.label for r in res] == [GVV, GVV, GVV, GVV, GVV, PVV, PVV, PVV, GVV]
    assert [r.threshold_deg for r in res] == [THR, THR - 5, THR - 5, THR - 5, THR - 5, THR - 5, THR + 5, THR + 5,
                                             THR + 5]
    for r in res:
        assert_consistent(r)
    assert f.changes == 2 and f.raw_changes == 4


def test_stamps_going_back_end_the_hold_and_reset_forgets_the_label():
    f = RegionFilter(HysteresisParams(min_dwell_s=0.2))
    f.update(10_000 * MS, pl(GVV), THR)
    assert f.update(1_000 * MS, pl(PVV), THR).changed     # a replay restarted: no hold
    f.reset()
    r = f.update(1_001 * MS, pl(BVV), THR)
    assert r.changed and r.label == BVV


def test_a_noisy_crossing_of_the_shipped_layout_changes_once():
    """A point moving at 2 cm/s across the OTS volume's boundary with 0.3 mm of noise, sampled at 120 Hz: the plain
    model flickers, the filtered label changes exactly once, within the dwell of the model's first change."""
    lay = load_layout(default_layout_path())
    # find a boundary crossing on a line through the OTS volume
    ots_o = lay.ots.T_omc_ots[:3, 3]
    axis = -lay.ots.T_omc_ots[:3, 2]                 # the Vega looks along its -z
    inside = ots_o + 1.5 * axis
    assert label_point(lay, inside).label == BVV
    d = np.cross(axis, [0.0, 0.0, 1.0])
    d /= np.linalg.norm(d)
    s = np.linspace(0.0, 2.0, 2001)
    labs = [label_point(lay, inside + si * d).label for si in s]
    k = next(i for i in range(len(labs)) if labs[i] != BVV)
    boundary = inside + s[k] * d
    rng = np.random.default_rng(3)
    speed, dt = 0.02, 1 / 120
    ts = np.arange(-1.0, 1.0, dt)                    # 1 s on each side of the boundary
    raw, res = [], []
    f = RegionFilter()
    for t in ts:
        p = boundary + speed * t * d + rng.normal(0, 3e-4, 3)
        lab = label_point(lay, p)
        raw.append(lab.label)
        res.append(f.update(int(round((t + 5) * 1e9)), lab, lay.threshold_deg))
    raw_changes = sum(1 for a, b in zip(raw, raw[1:], strict=False) if a != b)
    assert raw_changes >= 3, "the test needs a model that flickers"
    ch = changes(res)
    assert len(ch) == 1 and res[ch[0]].label == labs[k]
    first_raw = next(i for i in range(len(raw)) if raw[i] != BVV)
    assert 0 <= (ch[0] - first_raw) * dt <= HysteresisParams().min_dwell_s
    for r in res:
        assert_consistent(r)
