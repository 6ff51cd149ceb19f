"""A per-installation noise model for ``fullperc`` (issue 18): the file behind ``fullperc.noise_model_file``.

Why a file: the constants of :mod:`measurement_models` and the time structure of the OMC's systematic error
(``FullpercParams.sys_time`` ...) are statistics of ONE optical motion-capture installation -- how well its cameras
are calibrated, how its error grows where few cameras see. The built-in values are those of the twin's ``spec``
profile; another room (the twin's ``paper`` profile, a user's OR) has other ones, and a filter given the wrong
ones is over- or under-confident. ``fit_noise_model`` (:mod:`fullperc_eval.evaluation.sensor_stats`) computes
them from a calibration recording -- the raw OMC against the arm's forward kinematics, no filter -- and writes
this file; ``fusion_node`` and the evaluator read it.

Format (YAML, SI units; every key of ``omc`` and ``omc_bias`` optional: a key not given keeps the built-in value)::

    fullperc_noise_model: 1          # format version
    source: "raw-sensor statistics of ..."   # free text: where the numbers come from
    omc:                             # measurement_models.OmcModelParams fields
      white_std: 1.97e-05            # [m]
      ...
    omc_bias:                        # FullpercParams fields: the OMC's systematic error over time and space
      sys_time: 3.06                 # [s]
      sys_std: 2.1e-04               # [m]
      rot_sys_time: 3.38             # [s] (0: the orientation bias is a random walk alone)
      rot_sys_std: 8.94e-03          # [rad]
      rot_bias_walk: 1.0e-06         # [rad^2/s]
      rot_bias_length: 5.27e-02      # [m] (0: the orientation bias does not decay with distance)
      bias_length: 0.296             # [m] (0: the position bias b does not decay with distance)
      bias_field_std: 3.41e-04       # [m] the OMC's position error field's std (b's far from where it was learnt)
      bias_field_length: 0.296       # [m] its correlation length (bias_field_std's and this: the raw variogram fit)

A file that cannot be read, has another version, an unknown key or a value that is not a finite number in its
range raises :class:`NoiseModelError` naming the file and the key: a typo must not silently leave a default.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.measurement_models import OmcModelParams

VERSION = 1

# key -> (unit, must be > 0 (else >= 0))
OMC_KEYS: dict[str, tuple[str, bool]] = {
    "white_std": ("m", False), "white_fit_gain": ("-", False), "white_margin_std": ("m", False),
    "sys_floor": ("m", False), "fit_gain": ("-", False), "margin_std": ("m", False), "margin_ref": ("deg", True),
    "margin_min": ("deg", True), "marker_lever": ("m", True), "rot_sys_floor": ("rad", False),
    "rot_margin_std": ("rad", False), "default_fit": ("m", False)}
BIAS_KEYS: dict[str, tuple[str, bool]] = {
    "sys_time": ("s", True), "sys_std": ("m", True), "rot_sys_time": ("s", False), "rot_sys_std": ("rad", False),
    "rot_bias_walk": ("rad^2/s", False), "rot_bias_length": ("m", False), "bias_length": ("m", False),
    "bias_field_std": ("m", False), "bias_field_length": ("m", False)}


class NoiseModelError(ValueError):
    """A noise-model file cannot be read or holds a wrong value; the message names the file and the key."""


@dataclass(frozen=True)
class NoiseModel:
    """The OMC model's constants and the ``FullpercParams`` fields a file replaces (only the keys it gives)."""

    omc: OmcModelParams = field(default_factory=OmcModelParams)
    bias: dict[str, float] = field(default_factory=dict)
    source: str = ""

    def apply(self, params: FullpercParams) -> FullpercParams:
        """``params`` with the file's ``omc_bias`` values."""
        return dataclasses.replace(params, **self.bias).validate()


def _section(raw: Any, keys: dict[str, tuple[str, bool]], name: str, where: str) -> dict[str, float]:
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise NoiseModelError(f"{where}: '{name}' must be a mapping of {sorted(keys)}")
    out = {}
    for k, v in raw.items():
        if k not in keys:
            raise NoiseModelError(f"{where}: unknown key '{name}.{k}' (known: {', '.join(keys)})")
        unit, positive = keys[k]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0 or \
                (positive and v == 0):
            raise NoiseModelError(f"{where}: '{name}.{k}' = {v!r} must be a finite number "
                                  f"{'> 0' if positive else '>= 0'} [{unit}]")
        out[k] = float(v)
    return out


def parse_noise_model(data: Any, where: str = "noise model") -> NoiseModel:
    """The :class:`NoiseModel` of a loaded YAML document (see the module docstring)."""
    if not isinstance(data, dict):
        raise NoiseModelError(f"{where}: expected a mapping with 'fullperc_noise_model: {VERSION}'")
    version = data.get("fullperc_noise_model")
    if version != VERSION:
        raise NoiseModelError(f"{where}: 'fullperc_noise_model' is {version!r}, this version reads {VERSION}")
    unknown = set(data) - {"fullperc_noise_model", "source", "omc", "omc_bias"}
    if unknown:
        raise NoiseModelError(f"{where}: unknown key(s) {sorted(unknown)} (known: source, omc, omc_bias)")
    omc = _section(data.get("omc"), OMC_KEYS, "omc", where)
    bias = _section(data.get("omc_bias"), BIAS_KEYS, "omc_bias", where)
    try:
        FullpercParams(**bias).validate()
    except ValueError as e:
        raise NoiseModelError(f"{where}: {e}") from None
    model = OmcModelParams(**omc)
    if model.white_std == 0 and model.white_margin_std == 0 and model.white_fit_gain * model.default_fit == 0:
        raise NoiseModelError(f"{where}: the OMC's white noise would be 0 without a fit error (omc.white_std, "
                              "white_margin_std and white_fit_gain * default_fit all 0): every sample's covariance "
                              "would be singular")
    return NoiseModel(omc=model, bias=bias, source=str(data.get("source") or ""))


def load_noise_model(path: str | Path) -> NoiseModel:
    """Read and check a noise-model file; :class:`NoiseModelError` naming it when it cannot be used."""
    from fullperc_common.yaml_file import load_yaml_file

    return parse_noise_model(load_yaml_file(path, "noise model", NoiseModelError), f"noise model {Path(path)}")


def noise_model_yaml(omc: dict[str, float], bias: dict[str, float], source: str) -> str:
    """The text of a noise-model file (checked by :func:`parse_noise_model` before it is returned)."""
    import yaml

    doc = {"fullperc_noise_model": VERSION, "source": source,
           "omc": {k: float(v) for k, v in omc.items()}, "omc_bias": {k: float(v) for k, v in bias.items()}}
    parse_noise_model(doc, "noise model to write")
    units = "\n".join(f"#   {s}.{k} [{u}]" for s, keys in (("omc", OMC_KEYS), ("omc_bias", BIAS_KEYS))
                      for k, (u, _) in keys.items() if k in doc[s])
    return ("# fullperc noise model (fullperc_fusion/noise_model_file.py); fusion_node: fullperc.noise_model_file\n"
            f"# units:\n{units}\n" + yaml.safe_dump(doc, sort_keys=False, width=110))
