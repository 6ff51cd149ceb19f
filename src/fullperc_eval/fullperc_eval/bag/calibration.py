"""``calibration.yaml``: the static transforms that turn a bag's joint states into ground truth.

The two static transforms (robot base in the ``base`` frame, tool on the flange) travel with the bag as
``calibration.yaml`` in the bag directory: the dataset generator and the simulator write them (their true
values), the evaluator reads them (:mod:`fullperc_eval.evaluation.ground_truth` explains why it never estimates
them from the bag it evaluates). For a real recording they are the user's robot-world / hand-eye calibration.

File format (metres, quaternions x y z w; ``source`` is free text saying where the numbers come from)::

    T_base_diana_base: [x, y, z, qx, qy, qz, qw]
    T_flange_tool:     [x, y, z, qx, qy, qz, qw]
    T_omc_base:        [x, y, z, qx, qy, qz, qw]   # optional
    source: "simulator truth (fullperc_eval.dataset, task G-B-P, seed 0)"

An optional ``T_omc_base`` (true pose of the base marker in ``omc``) places the truth in the layout frame for
the region labels.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from fullperc_common.transforms import T_to_pq, make_T

CALIBRATION_FILE = "calibration.yaml"
REQUIRED = ("T_base_diana_base", "T_flange_tool")
OPTIONAL = ("T_omc_base",)
# First line of every file written: the committed sample bags carry it as it is (regenerated bags stay
# byte-identical to them), so it still names the module that defined the format when they were made.
HEADER = ("# Calibration linking the Diana's forward kinematics to the base marker (fullperc_eval.ground_truth).\n"
          "# Metres, quaternions x y z w. T_a_b maps points of frame b into frame a.\n")


class CalibrationError(ValueError):
    """The calibration file is missing or malformed; the message names the file and the field."""


@dataclass
class Calibration:
    T_base_diana_base: np.ndarray
    T_flange_tool: np.ndarray
    T_omc_base: np.ndarray | None = None
    source: str = ""

    def as_dict(self) -> dict:
        out: dict = {}
        for k in REQUIRED + OPTIONAL:
            T = getattr(self, k)
            if T is not None:
                p, q = T_to_pq(T)
                out[k] = [float(v) for v in (*p, *q)]
        out["source"] = self.source
        return out


def _pose7(value, name: str, where: str) -> np.ndarray:
    if not isinstance(value, list | tuple) or len(value) != 7:
        raise CalibrationError(f"{where}: '{name}' must be a list [x, y, z, qx, qy, qz, qw], got {value!r}")
    try:
        v = np.array([float(x) for x in value])
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: '{name}' has a non-numeric entry: {value!r}") from None
    if not np.all(np.isfinite(v)):
        raise CalibrationError(f"{where}: '{name}' contains NaN/inf")
    n = float(np.linalg.norm(v[3:]))
    if abs(n - 1.0) > 1e-3:
        raise CalibrationError(f"{where}: '{name}' quaternion has norm {n:.6f}, expected 1 (x y z w order)")
    return make_T(v[:3], v[3:] / n)


def parse_calibration(data, where: str = "<calibration>") -> Calibration:
    if not isinstance(data, dict):
        raise CalibrationError(f"{where}: expected a mapping with {', '.join(REQUIRED)}")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise CalibrationError(f"{where}: missing {', '.join(missing)} (needed to turn joint states into "
                               "ground truth in the base frame)")
    kw = {k: _pose7(data[k], k, where) for k in REQUIRED}
    for k in OPTIONAL:
        if data.get(k) is not None:
            kw[k] = _pose7(data[k], k, where)
    return Calibration(**kw, source=str(data.get("source", "")))


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration file, or ``<bag>/calibration.yaml`` when given a bag directory."""
    p = Path(path)
    if p.is_dir():
        p = p / CALIBRATION_FILE
    if not p.is_file():
        raise CalibrationError(
            f"no calibration file {str(p)!r}: the evaluator needs T_base_diana_base and T_flange_tool to compute "
            f"the ground truth (put a {CALIBRATION_FILE} into the bag directory or pass --calibration FILE)")
    try:
        data = yaml.safe_load(p.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise CalibrationError(f"{p}: not a readable YAML file ({type(e).__name__}: {e})") from None
    return parse_calibration(data, str(p))


def save_calibration(path: str | os.PathLike, cal: Calibration) -> Path:
    """Write ``cal`` to ``path`` (a file, or ``<bag>/calibration.yaml`` when given a directory)."""
    p = Path(path)
    if p.is_dir():
        p = p / CALIBRATION_FILE
    p.write_text(HEADER + yaml.safe_dump(cal.as_dict(), sort_keys=False, default_flow_style=None))
    return p
