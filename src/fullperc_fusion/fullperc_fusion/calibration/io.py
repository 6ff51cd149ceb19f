"""Calibration YAML: :func:`save_calibration` / :func:`load_calibration` (format version 1).

Layout (SI; quaternion in ROS order x y z w; ``T_a_b`` maps points from b into a)::

    version: 1
    stamp_ns: 1700000000000000000       # end of the collection, sensor stamps
    duration_s: 10.0
    source: calibrate, bag ...
    conventions: ...                    # human-readable note; ignored when read
    links:
      T_omc_base:
        position: [x, y, z]             # m
        quaternion_xyzw: [x, y, z, w]
        covariance: [[6 floats] x 6]    # of the mean; tangent [dx dy dz rx ry rz], parent frame, m / rad
        n_samples: 600
        n_inliers: 598
        rms_trans_mm: 0.21              # per-sample residuals of the inliers
        max_trans_mm: 0.70
        rms_rot_mrad: 1.9
        max_rot_mrad: 6.1
        source: OMC body 'base'

Floats are written by PyYAML as ``repr`` and so read back bit for bit. Reading checks every field and raises
:class:`CalibrationError` naming the file and the field: missing or unknown fields, wrong types, non-finite
numbers, a quaternion whose norm is not 1 (within 1e-6), a covariance that is not 6x6, symmetric and
positive definite, n_inliers > n_samples.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fullperc_common.yaml_file import load_yaml_file
from fullperc_fusion.calibration.se3_stats import (
    CALIBRATION_VERSION,
    LINK_NAMES,
    Calibration,
    CalibrationError,
    LinkEstimate,
)

CONVENTIONS = ("T_a_b maps points from frame b into frame a; position in m; quaternion x y z w; covariance of the "
               "mean in the tangent space [dx dy dz rx ry rz] of the parent frame a: p = p_mean + d, "
               "R = Exp(r) R_mean (m, rad)")
_TOP = {"version", "stamp_ns", "duration_s", "source", "conventions", "links"}
_LINK = {"position", "quaternion_xyzw", "covariance", "n_samples", "n_inliers", "rms_trans_mm", "max_trans_mm",
         "rms_rot_mrad", "max_rot_mrad", "source"}
_SOURCE_LINK = re.compile(r"^T_(base|rig)_[a-z][a-z0-9_]*$")   # a further local source's links (sources.py)
_RESID = ("rms_trans_mm", "max_trans_mm", "rms_rot_mrad", "max_rot_mrad")


def calibration_to_dict(cal: Calibration) -> dict[str, Any]:
    links = {}
    for name, e in cal.links.items():
        d: dict[str, Any] = {
            "position": [float(x) for x in e.position],
            "quaternion_xyzw": [float(x) for x in e.quat_xyzw],
            "covariance": [[float(x) for x in row] for row in np.asarray(e.cov)],
            "n_samples": int(e.n_samples),
            "n_inliers": int(e.n_inliers),
        }
        for k in _RESID:
            d[k] = float(getattr(e, k))
        d["source"] = str(e.source)
        links[name] = d
    return {"version": int(cal.version), "stamp_ns": int(cal.stamp_ns), "duration_s": float(cal.duration_s),
            "source": str(cal.source), "conventions": CONVENTIONS, "links": links}


def save_calibration(path: str | os.PathLike, cal: Calibration) -> None:
    """Write ``cal`` (checked first, as :func:`load_calibration` would) atomically: temp file + rename."""
    data = calibration_to_dict(cal)
    p = Path(path)
    parse_calibration(data, str(p))
    text = yaml.safe_dump(data, default_flow_style=None, sort_keys=False, width=200)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read and check a calibration YAML; :class:`CalibrationError` names the file and the bad field."""
    return parse_calibration(load_yaml_file(path, "calibration file", CalibrationError), str(Path(path)))


class _Ctx:
    def __init__(self, source: str) -> None:
        self.source = source

    def err(self, where: str, what: str) -> CalibrationError:
        return CalibrationError(f"calibration file {self.source}: field '{where}': {what}")

    def fields(self, m: Any, allowed: set[str], where: str) -> Mapping:
        if not isinstance(m, Mapping):
            raise self.err(where or "(top level)", f"expected a mapping, got {type(m).__name__}")
        unknown = sorted(str(k) for k in m if k not in allowed)
        if unknown:
            raise self.err(where or "(top level)", f"unknown field(s) {unknown}")
        for k in sorted(allowed - {"conventions"}):
            if k not in m or m[k] is None:
                raise self.err(f"{where}.{k}" if where else k, "missing")
        return m

    def int_(self, v: Any, where: str, lo: int) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.err(where, f"expected an integer, got {v!r}")
        if v < lo:
            raise self.err(where, f"must be >= {lo}, got {v}")
        return int(v)

    def num(self, v: Any, where: str, lo: float | None = None) -> float:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.err(where, f"expected a number, got {v!r}")
        x = float(v)
        if not np.isfinite(x):
            raise self.err(where, f"not finite ({x})")
        if lo is not None and x < lo:
            raise self.err(where, f"must be >= {lo}, got {x}")
        return x

    def arr(self, v: Any, where: str, shape: tuple[int, ...]) -> np.ndarray:
        try:
            a = np.array(v, dtype=float)
        except (TypeError, ValueError) as e:
            raise self.err(where, f"expected numbers of shape {shape}: {e}") from e
        if a.shape != shape:
            raise self.err(where, f"shape {a.shape}, expected {shape}")
        if not np.all(np.isfinite(a)):
            raise self.err(where, "contains a non-finite number")
        return a


def _parse_link(c: _Ctx, m: Any, where: str) -> LinkEstimate:
    m = c.fields(m, _LINK, where)
    pos = c.arr(m["position"], f"{where}.position", (3,))
    q = c.arr(m["quaternion_xyzw"], f"{where}.quaternion_xyzw", (4,))
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-6:
        raise c.err(f"{where}.quaternion_xyzw", f"norm {n:.9g} is not 1")
    cov = c.arr(m["covariance"], f"{where}.covariance", (6, 6))
    if np.max(np.abs(cov - cov.T)) > 1e-9 * max(float(np.max(np.abs(cov))), 1e-300):
        raise c.err(f"{where}.covariance", "not symmetric")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError as e:
        raise c.err(f"{where}.covariance", "not positive definite") from e
    ns = c.int_(m["n_samples"], f"{where}.n_samples", 1)
    ni = c.int_(m["n_inliers"], f"{where}.n_inliers", 1)
    if ni > ns:
        raise c.err(f"{where}.n_inliers", f"{ni} > n_samples {ns}")
    res = [c.num(m[k], f"{where}.{k}", 0.0) for k in _RESID]
    if not isinstance(m["source"], str):
        raise c.err(f"{where}.source", f"expected a string, got {m['source']!r}")
    return LinkEstimate(pos, q, cov, ns, ni, *res, source=m["source"])


def parse_calibration(data: Any, source: str = "<data>") -> Calibration:
    """A :class:`Calibration` from the mapping of a calibration YAML; errors name ``source`` and the field."""
    c = _Ctx(source)
    m = c.fields(data, _TOP, "")
    version = c.int_(m["version"], "version", 0)
    if version != CALIBRATION_VERSION:
        raise c.err("version", f"{version} is not supported (this reader knows {CALIBRATION_VERSION})")
    stamp = c.int_(m["stamp_ns"], "stamp_ns", 0)
    dur = c.num(m["duration_s"], "duration_s", 0.0)
    for k in ("source", "conventions"):
        if k in m and not isinstance(m[k], str):
            raise c.err(k, f"expected a string, got {m[k]!r}")
    links = m["links"]
    if not isinstance(links, Mapping) or not links:
        raise c.err("links", "expected a non-empty mapping of link name to link")
    unknown = sorted(str(k) for k in links if k not in LINK_NAMES and not _SOURCE_LINK.match(str(k)))
    if unknown:
        raise c.err("links", f"unknown link(s) {unknown}; known: {list(LINK_NAMES)} and T_base_<source> / "
                             "T_rig_<source> of a further local source (sources.py)")
    names = [n for n in LINK_NAMES if n in links] + sorted(str(k) for k in links if k not in LINK_NAMES)
    out = {name: _parse_link(c, links[name], f"links.{name}") for name in names}
    return Calibration(out, stamp, dur, m["source"], version)
