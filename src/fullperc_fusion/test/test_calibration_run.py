"""CalibrationRun: what the calibrate executable and fusion_node's ~/calibrate run (made-up stamps and host times)."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_common.testing import wait_for
from fullperc_common.transforms import T_to_pq, make_T
from fullperc_fusion.calibration.run import CalibrationRun, summary
from fullperc_fusion.calibration.se3_stats import CalibrationBodies, se3_retract

S = 1_000_000_000
T0 = 1_700_000_000 * S
T_OMC_BASE = make_T([1.0, 0.5, 0.8])
T_OTS_BASE = make_T([0.1, 0.2, -1.9])


def feed(run, seconds, rng, move_at=None, start=0.0):
    for k in range(int(seconds * 120)):
        t = start + k / 120
        omc = se3_retract(T_OMC_BASE, rng.normal(size=6) * 2e-4)
        if move_at is not None and t >= move_at:
            omc[:3, 3] += [5e-3, 0, 0]
        run.add("omc", "base", T0 + round(t * S), *T_to_pq(omc))          # position + quaternion, as from a topic
        if k % 2 == 0:
            run.add("ots", "base", T0 + round(t * S), se3_retract(T_OTS_BASE, rng.normal(size=6) * 1e-4))  # 4x4


def test_a_still_setup_is_calibrated_when_the_stamps_span_the_duration():
    run = CalibrationRun(("T_omc_base", "T_base_ots"), CalibrationBodies(), 2.0, now=100.0, timeout_s=5.0)
    feed(run, 1.5, np.random.default_rng(0))
    assert not run.poll(100.5) and not run.done          # host time does not end it, the stamps do
    feed(run, 1.0, np.random.default_rng(1), start=1.5)
    assert run.poll(100.6) and run.result is not None and run.error is None
    assert set(run.result.links) == {"T_omc_base", "T_base_ots"}
    text = summary(run.result)
    assert "T_omc_base p=[1.0000, 0.5000, 0.8000] m" in text and "inliers" in text and "mm" in text
    assert not run.add("omc", "base", T0 + 3 * S, T_OMC_BASE)     # done: ignored


def test_a_moved_body_is_refused_naming_it():
    run = CalibrationRun(("T_omc_base", "T_base_ots"), CalibrationBodies(), 2.0, now=0.0)
    feed(run, 2.2, np.random.default_rng(2), move_at=1.0)
    assert run.poll(1.0) and run.result is None
    assert run.error.startswith("OMC body 'base' moved during the collection")
    assert "OTS tool 'base'" not in run.error      # the OTS did not move


def test_no_data_ends_at_the_host_time_bound():
    run = CalibrationRun(("T_omc_base", "T_base_ots"), CalibrationBodies(), 2.0, now=10.0, timeout_s=3.0)
    feed(run, 0.5, np.random.default_rng(3))       # the stream stops after 0.5 s
    assert not run.poll(14.9)
    assert run.poll(15.0) and run.result is None
    assert "too few sightings: they span 0.5 s of the 2 s needed after 5 s of host time" in run.error
    assert "OMC body 'base': 60" in run.error and "OTS tool 'base': 30" in run.error


def test_bad_arguments():
    with pytest.raises(ValueError, match="timeout_s"):
        CalibrationRun(("T_omc_base",), CalibrationBodies(), 1.0, now=0.0, timeout_s=0.0)
    with pytest.raises(ValueError, match="links"):
        CalibrationRun(("T_x",), CalibrationBodies(), 1.0, now=0.0)


def test_in_the_background_the_result_comes_at_a_later_poll_equal_and_later_sightings_are_not_collected():
    """fusion_node's form (background=True): the poll that finds the collection complete starts the robust means
    on the worker and returns False at once; a poll after it finished gives the same calibration the synchronous
    form gives; sightings in between are ignored (the worker reads the collection)."""
    runs = [CalibrationRun(("T_omc_base", "T_base_ots"), CalibrationBodies(), 2.0, now=0.0, background=bg)
            for bg in (False, True)]
    for r in runs:
        feed(r, 2.5, np.random.default_rng(4))
    sync, bg = runs
    assert sync.poll(1.0) and sync.result is not None
    assert not bg.poll(1.0) and not bg.done
    assert not bg.add("omc", "base", T0 + S, T_OMC_BASE)          # inside the window, but the means are running
    wait_for(lambda: bg.poll(1.1), 60.0, 0.01, what="the background calibration")   # a liveness bound
    assert bg.error is None and summary(bg.result) == summary(sync.result)
    for name, e in sync.result.links.items():
        np.testing.assert_array_equal(bg.result.links[name].position, e.position)


def test_a_refusal_in_the_background_is_a_refusal():
    run = CalibrationRun(("T_omc_base", "T_base_ots"), CalibrationBodies(), 2.0, now=0.0, background=True)
    feed(run, 2.2, np.random.default_rng(2), move_at=1.0)
    wait_for(lambda: run.poll(1.0), 60.0, 0.01, what="the background calibration")
    assert run.result is None and run.error.startswith("OMC body 'base' moved during the collection")
