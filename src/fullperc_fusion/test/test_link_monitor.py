"""Link monitor: the OTS's live view of the base marker against the calibrated link (injected data, made-up stamps).

Noise of a Vega seeing a marker at ~2 m: ~0.1-0.3 mm and ~3 mrad per frame at 60 Hz (as in test_calibration).
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import make_T
from fullperc_fusion.calibration.monitor import LinkMonitor, MonitorParams
from fullperc_fusion.calibration.se3_stats import se3_retract

S = 1_000_000_000
T0 = 1_700_000_000 * S
HZ = 60
T_OTS_BASE = make_T([0.2, -0.1, -1.9], Rotation.from_euler("xyz", [170.0, 10.0, 30.0], degrees=True).as_quat())
SIG_VEGA = np.array([0.1e-3, 0.1e-3, 0.3e-3, 3e-3, 3e-3, 3e-3])


def sightings(seconds, rng, step_at=None, step=(0, 0, 0, 0, 0, 0), back_at=None, start=0.0):
    """(t_ns, T_ots_base) at 60 Hz with Vega noise; from ``step_at`` to ``back_at`` s displaced by ``step``
    (tangent [dx dy dz rx ry rz] in the OTS frame)."""
    out = []
    for k in range(int(seconds * HZ)):
        t = start + k / HZ
        d = rng.normal(size=6) * SIG_VEGA
        if step_at is not None and t >= step_at and (back_at is None or t < back_at):
            d = d + np.asarray(step, dtype=float)
        out.append((T0 + round(t * S), se3_retract(T_OTS_BASE, d)))
    return out


def run(mon, data):
    return [c for t, T in data if (c := mon.add(t, T)) is not None]


@pytest.mark.parametrize("seed", range(5))
def test_noise_is_no_bump(seed):
    mon = LinkMonitor(MonitorParams(window_s=1.0))
    mon.set_reference(T_OTS_BASE)
    checks = run(mon, sightings(60.0, np.random.default_rng(seed)))
    assert len(checks) >= 100      # every half window after the first full one
    assert not any(c.bumped for c in checks)
    assert not mon.bumped and mon.n_bumped_checks == 0
    # the margin is real: the window mean stays well inside the limits
    assert max(c.dtrans_m for c in checks) < 0.25 * mon.params.trans_max_m
    assert max(c.drot_rad for c in checks) < 0.5 * mon.params.rot_max_rad


@pytest.mark.parametrize("step_at", [5.0, 5.3, 5.77])
def test_3mm_step_is_a_bump_within_one_and_a_half_windows_and_recovers(step_at):
    W = 1.0
    mon = LinkMonitor(MonitorParams(window_s=W, trans_max_m=0.002))
    mon.set_reference(T_OTS_BASE)
    data = sightings(15.0, np.random.default_rng(1), step_at=step_at, step=(3e-3, 0, 0, 0, 0, 0), back_at=10.0)
    checks = run(mon, data)
    t = [(c.t_ns - T0) / S for c in checks]
    assert not any(c.bumped for c, ti in zip(checks, t, strict=True) if ti < step_at)   # nothing before the step
    first = next(ti for c, ti in zip(checks, t, strict=True) if c.bumped)
    assert step_at < first <= step_at + 1.5 * W + 1.0 / HZ
    during = [c for c, ti in zip(checks, t, strict=True) if step_at + W < ti < 10.0]
    assert during and all(c.bumped for c in during)
    assert all(abs(c.dtrans_m - 3e-3) < 0.3e-3 for c in during)
    # put back at 10 s: clears within 1.5 windows and stays clear
    cleared = next(ti for c, ti in zip(checks, t, strict=True) if ti > 10.0 and not c.bumped)
    assert cleared <= 10.0 + 1.5 * W + 1.0 / HZ
    assert not any(c.bumped for c, ti in zip(checks, t, strict=True) if ti > 10.0 + W)
    assert not mon.bumped


def test_message_names_the_link_the_body_and_the_size():
    mon = LinkMonitor(MonitorParams(window_s=0.5), link="T_base_ots", label="OTS tool 'base'")
    mon.set_reference(T_OTS_BASE)
    assert mon.message("tool") == ""
    run(mon, sightings(3.0, np.random.default_rng(2), step_at=1.0, step=(0, 3e-3, 0, 0, 0, 0)))
    assert mon.bumped and mon.first_bump_ns is not None
    msg = mon.message("tool")
    assert "target 'tool'" in msg and "T_base_ots" in msg and "OTS tool 'base'" in msg and "bumped" in msg
    size = float(re.search(r"is ([0-9.]+) mm", msg).group(1))
    assert abs(size - 3.0) < 0.3 and "limits 2.00 mm" in msg


def test_a_turn_is_a_bump_too():
    mon = LinkMonitor(MonitorParams(window_s=1.0, rot_max_rad=0.003))
    mon.set_reference(T_OTS_BASE)
    checks = run(mon, sightings(6.0, np.random.default_rng(3), step_at=2.0, step=(0, 0, 0, 0, 0, 6e-3)))
    late = [c for c in checks if (c.t_ns - T0) / S > 3.5]
    assert late and all(c.bumped and c.drot_rad > 4e-3 and c.dtrans_m < 1e-3 for c in late)


def test_a_few_outliers_are_no_bump():
    rng = np.random.default_rng(4)
    data = sightings(10.0, rng)
    for i in range(0, len(data), 37):      # gross reflections now and then
        data[i] = (data[i][0], se3_retract(T_OTS_BASE, np.array([0.02, 0, 0, 0, 0.05, 0])))
    mon = LinkMonitor()
    mon.set_reference(T_OTS_BASE)
    checks = run(mon, data)
    assert checks and not any(c.bumped for c in checks)


def test_new_reference_clears_and_needs_a_full_window():
    mon = LinkMonitor(MonitorParams(window_s=1.0))
    mon.set_reference(T_OTS_BASE)
    moved = se3_retract(T_OTS_BASE, np.array([5e-3, 0, 0, 0, 0, 0]))
    run(mon, [(T0 + round(k / HZ * S), moved) for k in range(3 * HZ)])
    assert mon.bumped
    mon.set_reference(moved)            # re-calibrated at the new place
    assert not mon.bumped and mon.last is None
    later = [(T0 + 3 * S + round(k / HZ * S), moved) for k in range(3 * HZ)]
    checks = run(mon, later)
    assert checks and checks[0].t_ns - later[0][0] >= S      # the first judgement after a full window
    assert not any(c.bumped for c in checks)


def test_without_reference_or_disabled_nothing_is_checked():
    data = sightings(3.0, np.random.default_rng(7), step_at=0.0, step=(0.01, 0, 0, 0, 0, 0))
    assert run(LinkMonitor(), data) == []              # no reference yet
    off = LinkMonitor(MonitorParams(enabled=False))
    off.set_reference(T_OTS_BASE)
    assert run(off, data) == [] and not off.bumped
    on = LinkMonitor()
    on.set_reference(T_OTS_BASE)
    on.set_reference(None)
    assert run(on, data) == []


def test_too_few_sightings_in_a_window_are_not_judged():
    mon = LinkMonitor(MonitorParams(window_s=1.0, min_samples=10))
    mon.set_reference(T_OTS_BASE)
    sparse = [(T0 + k * S // 5, se3_retract(T_OTS_BASE, np.array([0.01, 0, 0, 0, 0, 0]))) for k in range(30)]
    assert run(mon, sparse) == []        # 5 Hz: 5 sightings per window


@pytest.mark.parametrize("kw", [{"trans_max_m": 0.0}, {"rot_max_rad": -1.0}, {"window_s": float("nan")},
                                {"min_samples": 1}, {"window_s": True}])
def test_bad_parameters_are_named(kw):
    name = next(iter(kw))
    with pytest.raises(ValueError, match=name):
        MonitorParams(**kw).validate()
