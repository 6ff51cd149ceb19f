"""fit_noise_model (evaluation/sensor_stats.py): statistics -> noise-model file, each rule of the mapping pinned
(the statistics themselves are held to the committed bags by test/test_model_constants.py)."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_eval.evaluation.bias_variogram import LENGTH_GRID
from fullperc_eval.evaluation.sensor_stats import (
    RANDOM_WALK_TAU_S,
    fit_gauss_markov,
    noise_model_from_stats,
    regress,
    write_noise_model,
)
from fullperc_fusion.filters.measurement_models import OmcModelParams
from fullperc_fusion.filters.noise_model_file import load_noise_model


def stats(**over):
    f = {"pos_white": np.array([0.02e-3, 0.08, 0.12e-3]), "pos_total": np.array([0.13e-3, 0.5, 0.5e-3]),
         "rot_total": np.array([1.7e-3, 5.0, 4.0e-3]), "fit_median": 0.05e-3, "n_omc": 1000,
         "pos_gm": (0.05e-3, 0.25e-3, 3.0), "rot_gm2": (1.2e-3, 1.5e-3, 0.4, 11e-3, 3.8),
         "rot_gm_dist": (0.5e-3, 10e-3, 0.05)}
    f.update(over)
    return f


def test_the_mapping_of_each_constant():
    omc, bias = noise_model_from_stats(stats())
    assert omc["white_std"] == 0.02e-3 and omc["white_fit_gain"] == 0.08 and omc["white_margin_std"] == 0.12e-3
    assert omc["sys_floor"] == pytest.approx(np.sqrt(0.13e-3**2 - 0.02e-3**2))      # beyond the white floor
    assert omc["fit_gain"] == 0.5 and omc["margin_std"] == 0.5e-3 and omc["default_fit"] == 0.05e-3
    assert omc["marker_lever"] == pytest.approx(0.1)                                   # k_fit / k_rot
    assert omc["rot_sys_floor"] == pytest.approx(np.sqrt(1.7e-3**2 - (0.02e-3 / 0.1) ** 2))
    assert omc["rot_margin_std"] == 4.0e-3
    assert bias == {"sys_time": 3.0, "sys_std": 0.25e-3, "rot_sys_time": 3.8, "rot_sys_std": 11e-3,
                    "rot_bias_length": 0.05}   # the distance fit's length


def test_a_slow_rotation_part_at_the_grids_end_is_a_random_walk():
    _, bias = noise_model_from_stats(stats(rot_gm2=(1.2e-3, 1.5e-3, 0.4, 8e-3, RANDOM_WALK_TAU_S * 2)))
    assert bias["rot_sys_time"] == 0.0 and bias["rot_sys_std"] == 0.0 and bias["rot_bias_length"] == 0.0
    # same short-lag increments: 2 s^2 (1 - exp(-L/tau)) ~ 2 s^2 L / tau = q L
    assert bias["rot_bias_walk"] == pytest.approx(2 * 8e-3**2 / (RANDOM_WALK_TAU_S * 2))


def test_the_position_bias_length_and_std_come_from_the_raw_differences_fit():
    """``bias_field_std`` / ``bias_field_length`` are the semivariogram fit's s_f and L, and ``bias_length`` L too; a
    length at the fit's grid end (no level-off within the data's distances, the paper bags) writes ``bias_length`` 0
    (b kept as learnt) and keeps s_f and L (the output covariance's growth with distance). Without the differences
    (``fitted`` without ``diffs``) the file leaves them out (the built-in values stay)."""
    _, bias = noise_model_from_stats(stats(pos_gm_dist=(0.05e-3, 0.34e-3, 0.3)))
    assert (bias["bias_length"], bias["bias_field_std"], bias["bias_field_length"]) == (0.3, 0.34e-3, 0.3)
    _, bias = noise_model_from_stats(stats(pos_gm_dist=(0.0, 4.8e-3, LENGTH_GRID[1])))
    assert (bias["bias_length"], bias["bias_field_std"], bias["bias_field_length"]) == (0.0, 4.8e-3, LENGTH_GRID[1])
    assert not {"bias_length", "bias_field_std", "bias_field_length"} & set(noise_model_from_stats(stats())[1])


def test_negative_regression_terms_count_as_none():
    omc, _ = noise_model_from_stats(stats(pos_total=np.array([1.2e-3, -0.7, 5e-3]),
                                          pos_white=np.array([-0.05e-3, 0.08, 0.2e-3]),
                                          rot_total=np.array([-5e-3, 1.9, 28e-3])))
    assert omc["fit_gain"] == 0.0 and omc["white_std"] == 0.0
    assert omc["sys_floor"] == pytest.approx(1.2e-3) and omc["rot_sys_floor"] == 0.0
    assert omc["marker_lever"] == OmcModelParams().marker_lever   # no fit gain: the built-in lever


def test_regress_keeps_the_sign_of_a_coefficient():
    rng = np.random.default_rng(0)
    fit, margin = rng.uniform(0, 1e-3, 500), rng.uniform(100, 2000, 500)
    y = 4e-8 - 0.25 * fit**2 + 1e-7 * 300 / margin
    a, k, c = regress(y, fit, margin)
    assert a == pytest.approx(2e-4) and k == pytest.approx(-0.5) and c == pytest.approx(np.sqrt(1e-7))


def test_the_written_file_is_a_noise_model_fusion_node_reads(tmp_path):
    p = tmp_path / "sub" / "noise.yaml"
    write_noise_model(p, stats(), "unit test")
    nm = load_noise_model(p)
    omc, bias = noise_model_from_stats(stats())
    assert all(getattr(nm.omc, k) == pytest.approx(v) for k, v in omc.items()) and nm.bias == pytest.approx(bias)
    assert nm.source == "unit test: 1000 OMC samples against the arm's forward kinematics"


def test_each_omc_row_has_the_fit_error_of_its_own_body(cached_bag_rows):
    """Every body's quality message of an OMC frame has the frame's stamp: a row's fit error must come from the
    target's own quality topic. (It came from whichever body's quality was read last at that stamp -- the
    instrument's in the committed bags -- so the rows where the instrument was not tracked were dropped as having
    no fit error and the model's fit-error terms were regressed on another body's fit.)"""
    from fullperc_common.testing import workspace_root
    from fullperc_eval.bag.reader import BagReader
    from fullperc_eval.evaluation.replay_data import _stamp_ns
    from fullperc_eval.evaluation.sensor_stats import FIT, T
    from fullperc_fusion.margin.layout import default_layout_path, load_layout

    bag = workspace_root() / "bags" / "spec" / "G-B-P"
    reader = BagReader(bag)
    reader.open()
    own, instrument_tracked = {}, False
    try:
        for m in reader.messages(["/omc/tool/quality", "/omc/instrument/pose"]):
            msg = reader.deserialize(m.data, m.msgtype)
            if m.topic == "/omc/tool/quality":
                own[_stamp_ns(msg.header)] = float(msg.fit_error)
            else:
                instrument_tracked = True
    finally:
        reader.close()
    assert instrument_tracked                                # the bag has a second body whose quality interleaves
    g, _ = cached_bag_rows(bag, load_layout(default_layout_path()))   # bag_rows', once per session (root conftest)
    ts = np.array(sorted(own))
    i = np.clip(np.searchsorted(ts, g[:, T] * 1e9), 1, len(ts) - 1)     # rows hold seconds (float): nearest stamp
    i -= np.abs(ts[i - 1] - g[:, T] * 1e9) < np.abs(ts[i] - g[:, T] * 1e9)
    assert np.all(np.abs(ts[i] - g[:, T] * 1e9) < 1e3)
    expected = np.array([own[int(t)] for t in ts[i]])
    assert len(g) > 3000 and np.all(expected >= 0)
    assert np.array_equal(g[:, FIT], expected)


LAGS_S = np.array([1, 6, 12, 30, 60, 120, 240, 360, 600, 1200]) / 120.0   # fitted()'s lags at 120 Hz


def test_the_gauss_markov_fit_recovers_a_known_process():
    w, sy, tau = 0.05e-3, 0.25e-3, 3.0
    rms = np.sqrt(2 * w**2 + 2 * sy**2 * (1 - np.exp(-LAGS_S / tau)))
    fw, fs, ft = fit_gauss_markov(LAGS_S, rms)
    assert fw == pytest.approx(w, rel=0.02) and fs == pytest.approx(sy, rel=0.02) and ft == pytest.approx(tau, rel=0.02)


def test_increments_growing_faster_than_linearly_still_give_a_usable_model(tmp_path):
    """One ``paper`` room over a single session of six bags (the OMC miscalibration of twin seed 1, everything else
    drawn from seed 1001: a session simulated by an analysis outside the repository): the OMC's position increments
    grow faster than linearly to the last lag, so no tau gives a fit with both variances >= 0. The fit under that
    constraint puts tau at the grid's end (a bias that wanders as a random walk over the session), not zeros --
    which ``write_noise_model`` refused (``omc_bias.sys_time`` must be > 0), so such a room got no model from its
    own recording."""
    rms = np.array([0.076, 0.112, 0.15, 0.231, 0.328, 0.449, 0.612, 0.744, 1.014, 1.713]) * 1e-3
    w, sy, tau = fit_gauss_markov(LAGS_S, rms)
    assert sy > 1e-3 and tau == pytest.approx(100.0) and w >= 0.0
    model = 2 * w**2 + 2 * sy**2 * (1 - np.exp(-LAGS_S / tau))
    assert np.all(np.abs(np.sqrt(model) / rms - 1) < 0.4)   # within 40 %: the best a concave form does on it
    write_noise_model(tmp_path / "room.yaml", stats(pos_gm=(w, sy, tau)), "unit test")
    assert load_noise_model(tmp_path / "room.yaml").bias["sys_time"] == pytest.approx(100.0)

