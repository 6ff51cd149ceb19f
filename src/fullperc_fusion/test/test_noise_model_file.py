"""The per-installation noise model (noise_model_file.py, ``fullperc.noise_model_file``): its format, every refusal,
and that fusion_node's mapping and the pipeline really use it (issue 18)."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from fullperc_common.params import ParameterError
from fullperc_fusion.filters.api import SOURCE_GLOBAL
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.measurement_models import OmcModelParams, omc_covariance, omc_systematic_var
from fullperc_fusion.filters.noise_model_file import (
    BIAS_KEYS,
    OMC_KEYS,
    NoiseModel,
    NoiseModelError,
    load_noise_model,
    noise_model_yaml,
    parse_noise_model,
)
from fullperc_fusion.fusion_config import FusionConfigError, load_fusion_config
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

sys.path.insert(0, str(Path(__file__).parent))
from test_pipeline_fullperc import run, stream  # noqa: E402  (same directory: the shared synthetic stream)

OMC = {"white_std": 5.6e-5, "white_fit_gain": 0.21, "white_margin_std": 1.7e-4, "sys_floor": 2.1e-3,
       "fit_gain": 1.25, "margin_std": 7.9e-4, "marker_lever": 0.17, "rot_sys_floor": 9.5e-3,
       "rot_margin_std": 1.1e-2, "default_fit": 1.9e-4}
BIAS = {"sys_time": 8.1, "sys_std": 1.6e-3, "rot_sys_time": 2.1, "rot_sys_std": 4.5e-3, "rot_bias_walk": 2e-7,
        "rot_bias_length": 0.03}


def test_the_keys_are_the_fields_they_replace():
    assert set(OMC_KEYS) == {f.name for f in dataclasses.fields(OmcModelParams)}
    assert set(BIAS_KEYS) <= {f.name for f in dataclasses.fields(FullpercParams)}


def test_a_written_file_reads_back_to_the_same_model(tmp_path):
    p = tmp_path / "noise.yaml"
    p.write_text(noise_model_yaml(OMC, BIAS, "unit test"))
    nm = load_noise_model(p)
    assert dataclasses.asdict(nm.omc) == {**dataclasses.asdict(OmcModelParams()), **OMC}
    assert nm.bias == BIAS and nm.source == "unit test"
    fp = nm.apply(FullpercParams(accel_noise=0.7))
    assert fp.accel_noise == 0.7 and all(getattr(fp, k) == v for k, v in BIAS.items())
    assert "# units:" in p.read_text() and "omc.sys_floor [m]" in p.read_text()


def test_keys_not_given_keep_the_built_in_values():
    nm = parse_noise_model({"fullperc_noise_model": 1, "omc": {"margin_std": 1e-3}})
    assert nm.omc == dataclasses.replace(OmcModelParams(), margin_std=1e-3)
    assert nm.bias == {} and nm.apply(FullpercParams()) == FullpercParams()
    assert NoiseModel().omc == OmcModelParams()


@pytest.mark.parametrize("doc, words", [
    ({"fullperc_noise_model": 2}, "this version reads 1"),
    ({"omc": {}}, "'fullperc_noise_model' is None"),
    ({"fullperc_noise_model": 1, "omcc": {}}, "unknown key(s) ['omcc']"),
    ({"fullperc_noise_model": 1, "omc": {"margin_sd": 1e-3}}, "unknown key 'omc.margin_sd'"),
    ({"fullperc_noise_model": 1, "omc": [1, 2]}, "'omc' must be a mapping"),
    ({"fullperc_noise_model": 1, "omc": {"margin_std": -1e-3}},
     "'omc.margin_std' = -0.001 must be a finite number >= 0"),
    ({"fullperc_noise_model": 1, "omc": {"margin_std": math.nan}}, "'omc.margin_std' = nan"),
    ({"fullperc_noise_model": 1, "omc": {"margin_std": "1e-3"}}, "'omc.margin_std' = '1e-3'"),
    ({"fullperc_noise_model": 1, "omc": {"margin_std": True}}, "'omc.margin_std' = True"),
    ({"fullperc_noise_model": 1, "omc": {"marker_lever": 0.0}}, "'omc.marker_lever' = 0.0 must be a finite number > 0"),
    ({"fullperc_noise_model": 1, "omc_bias": {"sys_time": 0}}, "'omc_bias.sys_time' = 0 must be a finite number > 0"),
    ({"fullperc_noise_model": 1, "omc_bias": {"rot_sys_std": math.inf}}, "'omc_bias.rot_sys_std' = inf"),
    ({"fullperc_noise_model": 1, "omc": {"white_std": 0, "white_margin_std": 0, "white_fit_gain": 0}},
     "white noise would be 0"),
    ([1, 2], "expected a mapping"),
])
def test_a_wrong_file_is_refused_naming_the_key(doc, words):
    with pytest.raises(NoiseModelError) as e:
        parse_noise_model(doc, "noise model x.yaml")
    assert words in str(e.value) and "x.yaml" in str(e.value)


def test_an_unreadable_file_is_refused_naming_it(tmp_path):
    with pytest.raises(NoiseModelError, match="missing.yaml: cannot read"):
        load_noise_model(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("omc: [")
    with pytest.raises(NoiseModelError, match="bad.yaml: not valid YAML"):
        load_noise_model(tmp_path / "bad.yaml")
    with pytest.raises(NoiseModelError):   # the writer checks too: it never writes a file the reader refuses
        noise_model_yaml({**OMC, "fit_gain": -1.0}, BIAS, "x")


def _fusion_yaml(tmp_path, noise_file) -> str:
    p = tmp_path / "fusion.yaml"
    p.write_text(yaml.safe_dump({"fusion_node": {"ros__parameters": {
        "fullperc": {"noise_model_file": str(noise_file), "sys_time": 99.0}}}}))
    return str(p)


def test_fusion_node_mapping_reads_the_file(tmp_path):
    nm = tmp_path / "noise.yaml"
    nm.write_text(noise_model_yaml(OMC, BIAS, "unit test"))
    cfg, vals = load_fusion_config(_fusion_yaml(tmp_path, nm))
    assert cfg.omc_model == dataclasses.replace(OmcModelParams(), **OMC)
    # the file's omc_bias replaces the parameters (fullperc.sys_time 99 given too: the file wins, as documented)
    assert cfg.params.sys_time == BIAS["sys_time"] and cfg.params.rot_bias_walk == BIAS["rot_bias_walk"]
    assert cfg.params.rot_bias_length == BIAS["rot_bias_length"]
    assert vals["fullperc.noise_model_file"] == str(nm)
    (tmp_path / "empty.yaml").write_text("")
    default, _ = load_fusion_config(tmp_path / "empty.yaml")
    assert default.omc_model == OmcModelParams() and default.params.sys_time == FullpercParams().sys_time


def test_a_bad_noise_model_file_stops_the_mapping_naming_the_parameter(tmp_path):
    nm = tmp_path / "noise.yaml"
    nm.write_text("fullperc_noise_model: 1\nomc: {margin_std: -1}\n")
    with pytest.raises(FusionConfigError) as e:
        load_fusion_config(_fusion_yaml(tmp_path, nm))
    assert isinstance(e.value, ParameterError)
    assert "parameter 'fullperc.noise_model_file'" in str(e.value) and "omc.margin_std" in str(e.value)


def test_the_pipeline_gives_fullperc_the_files_covariances():
    model = dataclasses.replace(OmcModelParams(), **OMC)
    seen: dict[str, list] = {"builtin": [], "file": []}
    for key, cfg in (("builtin", TargetConfig(filters=("fullperc",))),
                     ("file", TargetConfig(filters=("fullperc",), omc_model=model))):
        pipe = TargetPipeline(cfg)
        f = pipe.filters["fullperc"]
        orig = f.update

        def spy(*ms, _orig=orig, _key=key):
            seen[_key].extend(m for m in ms if m.source == SOURCE_GLOBAL)
            return _orig(*ms)

        f.update = spy
        run(pipe, stream(seconds=0.5), quality=lambda k: {"fit_error": 1e-3})
    a, b = seen["builtin"][0], seen["file"][0]
    np.testing.assert_allclose(a.cov, omc_covariance(1e-3, None), rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(b.cov, omc_covariance(1e-3, None, model), rtol=1e-9, atol=1e-18)
    assert b.extras["sys_var"] == pytest.approx(omc_systematic_var(1e-3, None, model)[0], rel=1e-12)
    assert b.extras["sys_var"] > 5 * a.extras["sys_var"]          # the file's, not the built-in one
