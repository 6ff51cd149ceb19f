"""Offline runs: determinism, array shapes and units, ground truth consistency, error sources switch off."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_common.transforms import inv_T
from fullperc_eval.sim.run import omc_errors, simulate
from fullperc_eval.sim.runner import run_task
from fullperc_eval.sim.scene import build_scene
from fullperc_eval.sim.tasks import plan_task
from fullperc_eval.sim.trajectories import JointArc

TASK = "P-G-B"


@pytest.fixture(scope="module")
def run0():
    return run_task(TASK, seed=0)


def _short(scene, plan, seconds=3.0):
    a = plan.arc
    return JointArc(a.q0, a.joint, a.start, a.start + (a.end - a.start) * 0.2, seconds, 0.2, 0.2)


@pytest.mark.slow
def test_seeded_runs_are_bit_identical(run0):
    again = run_task(TASK, seed=0).flat()
    # another seed gives another tool measurement (the tool's data do not depend on the extra targets:
    # test_sim_walker.py, test_sim_breathing.py, so their simulation is left out here)
    other = run_task(TASK, seed=1, extra_targets=False).flat()
    first = run0.flat()
    assert first.keys() == again.keys()
    for k in first:
        np.testing.assert_array_equal(first[k], again[k], err_msg=k)
    assert not np.array_equal(first["omc/tool/position"], other["omc/tool/position"], equal_nan=True)


def test_arrays_shapes_rates_and_truth(run0):
    r = run0
    F = len(r.omc.t_ns)
    assert F == pytest.approx(r.duration_s * 120, abs=2)
    assert np.all(np.diff(r.omc.frame_number.astype(np.int64)) == 1)
    assert np.all(np.diff(r.omc.t_ns) > 0) and np.all(np.diff(r.ots.t_ns) > 0)
    assert len(r.ots.t_ns) == pytest.approx(r.duration_s * 60, abs=2)
    for b in r.omc.bodies.values():
        assert b.position.shape == (F, 3) and b.quat_xyzw.shape == (F, 4)
        assert np.all(np.isfinite(b.position[b.tracked])) and np.all(np.isnan(b.position[~b.tracked]))
        np.testing.assert_allclose(np.linalg.norm(b.quat_xyzw[b.tracked], axis=1), 1.0, atol=1e-9)
    # truth = static chain of the true transforms and FK of the joint states
    st = r.static
    np.testing.assert_allclose(r.truth.T_base_tool, inv_T(st["T_omc_base"]) @ r.truth.T_omc_tool, atol=1e-12)
    from fullperc_drivers.diana_kinematics import DianaKinematics

    k = len(r.diana.t_ns) // 2
    i = int(np.searchsorted(r.omc.t_ns, r.diana.t_ns[k]))
    assert r.omc.t_ns[i] == r.diana.t_ns[k]  # 120 Hz and 100 Hz grids meet every 50 ms
    T = st["T_omc_diana_base"] @ DianaKinematics().fk(r.diana.q[k]) @ st["T_flange_tool"]
    np.testing.assert_allclose(T, r.truth.T_omc_tool[i], atol=1e-12)
    np.testing.assert_allclose(st["T_omc_ots_rig"] @ st["T_ots_rig_ots"], st["T_omc_ots"], atol=1e-12)


def test_measurements_are_close_to_truth_but_not_equal(run0):
    e = omc_errors(run0)
    assert e["tracked"].mean() > 0.5
    assert 1e-5 < np.median(e["omc"]) < 0.02  # millimetre-class errors, never exactly zero
    v = run0.ots.tools["tool"]
    assert v.visible.any()
    truth_ots = inv_T(run0.static["T_omc_ots"]) @ run0.truth_ots.T_omc_tool
    err = np.linalg.norm(v.position[v.visible] - truth_ots[v.visible, :3, 3], axis=1)
    assert np.median(err) < 0.5e-3  # Vega: sub-millimetre
    assert np.all(np.isnan(v.position[~v.visible]))


def test_without_noise_miscalibration_and_staff_the_omc_is_exact():
    scene = build_scene(0, miscalibration=False)
    plan = plan_task(TASK, scene)
    scene = scene.with_diana_base(plan.T_omc_diana_base)
    r = simulate(scene, _short(scene, plan), task=TASK, noise=False, staff=False)
    e = omc_errors(r)
    assert e["tracked"].any()
    assert e["omc"].max() < 1e-9
    v = r.ots.tools["base"]
    assert v.visible.all()
    truth = inv_T(r.static["T_omc_ots"]) @ r.static["T_omc_base"]
    np.testing.assert_allclose(v.position, np.broadcast_to(truth[:3, 3], v.position.shape), atol=1e-9)
