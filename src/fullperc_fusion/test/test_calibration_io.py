"""Calibration YAML: exact round trip, and every malformed file refused naming the file and the field."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from fullperc_common.transforms import make_T
from fullperc_fusion.calibration.io import calibration_to_dict, load_calibration, save_calibration
from fullperc_fusion.calibration.se3_stats import Calibration, CalibrationError, robust_se3_mean, se3_retract


def make_cal() -> Calibration:
    rng = np.random.default_rng(0)
    links = {}
    for name, sig in (("T_omc_base", 1e-3), ("T_base_ots", 3e-3)):
        T0 = make_T(rng.normal(size=3), Rotation.from_rotvec(rng.normal(size=3)).as_quat())
        Ts = np.stack([se3_retract(T0, rng.normal(size=6) * sig) for _ in range(50)])
        links[name] = robust_se3_mean(Ts, source=f"test {name}")
    return Calibration(links, stamp_ns=1_700_000_000_123_456_789, duration_s=10.0 / 3, source="unit test")


def test_round_trip_is_exact(tmp_path):
    cal = make_cal()
    p = tmp_path / "sub" / "cal.yaml"
    save_calibration(p, cal)
    back = load_calibration(p)
    assert (back.version, back.stamp_ns, back.duration_s, back.source) == (1, cal.stamp_ns, cal.duration_s,
                                                                           "unit test")
    assert set(back.links) == set(cal.links)
    for name, a in cal.links.items():
        b = back.links[name]
        assert np.array_equal(a.position, b.position)
        assert np.array_equal(a.quat_xyzw, b.quat_xyzw)
        assert np.array_equal(a.cov, b.cov)
        assert np.array_equal(a.T, b.T)
        for k in ("n_samples", "n_inliers", "rms_trans_mm", "max_trans_mm", "rms_rot_mrad", "max_rot_mrad", "source"):
            assert getattr(a, k) == getattr(b, k), k
    # and again: the file is a fixed point
    save_calibration(tmp_path / "again.yaml", back)
    assert (tmp_path / "again.yaml").read_text() == p.read_text()
    assert [f.name for f in p.parent.iterdir()] == ["cal.yaml"]  # no temp file left behind


def test_quaternion_is_written_xyzw(tmp_path):
    cal = make_cal()
    e = cal.links["T_omc_base"]
    th = 0.4
    e.position, e.quat_xyzw = np.zeros(3), np.array([np.sin(th / 2), 0.0, 0.0, np.cos(th / 2)])
    save_calibration(tmp_path / "c.yaml", cal)
    d = yaml.safe_load((tmp_path / "c.yaml").read_text())
    assert d["links"]["T_omc_base"]["quaternion_xyzw"] == [np.sin(th / 2), 0.0, 0.0, np.cos(th / 2)]
    assert np.allclose(load_calibration(tmp_path / "c.yaml").T("T_omc_base")[:3, :3],
                       Rotation.from_euler("x", th).as_matrix())


def write(tmp_path, data, name="bad.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def good():
    return calibration_to_dict(make_cal())


def _set(d, path, value):
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[k]
    if value is KeyError:
        del d[keys[-1]]
    else:
        d[keys[-1]] = value


NAN_COV = [[float("nan")] * 6] * 6
NON_PD = np.diag([1e-8, 1e-8, 1e-8, 1e-8, 1e-8, -1e-8]).tolist()
ASYM = (np.eye(6) * 1e-8 + np.triu(np.ones((6, 6)), 1) * 1e-9).tolist()


@pytest.mark.parametrize("path,value,field,why", [
    ("version", KeyError, "version", "missing"),
    ("version", 2, "version", "not supported"),
    ("stamp_ns", -1, "stamp_ns", ">= 0"),
    ("stamp_ns", 1.5, "stamp_ns", "integer"),
    ("duration_s", float("nan"), "duration_s", "not finite"),
    ("source", KeyError, "source", "missing"),
    ("links", {}, "links", "non-empty"),
    ("links.T_foo", {}, "links", "unknown link"),
    ("extra", 1, "(top level)", "unknown field"),
    ("links.T_omc_base.covariance", KeyError, "links.T_omc_base.covariance", "missing"),
    ("links.T_omc_base.position", [0.0, float("nan"), 0.0], "links.T_omc_base.position", "non-finite"),
    ("links.T_omc_base.position", [0.0, 1.0], "links.T_omc_base.position", "shape"),
    ("links.T_omc_base.quaternion_xyzw", [0.0, 0.0, 0.0, 0.9], "links.T_omc_base.quaternion_xyzw", "norm"),
    ("links.T_base_ots.covariance", NAN_COV, "links.T_base_ots.covariance", "non-finite"),
    ("links.T_base_ots.covariance", NON_PD, "links.T_base_ots.covariance", "not positive definite"),
    ("links.T_base_ots.covariance", ASYM, "links.T_base_ots.covariance", "not symmetric"),
    ("links.T_base_ots.covariance", [[1.0] * 5] * 6, "links.T_base_ots.covariance", "shape"),
    ("links.T_base_ots.n_inliers", 51, "links.T_base_ots.n_inliers", "> n_samples"),
    ("links.T_base_ots.n_samples", True, "links.T_base_ots.n_samples", "integer"),
    ("links.T_base_ots.rms_rot_mrad", -1.0, "links.T_base_ots.rms_rot_mrad", ">= 0"),
    ("links.T_base_ots.rms_rot_mrad", "x", "links.T_base_ots.rms_rot_mrad", "number"),
    ("links.T_base_ots.source", 3, "links.T_base_ots.source", "string"),
    ("links.T_base_ots.typo", 3, "links.T_base_ots", "unknown field"),
])
def test_malformed_file_refused_naming_field(tmp_path, path, value, field, why):
    d = good()
    _set(d, path, value)
    p = write(tmp_path, d)
    with pytest.raises(CalibrationError) as e:
        load_calibration(p)
    msg = str(e.value)
    assert msg.startswith(f"calibration file {p}: field '{field}'"), msg
    assert why in msg, msg


def test_unreadable_files_refused(tmp_path):
    with pytest.raises(CalibrationError, match="missing.yaml: cannot read"):
        load_calibration(tmp_path / "missing.yaml")
    (tmp_path / "broken.yaml").write_text("version: [1\n")
    with pytest.raises(CalibrationError, match="broken.yaml: not valid YAML"):
        load_calibration(tmp_path / "broken.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(CalibrationError, match=r"list.yaml: field '\(top level\)': expected a mapping"):
        load_calibration(tmp_path / "list.yaml")


def test_conventions_note_is_optional(tmp_path):
    d = good()
    assert "x y z w" in d["conventions"]
    del d["conventions"]
    assert set(load_calibration(write(tmp_path, d)).links) == {"T_omc_base", "T_base_ots"}


def test_save_refuses_an_invalid_calibration(tmp_path):
    cal = make_cal()
    cal.links["T_omc_base"].cov = -np.eye(6)
    with pytest.raises(CalibrationError, match="T_omc_base.covariance"):
        save_calibration(tmp_path / "x.yaml", cal)
    assert not (tmp_path / "x.yaml").exists()
