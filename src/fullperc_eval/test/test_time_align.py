"""Time alignment of the OMC's and the Vega's stamps (``time_align``, :mod:`fullperc_eval.evaluation.time_align`).

* the core on synthetic signals: known shifts (both signs, off the sample grid, different rates and phases, noise)
  recovered to a fraction of a millisecond; drift; the motion signals' frame invariance; refusals;
* the sign convention: OTS stamps late by X -> ``offset_s = +X``, and ``ndi_driver.device_latency_s`` (subtracted
  from the Vega's stamps) ``+= X`` removes it; early by more than the current latency -> ``omc_driver``'s
  ``transport_delay_s`` takes the rest;
* the twin: a short take (:func:`fullperc_eval.sim.sync_take.sync_take`, the tool waved in both trackers' view)
  with the Vega's stamps made late in the twin itself (``ots.stamp_offset_s``: +5, 0, -5 ms), written as a bag and
  read by the installed-entry CLI: the offset recovered to <= 0.5 ms and written as a parameters file.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import yaml

from fullperc_common.testing import installed_exe
from fullperc_eval.evaluation import time_align_cli as cli
from fullperc_eval.evaluation.time_align_cli import main as cli_main
from fullperc_eval.sim.dataset import EPOCH_NS, content_from_sim, write_bag
from fullperc_eval.sim.sync_take import sync_take
from fullperc_fusion.calibration import time_offset as ta

TOL_TWIN_S = 0.0005         # the brief: 5 ms recovered to <= 0.5 ms in the twin


def _path(t: np.ndarray) -> np.ndarray:
    """A smooth, non-periodic 3-D motion (a tool waved by hand): sums of sines, ~0.1-0.4 m/s."""
    f = np.array([[0.31, 0.87], [0.53, 1.13], [0.41, 0.71]])
    a = np.array([[0.05, 0.03], [0.04, 0.02], [0.03, 0.02]])
    ph = np.array([[0.1, 2.3], [1.2, 0.7], [1.9, 2.8]])
    return np.stack([(a[k] * np.sin(2 * np.pi * f[k] * t[:, None] + ph[k])).sum(axis=1) for k in range(3)], axis=1)


def _quat(t: np.ndarray) -> np.ndarray:
    """A rotation about a wobbling axis (x y z w)."""
    ang = 0.4 * np.sin(2 * np.pi * 0.45 * t) + 0.2 * np.sin(2 * np.pi * 1.05 * t + 1.0)
    ax = np.stack([np.ones_like(t), 0.3 * np.sin(2 * np.pi * 0.2 * t), 0.2 * np.ones_like(t)], axis=1)
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    return np.concatenate([ax * np.sin(ang / 2)[:, None], np.cos(ang / 2)[:, None]], axis=1)


def _devices(shift_s: float, seed: int = 0, noise: bool = True, duration_s: float = 12.0, drift: float = 0.0):
    """OMC at 120 Hz, Vega at 60 Hz with its own phase; the Vega's stamps = truth + shift (+ drift x t)."""
    rng = np.random.default_rng(seed)
    ta_ = np.arange(0.0, duration_s, 1 / 120)
    tb = np.arange(rng.uniform(0, 1 / 60), duration_s, 1 / 60)
    pa = _path(ta_) + (2e-4 * rng.standard_normal((len(ta_), 3)) if noise else 0)
    pb = _path(tb) + (1.2e-4 * rng.standard_normal((len(tb), 3)) if noise else 0)
    return ta_, pa, tb + shift_s + drift * tb, pb


@pytest.mark.parametrize("shift_ms", [5.0, 0.0, -12.3, 37.1])
def test_synthetic_shift_recovered(shift_ms):
    ta_, pa, tb, pb = _devices(shift_ms * 1e-3, seed=int(abs(shift_ms) * 10))
    r = ta.align_tracks(ta_, pa, tb, pb)
    assert abs(r.offset_s - shift_ms * 1e-3) < 0.3e-3, r
    assert r.peak_corr > 0.95 and abs(r.gain - 1) < 0.05
    assert len(r.windows) >= 3 and 1e-6 < r.offset_sigma_s < 1e-3
    # noise-free: only the two filters' different rates are left
    ta_, pa, tb, pb = _devices(shift_ms * 1e-3, noise=False)
    assert abs(ta.align_tracks(ta_, pa, tb, pb).offset_s - shift_ms * 1e-3) < 0.05e-3


def test_sign_convention_and_the_parameter_that_corrects_it():
    """OTS stamps late by 5 ms relative to OMC -> +5 ms; the Vega's device_latency_s + 5 ms removes it."""
    ta_, pa, tb, pb = _devices(0.005, seed=1)
    r = ta.align_tracks(ta_, pa, tb, pb)
    assert r.offset_s == pytest.approx(0.005, abs=0.3e-3)
    assert cli.describe(r.offset_s).startswith("OTS stamps are late by 5.")
    assert cli.describe(-0.005) == "OTS stamps are early by 5.000 ms relative to OMC"
    p = cli.corrected_parameters(r.offset_s, device_latency_s=0.010)
    assert p == {"ndi_driver": {"device_latency_s": pytest.approx(0.015, abs=0.3e-3)}}
    # what the driver does with it: stamp = (what it stamped before) - (new - old latency) -> aligned
    corrected = tb - (p["ndi_driver"]["device_latency_s"] - 0.010)
    assert abs(ta.align_tracks(ta_, pa, corrected, pb).offset_s) < 0.3e-3
    # early by more than the current latency: the Vega's latency cannot go below 0, the OMC's stamps move instead
    p = cli.corrected_parameters(-0.005, device_latency_s=0.002, transport_delay_s=0.001)
    assert p == {"ndi_driver": {"device_latency_s": 0.0}, "omc_driver": {"transport_delay_s": 0.004}}
    with pytest.raises(ta.AlignmentError, match="transport_delay_s"):
        cli.corrected_parameters(-2.0)
    text = cli.params_yaml(p, "a comment\nover two lines")
    assert text.startswith("# a comment\n# over two lines\n")
    assert yaml.safe_load(text) == {"/**/ndi_driver": {"ros__parameters": {"device_latency_s": 0.0}},
                                    "/**/omc_driver": {"ros__parameters": {"transport_delay_s": 0.004}}}


def test_drift_is_a_line_through_the_window_offsets():
    ta_, pa, tb, pb = _devices(0.003, seed=2, duration_s=24.0, drift=200e-6)
    r = ta.align_tracks(ta_, pa, tb, pb)
    assert r.drift == pytest.approx(200e-6, abs=60e-6)
    assert r.offset_s == pytest.approx(0.003 + 200e-6 * r.t_ref_s, abs=0.3e-3)   # the offset at mid-recording
    ta_, pa, tb, pb = _devices(0.003, seed=2, duration_s=24.0)
    assert abs(ta.align_tracks(ta_, pa, tb, pb).drift) < 60e-6


def test_motion_signals_do_not_depend_on_the_frames():
    """Speed: any rigid change of the world frame; angular speed: also a body origin elsewhere on the body."""
    t = np.arange(0, 5, 1 / 120)
    p, q = _path(t), _quat(t)
    R = ta._rotmats(q).reshape(-1, 3, 3)
    c = 2 ** -0.5
    W = np.array([[c, -c, 0], [c, c, 0], [0, 0, 1]])          # another world frame: rotated, moved
    lever = np.array([0.05, -0.02, 0.1])                      # another origin on the body
    for sig, p2, q2 in [("speed", p @ W.T + [1, 2, 3], None),
                        ("angular", (p + R @ lever) @ W.T, np.array([0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)]))]:
        a = ta.motion_signal(t, p, q, sig)
        if q2 is not None:   # the world rotated by 45 deg about z: q -> q_W * q
            x, y, z, w = q2
            qx, qy, qz, qw = q.T
            q2 = np.stack([w * qx + x * qw + y * qz - z * qy, w * qy - x * qz + y * qw + z * qx,
                           w * qz + x * qy - y * qx + z * qw, w * qw - x * qx - y * qy - z * qz], axis=1)
        b = ta.motion_signal(t, p2, q2, sig)
        np.testing.assert_allclose(b.segments[0][1], a.segments[0][1], atol=1e-9)
    # the filter's half window is cut at each end of a segment (a one-sided derivative would shift it)
    m = ta.motion_signal(np.r_[t[:300], t[400:]], np.r_[p[:300], p[400:]])
    assert len(m.segments) == 2 and m.segments[0][0][0] == pytest.approx(t[6])


def test_refusals():
    t = np.arange(0, 10, 1 / 60)
    still = np.zeros((len(t), 3)) + 1e-4 * np.random.default_rng(0).standard_normal((len(t), 3))
    with pytest.raises(ta.AlignmentError, match="correlation"):
        ta.align_tracks(t, still, t, still[::-1].copy())
    ta_, pa, tb, pb = _devices(0.0, duration_s=1.5)
    with pytest.raises(ta.AlignmentError, match="overlap"):
        ta.align_tracks(ta_, pa, tb, pb)
    with pytest.raises(ta.AlignmentError, match="OTS"):
        ta.align_tracks(ta_, pa, tb[:3], pb[:3])
    with pytest.raises(ValueError, match="orientations"):
        ta.motion_signal(t, still, None, "angular")


# ---------------------------------------------------------------------------------------------------- the twin
@pytest.fixture(scope="module")
def twin_bags(tmp_path_factory):
    """One short take per injected Vega stamp offset (twin ``ots.stamp_offset_s``), written as bags."""
    out = {}
    for off_ms in (5.0, 0.0, -5.0):
        run = sync_take(seed=0, ots_stamp_offset_s=off_ms * 1e-3)
        assert run.ots.stamp_offset_s == off_ms * 1e-3
        out[off_ms] = write_bag(tmp_path_factory.mktemp("sync") / f"sync_{off_ms:+.0f}ms", content_from_sim(run))
        out[f"run{off_ms}"] = run
    return out


def _cli(capsys, *argv) -> tuple[int, dict, str]:
    rc = cli_main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, (json.loads(cap.out.strip().splitlines()[-1]) if rc == 0 else {}), cap.err


def test_twin_stamp_offset_is_in_the_bag_only(twin_bags):
    """The twin's offset moves only the Vega's stamps: the measurements and the truth are those of the run without."""
    late, zero = twin_bags["run5.0"], twin_bags["run0.0"]
    np.testing.assert_array_equal(late.ots.t_ns, zero.ots.t_ns)
    np.testing.assert_array_equal(late.ots.tools["tool"].position, zero.ots.tools["tool"].position)
    c_late, c_zero = content_from_sim(late), content_from_sim(zero)
    np.testing.assert_array_equal(c_late.ots.t_ns - c_zero.ots.t_ns, 5_000_000)
    np.testing.assert_array_equal(c_late.omc.t_ns, c_zero.omc.t_ns)
    assert c_zero.ots.t_ns[0] == zero.ots.t_ns[0] + EPOCH_NS


@pytest.mark.parametrize("off_ms", [5.0, 0.0, -5.0])
def test_twin_offset_recovered_and_written(twin_bags, tmp_path, capsys, off_ms):
    params = tmp_path / "time_offset.yaml"
    rc, doc, err = _cli(capsys, twin_bags[off_ms], "--out", params)
    assert rc == 0, err
    assert abs(doc["offset_s"] - off_ms * 1e-3) <= TOL_TWIN_S, doc
    assert 0 < doc["offset_sigma_s"] < 1e-3 and doc["peak_corr"] > 0.9
    if off_ms:
        assert doc["meaning"].startswith(f"OTS stamps are {'early' if off_ms < 0 else 'late'} by ")
    assert doc["meaning"] in err
    written = yaml.safe_load(params.read_text())
    assert written == {f"/**/{node}": {"ros__parameters": vals} for node, vals in doc["params"].items()}
    lat = written["/**/ndi_driver"]["ros__parameters"]["device_latency_s"]
    if off_ms > 0:      # recorded with the default 0: the Vega's latency to subtract is the offset
        assert lat == pytest.approx(off_ms * 1e-3, abs=TOL_TWIN_S) and "/**/omc_driver" not in written
    elif off_ms < 0:    # the Vega early: its latency stays 0, the OMC's stamps move back by the offset
        assert lat == 0.0
        assert written["/**/omc_driver"]["ros__parameters"]["transport_delay_s"] == pytest.approx(
            -off_ms * 1e-3, abs=TOL_TWIN_S)


def test_twin_negative_offset_with_a_latency_already_set(twin_bags, capsys):
    """Recorded with device_latency_s 0.014 and the Vega's stamps 5 ms early: it becomes ~0.009, no file written."""
    rc, doc, _ = _cli(capsys, twin_bags[-5.0], "--device-latency", "0.014", "--out", "-")
    assert rc == 0 and doc["params_file"] is None
    assert doc["params"] == {"ndi_driver": {"device_latency_s": pytest.approx(0.009, abs=TOL_TWIN_S)}}


def test_cli_errors(twin_bags, capsys, tmp_path):
    rc, _, err = _cli(capsys, twin_bags[0.0], "--ots-topic", "/ots/nothing/pose", "--out", "-")
    assert rc == 1 and "error:" in err and "/ots/nothing/pose" in err and "/ots/tool/pose" in err
    rc, _, err = _cli(capsys, twin_bags[0.0], "--ots-topic", "/ots/tool/quality", "--out", "-")
    assert rc == 1 and "not geometry_msgs/msg/PoseStamped" in err
    rc, _, err = _cli(capsys, tmp_path / "no_bag", "--out", "-")
    assert rc == 1 and err.startswith("error:")


def test_installed_executable_help():
    out = subprocess.run([installed_exe("fullperc_eval", "time_align"), "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "usage: time_align" in out and "late by offset_s relative to OMC" in out and "--device-latency" in out
