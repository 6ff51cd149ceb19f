"""The noise-model constants are the raw-sensor statistics of the committed bags (issue 18: "calibrated on
raw-sensor statistics"; docs/fullperc_filter.md).

``fit_noise_model`` (``fullperc_eval.evaluation.sensor_stats``) computes them from every tracked OMC and Vega
sample of ``bags/spec`` (and, for the orientation bias's slow part, ``bags/paper``) against the Diana forward
kinematics -- no filter runs. This test recomputes them and fails when a constant of ``measurement_models`` or
``FullpercParams`` is no longer what the bags give (to 2 %: the constants are written with three digits), e.g.
after the twin or the bags changed and nobody refitted the models.

The rows are read in bulk (``sensor_stats.bag_rows``); the first test pins them to the per-message reading through
the node's pipeline (``bag_rows_per_message``), bit for bit, on a committed bag.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from fullperc_eval.evaluation import sensor_stats
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.measurement_models import LocalModelParams, OmcModelParams
from fullperc_fusion.margin.layout import default_layout_path, load_layout

ROOT = Path(__file__).resolve().parents[1]

REL = 0.02


def test_bag_rows_read_in_bulk_are_the_per_message_rows(monkeypatch):
    """bag_rows (records decoded in bulk, only the chain's link estimation per record, stacked mapping) gives the
    rows of bag_rows_per_message (rosbags' deserialiser, every message through TargetPipeline), bit for bit, without
    falling back to it. The bag: one with both devices, the link calibration and the target's qualities (all are)."""
    bag = ROOT / "bags" / "spec" / "G-B-P"
    layout = load_layout(default_layout_path())
    ref = sensor_stats.bag_rows_per_message(bag, layout)

    def no_fallback(*_a, **_k):
        raise AssertionError("bag_rows fell back to the per-message reading")
    monkeypatch.setattr(sensor_stats, "bag_rows_per_message", no_fallback)
    got = sensor_stats.bag_rows(bag, layout)
    assert len(ref[0]) > 1000 and len(ref[1]) > 100                     # both devices, their fit errors read
    assert (ref[0][:, sensor_stats.FIT] > 0).all() and (ref[1][:, sensor_stats.FIT] > 0).all()
    for a, b in zip(got, ref, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert np.array_equal(a, b, equal_nan=True)


@pytest.fixture(scope="module")
def stats(cached_bag_rows):
    """fit_noise_model's statistics of each profile's bags; each bag's rows are sensor_stats.bag_rows', computed once
    per test session (root conftest: the other tests of the committed bags' raw rows read the same)."""
    layout = load_layout(default_layout_path())
    cached_bag_rows.prefetch(sorted(b for p in ("spec", "paper") for b in (ROOT / "bags" / p).iterdir() if b.is_dir()),
                             layout)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sensor_stats, "bag_rows", cached_bag_rows)
        return {p: sensor_stats.fitted(*sensor_stats.profile_rows(ROOT / "bags" / p, layout),
                                       sensor_stats.profile_differences(ROOT / "bags" / p)) for p in ("spec", "paper")}


def test_omc_model_constants_are_the_spec_bags_statistics(stats):
    """Every constant of the built-in OMC model is what fit_noise_model writes for the spec bags."""
    omc, bias = sensor_stats.noise_model_from_stats(stats["spec"])
    pr = OmcModelParams()
    assert set(omc) == {f.name for f in dataclasses.fields(pr)} - {"margin_ref", "margin_min"}
    for name, v in omc.items():
        assert getattr(pr, name) == pytest.approx(v, rel=REL), name
    assert FullpercParams().sys_time == pytest.approx(bias["sys_time"], rel=REL)
    assert FullpercParams().sys_std == pytest.approx(bias["sys_std"], rel=REL)


def test_systematic_error_parameters_are_the_structure_function_fits(stats):
    pr = FullpercParams()
    _, s, tau = stats["spec"]["pos_gm"]
    assert pr.sys_std == pytest.approx(s, rel=REL) and pr.sys_time == pytest.approx(tau, rel=REL)
    _, _, _, s_slow, tau_slow = stats["paper"]["rot_gm2"]
    assert pr.rot_sys_std == pytest.approx(s_slow, rel=REL) and pr.rot_sys_time == pytest.approx(tau_slow, rel=REL)
    # beta's spatial decay: the paper bags' rotation error over distance (the same fit, lags in metres)
    assert pr.rot_bias_length == pytest.approx(stats["paper"]["rot_gm_dist"][2], rel=REL)
    # rot_bias_walk (what of beta stays) is of the order of the short-lag increments of spec's slow rotation part,
    # 2 s^2 / tau (1.5e-6 rad^2/s: 1.44 mrad / 2.8 s)
    _, _, _, s_spec, tau_spec = stats["spec"]["rot_gm2"]
    assert 0.3 <= pr.rot_bias_walk / (2 * s_spec**2 / tau_spec) <= 3.0


def test_vega_orientation_constant_is_the_raw_vega_statistic(stats):
    assert LocalModelParams().rot_std_ref == pytest.approx(stats["spec"]["ots_rot_rms"], rel=0.05)


def test_position_bias_decay_is_written_where_the_raw_differences_show_a_length(stats):
    """``bias_length`` / ``bias_field_std`` of a noise-model file: the semivariogram over distance of the raw
    (OMC - local chain) differences (bias_variogram; no truth involved), fitted as nugget + s_f^2 (1 - exp(-h / L)).
    The spec bags level off inside the Vega's reach (a length of decimetres is written); the paper bags' error field
    holds beyond it, the fit runs to its grid's end and 0 (off, the built-in default) is written, with the fit's s_f and
    L for the output covariance. The built-in s_f and L are the spec bags' fit."""
    spec = sensor_stats.noise_model_from_stats(stats["spec"])[1]
    paper = sensor_stats.noise_model_from_stats(stats["paper"])[1]
    assert 0.05 < spec["bias_length"] < 2.0 and 0.0 < spec["bias_field_std"] < 2e-3, spec
    assert paper["bias_length"] == 0.0 and paper["bias_field_std"] > 1e-3, paper   # millimetres: paper's OMC
    assert stats["paper"]["pos_gm_dist"][2] > 1.0    # the fit's length: at its grid's end, not a short one
    assert paper["bias_field_length"] == stats["paper"]["pos_gm_dist"][2]
    pr = FullpercParams()
    assert pr.bias_length == 0.0
    assert pr.bias_field_std == pytest.approx(spec["bias_field_std"], rel=0.02), spec
    assert pr.bias_field_length == pytest.approx(spec["bias_field_length"], rel=0.02), spec
