"""fusion_config: the one parameter table of fusion_node and its mapping, used live and offline."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import yaml

from fullperc_common.params import ParameterError
from fullperc_fusion import fusion_config as fc
from fullperc_fusion.calibration.monitor import MonitorParams
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.fusion_health import HealthParams
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig

# fusion.yaml's `tool.ang_accel_noise`: the simulated OR's tool is held by the arm (test_truth_motion.py ties the
# value to its truth motion); the node-wide default is a hand-held target's


def _same_config(a: TargetConfig, b: TargetConfig) -> None:
    assert (a.name, a.filters, a.params, a.slop_ns, a.delay_ns) == (b.name, b.filters, b.params, b.slop_ns, b.delay_ns)
    assert (a.orientation_std_local, a.orientation_std_global) == (b.orientation_std_local, b.orientation_std_global)
    assert a.monitor == b.monitor
    for f in dataclasses.fields(ChainConfig):
        x, y = getattr(a.chain, f.name), getattr(b.chain, f.name)
        assert (x is None and y is None) or np.array_equal(x, y), f.name


def _write(tmp_path, params: dict, top: str = "fusion_node"):
    p = tmp_path / "f.yaml"
    p.write_text(yaml.safe_dump({top: {"ros__parameters": params}}))
    return p


def test_shipped_file_gives_the_built_in_defaults():
    """fusion.yaml says every value equals the node's built-in default, and no target sets its own motion: the tool's
    filters get exactly the defaults, with ``motion`` auto (the node's per-target default; the filters' dataclass
    says "fixed" for a direct caller)."""
    cfg, values = fc.load_fusion_config()
    auto = dataclasses.replace(FullpercParams(), motion="auto")
    _same_config(cfg, TargetConfig(name="tool", chain=ChainConfig(), filters=fc.PAPER_ORDER, params=auto))
    assert values["_source"].endswith("fusion.yaml")
    for p in fc.PARAMS:
        assert values[p.name] == fc.convert(p, None), p.name
    assert fc.health_params(values) == HealthParams()


def test_empty_file_and_defaults_agree(tmp_path):
    a, _ = fc.load_fusion_config(_write(tmp_path, {}))
    b, _ = fc.load_fusion_config()
    _same_config(a, b)
    # a ROS wildcard params file works too
    c, _ = fc.load_fusion_config(_write(tmp_path, {"noise": {"accel": 0.2}}, top="/**"))
    assert c.params.accel_noise == 0.2


def test_fusion_yaml_documents_every_parameter_with_its_default():
    """Every row of the table is in the shipped file (optional ones as a comment), with the table's default and,
    for a physical quantity, its unit in the comment."""
    path = fc.default_fusion_config_path()
    text = path.read_text()
    flat = fc.read_params_file(path)
    for p in fc.PARAMS:
        leaf = p.name.rsplit(".", 1)[-1]
        assert re.search(rf"^\s*#?\s*{re.escape(leaf)}:", text, re.M), f"{p.name} is not in {path}"
        if p.default is not None:
            assert p.name in flat, p.name
            assert fc.convert(p, flat[p.name]) == fc.convert(p, None), p.name
    for name in ("alarm.hop_window", "alarm.bias_max", "alarm.reject_timeout", "problem_hold"):
        leaf = name.rsplit(".", 1)[-1]
        line = next(line for line in text.splitlines() if re.match(rf"\s*{leaf}:", line))
        assert re.search(r"\[(s|m)\]", line), line
    # beside the table: the tool's device names and turn model, and the instrument's own motion model (a target
    # not in `targets`: the node's default run does not read it;
    # test_the_shipped_fusion_yaml_gives_the_instrument_its_own_model)
    assert set(flat) <= {p.name for p in fc.PARAMS} | {"tool.omc_body", "tool.ots_tool", "tool.ang_accel_noise",
                                                        "instrument.accel_noise", "instrument.hop_to_bias",
                                                        "instrument.init_vel_std"}


def test_values_are_mapped(tmp_path):
    p = _write(tmp_path, {
        "noise": {"accel": 0.2, "global_std": 0.001}, "hop_to_bias": False, "slop": 0.002, "reorder_delay": 0.1,
        "local_chain": "direct", "init_samples": 5, "tool": {"omc_body": "t1"}, "T_base_ots": [1, 2, 3, 0, 0, 0, 1],
        "filter": "ckf", "filters": ["kf", "ckf"], "alarm": {"bias_max": 0.05, "hop_max": 3}})
    cfg, values = fc.load_fusion_config(p)
    assert cfg.params.accel_noise == 0.2 and cfg.params.global_std == 0.001 and cfg.params.hop_to_bias is False
    assert (cfg.slop_ns, cfg.delay_ns) == (2_000_000, 100_000_000)
    assert cfg.chain.local_chain == "direct" and cfg.chain.init_samples == 5 and cfg.chain.omc_target == "t1"
    assert cfg.chain.ots_target == "tool"          # per-target default: the target's name
    np.testing.assert_allclose(cfg.chain.T_base_ots[:3, 3], [1, 2, 3])
    assert cfg.filters == fc.PAPER_ORDER            # the evaluator's default: every method
    assert fc.load_fusion_config(p, filters=None).config.filters == ("ckf", "kf")   # as the node runs them
    assert fc.health_params(values) == HealthParams(bias_max_m=0.05, hop_max=3, offset_warn_s=0.001)   # slop / 2
    other = fc.load_fusion_config(p, target="probe").config
    assert other.name == "probe" and other.chain.omc_target == "probe"


@pytest.mark.parametrize(("params", "name"), [
    ({"T_rig_ots": [1, 2, 3]}, "T_rig_ots"),
    ({"T_rig_ots": [0, 0, 0, 0, 0, 0, 2]}, "T_rig_ots"),          # not a unit quaternion
    ({"noise": {"global_std": -1.0}}, "noise.global_std"),
    ({"noise": {"accel": float("nan")}}, "noise.accel"),
    ({"noise": {"accel": "0.1"}}, "noise.accel"),                  # a string is not a number
    ({"hop_to_bias": 1}, "hop_to_bias"),                           # 1 is not a bool
    ({"init_samples": 0}, "init_samples"),
    ({"init_samples": 2.5}, "init_samples"),
    ({"local_chain": "moving"}, "local_chain"),
    ({"filter": "ukf"}, "filter"),
    ({"filters": ["kf", "ukf"]}, "filters"),
    ({"targets": []}, "targets"),
    ({"tool": {"omc_body": ""}}, "tool.omc_body"),
    ({"tool": {"ang_accel_noise": -1.0}}, "tool.ang_accel_noise"),
    ({"tool": {"ang_accel_noise": "fast"}}, "tool.ang_accel_noise"),
    ({"tool": {"accel_noise": 0.0}}, "tool.accel_noise"),
    ({"tool": {"accel_noise": float("inf")}}, "tool.accel_noise"),
    ({"tool": {"hop_to_bias": "no"}}, "tool.hop_to_bias"),
    ({"tool": {"hop_to_bias": 0}}, "tool.hop_to_bias"),             # 0 is not a bool
    ({"tool": {"init_vel_std": -0.1}}, "tool.init_vel_std"),
    ({"clock": "wall"}, "clock"),
    ({"alarm": {"hop_window": 0.0}}, "alarm.hop_window"),
    ({"alarm": {"hop_max": 0}}, "alarm.hop_max"),
    ({"alarm": {"bias_max": -0.02}}, "alarm.bias_max"),
    ({"alarm": {"reject_timeout": float("inf")}}, "alarm.reject_timeout"),
    ({"problem_hold": 0}, "problem_hold"),
    ({"static_links": "median"}, "static_links"),
    ({"calibration": {"duration": 0.0}}, "calibration.duration"),
    ({"calibration": {"min_samples": 1}}, "calibration.min_samples"),
    ({"calibration": {"max_drift": -1e-3}}, "calibration.max_drift"),
    ({"calibration": {"max_rot_drift": float("nan")}}, "calibration.max_rot_drift"),
    ({"calibration": {"timeout": 0}}, "calibration.timeout"),
    ({"calibration": {"output": 3}}, "calibration.output"),
    ({"link_monitor": {"trans_max": 0.0}}, "link_monitor.trans_max"),
    ({"link_monitor": {"rot_max": -0.003}}, "link_monitor.rot_max"),
    ({"link_monitor": {"window": float("inf")}}, "link_monitor.window"),
    ({"link_monitor": {"recalibrate": "yes"}}, "link_monitor.recalibrate"),
    ({"link_monitor": {"enabled": 1}}, "link_monitor.enabled"),
    ({"calibration_file": "/nonexistent/cal.yaml"}, "calibration_file"),
])
def test_bad_values_name_the_parameter_and_the_file(tmp_path, params, name):
    p = _write(tmp_path, params)
    with pytest.raises(fc.FusionConfigError, match=re.escape(f"'{name}'")) as e:
        fc.load_fusion_config(p)
    assert str(p) in str(e.value)
    assert isinstance(e.value, ParameterError) and isinstance(e.value, ValueError)


def test_unreadable_files(tmp_path):
    with pytest.raises(fc.FusionConfigError, match="cannot read"):
        fc.load_fusion_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("fusion_node: [1, 2]\n")
    with pytest.raises(fc.FusionConfigError, match="ros__parameters"):
        fc.load_fusion_config(bad)


def test_the_mapping_is_the_same_for_a_getter_and_for_values():
    """The node passes a getter that declares each parameter; the file path passes values: same config."""
    seen = []

    def get(name, default):
        seen.append(name)
        return {"noise.accel": 0.3, "probe.ots_tool": "p2"}.get(name)

    cfg = fc.target_config(get, "probe")
    assert cfg.params.accel_noise == 0.3 and cfg.chain.ots_target == "p2" and cfg.filters == ("cbkf",)
    assert set(seen) == {p.name for p in fc.PARAMS} | {f"probe.{tp.name}" for tp in fc.TARGET_PARAMS}
    vals = fc.read_values(get, ["probe"])
    _same_config(fc.target_config(vals, "probe"), cfg)
    with pytest.raises(ParameterError, match="'probe.omc_body'"):
        fc.target_config(lambda n, d: "" if n == "probe.omc_body" else None, "probe")


def test_calibration_and_link_monitor_rows_are_mapped(tmp_path):
    p = _write(tmp_path, {"static_links": "calibrate", "calibration": {
        "duration": 4.0, "min_samples": 12, "max_drift": 2e-3, "max_rot_drift": 5e-3, "output": "out.yaml",
        "timeout": 3.0}, "link_monitor": {"enabled": False, "trans_max": 0.004, "rot_max": 0.006, "window": 2.0,
                                         "recalibrate": True}})
    cfg, values = fc.load_fusion_config(p)
    c = cfg.chain
    assert c.static_links == "calibrate" and c.calibration_duration_s == 4.0 and c.calibration is None
    assert c.calibration_settings.min_samples == 12
    assert (c.calibration_settings.static.max_drift_m, c.calibration_settings.static.max_drift_rad) == (2e-3, 5e-3)
    assert cfg.monitor == MonitorParams(enabled=False, trans_max_m=0.004, rot_max_rad=0.006, window_s=2.0,
                                        recalibrate=True)
    assert values["calibration.output"] == "out.yaml" and values["calibration.timeout"] == 3.0
    # the defaults: calibrate (bridged by the average of init_samples), monitoring on without re-calibration
    d = fc.load_fusion_config().config
    assert d.chain.static_links == "calibrate" and d.monitor == MonitorParams() and d.chain.calibration is None


def _calibration_file(tmp_path):
    from fullperc_common.transforms import make_T
    from fullperc_fusion.calibration.collector import Collector
    from fullperc_fusion.calibration.io import save_calibration

    rng = np.random.default_rng(0)
    col = Collector(("T_omc_base", "T_base_ots"), duration_s=1.0)
    for k in range(130):
        t = 10**18 + k * 8_333_333
        col.add("omc", "base", t, make_T([1.0, 0.5, 0.8] + rng.normal(0, 1e-4, 3)))
        col.add("ots", "base", t, make_T([0.1, 0.2, -1.9] + rng.normal(0, 1e-4, 3)))
    path = tmp_path / "cal.yaml"
    save_calibration(path, col.finish(source="test"))
    return path


def test_calibration_file_is_loaded_into_the_chain(tmp_path):
    cal = _calibration_file(tmp_path)
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"calibration_file": str(cal)}))
    c = cfg.chain
    assert c.calibration is not None and set(c.calibration.links) == {"T_omc_base", "T_base_ots"}
    assert c.calibration_file == str(cal)
    np.testing.assert_allclose(c.calibration.T("T_omc_base")[:3, 3], [1.0, 0.5, 0.8], atol=1e-4)
    # given twice: as a parameter and in the file
    with pytest.raises(fc.FusionConfigError, match="T_base_ots is given both"):
        fc.load_fusion_config(_write(tmp_path, {"calibration_file": str(cal), "T_base_ots": [1, 2, 3, 0, 0, 0, 1]}))


def test_a_bad_calibration_file_names_the_parameter_the_file_and_the_field(tmp_path):
    cal = _calibration_file(tmp_path)
    data = yaml.safe_load(cal.read_text())
    data["links"]["T_base_ots"]["quaternion_xyzw"] = [0, 0, 0, 2.0]
    cal.write_text(yaml.safe_dump(data))
    with pytest.raises(fc.FusionConfigError) as e:
        fc.load_fusion_config(_write(tmp_path, {"calibration_file": str(cal)}))
    msg = str(e.value)
    assert "'calibration_file'" in msg and str(cal) in msg and "links.T_base_ots.quaternion_xyzw" in msg
    assert isinstance(e.value, ParameterError)


def test_fullperc_block_is_mapped_and_its_layout_loaded_only_when_used(tmp_path):
    """filter: fullperc -> FullpercParams from the fullperc.* rows and the layout for the OMC model's view margin;
    without a filter that uses the models no layout is read; a bad layout file names the parameter."""
    from fullperc_fusion.margin.layout import Layout

    p = _write(tmp_path, {"filter": "fullperc", "fullperc": {"sys_time": 2.5, "rot_local_std": 1e-3}})
    cfg, _ = fc.load_fusion_config(p, filters=None)
    assert cfg.filters == ("fullperc",) and isinstance(cfg.params, FullpercParams)
    assert cfg.params.sys_time == 2.5 and cfg.params.rot_local_std == 1e-3
    assert isinstance(cfg.layout, Layout)
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"filter": "cbkf"}), filters=None)
    assert cfg.layout is None
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"filter": "fullperc", "fullperc": {"layout_file": "none"}}),
                                   filters=None)
    assert cfg.layout is None
    bad = _write(tmp_path, {"filter": "fullperc", "fullperc": {"layout_file": str(tmp_path / "missing.yaml")}})
    with pytest.raises(fc.FusionConfigError, match="fullperc.layout_file"):
        fc.load_fusion_config(bad, filters=None)
    with pytest.raises(fc.FusionConfigError, match="fullperc.sys_time"):
        fc.load_fusion_config(_write(tmp_path, {"fullperc": {"sys_time": 0.0}}), filters=None)
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"filter": "fullperc"}), filters=None)
    assert cfg.params.hop_into == "b"     # CBKF's rule unless asked
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"filter": "fullperc", "fullperc": {"hop_into": "g"}}),
                                   filters=None)
    assert cfg.params.hop_into == "g"
    with pytest.raises(fc.FusionConfigError, match="fullperc.hop_into"):
        fc.load_fusion_config(_write(tmp_path, {"fullperc": {"hop_into": "p"}}), filters=None)
    assert cfg.params.hop_confirm == 1   # every crossing a hop (CBKF's rule) unless asked
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"filter": "fullperc", "fullperc": {"hop_confirm": 2}}),
                                   filters=None)
    assert cfg.params.hop_confirm == 2
    for bad in (0, 1.5):
        with pytest.raises(fc.FusionConfigError, match="fullperc.hop_confirm"):
            fc.load_fusion_config(_write(tmp_path, {"fullperc": {"hop_confirm": bad}}), filters=None)
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"fullperc": {"noise_adapt_time": 0.0, "noise_adapt_max": 4.0}}),
                                   filters=None)
    assert (cfg.params.noise_adapt_time, cfg.params.noise_adapt_max) == (0.0, 4.0)
    for bad in ({"noise_adapt_time": -0.1}, {"noise_adapt_max": 0.5}):
        with pytest.raises(fc.FusionConfigError, match=f"fullperc.{next(iter(bad))}"):
            fc.load_fusion_config(_write(tmp_path, {"fullperc": bad}), filters=None)
    rot = {"rot_noise_adapt_time": 0.5, "rot_noise_adapt_min": 0.2, "rot_noise_adapt_max": 4.0, "rot_noise_length": 0.1}
    cfg, _ = fc.load_fusion_config(_write(tmp_path, {"fullperc": rot}), filters=None)
    assert {k: getattr(cfg.params, k) for k in rot} == rot
    assert fc.load_fusion_config(_write(tmp_path, {}), filters=None)[0].params.rot_noise_adapt_time == 1.0
    for bad in ({"rot_noise_adapt_time": -1.0}, {"rot_noise_adapt_min": 0.0}, {"rot_noise_adapt_min": 2.0},
                {"rot_noise_adapt_max": 0.5}, {"rot_noise_length": -0.1}):
        with pytest.raises(fc.FusionConfigError, match=f"fullperc.{next(iter(bad))}"):
            fc.load_fusion_config(_write(tmp_path, {"fullperc": bad}), filters=None)


def test_a_float_without_a_dot_is_read_as_rcl_reads_it(tmp_path):
    """``accel: 1e-3`` is a double to fusion_node (rcl's YAML parser) but a string to PyYAML (YAML 1.1): the
    evaluator reads params files as the node does, so the same file works offline. Quoted, it stays a string
    (refused, as the node refuses it)."""
    p = tmp_path / "f.yaml"
    p.write_text("fusion_node:\n  ros__parameters:\n    noise:\n      accel: 1e-3\n    fullperc:\n"
                 "      noise_adapt_time: 4E-1\n")
    cfg, _ = fc.load_fusion_config(p, filters=None)
    assert cfg.params.accel_noise == 1e-3 and cfg.params.noise_adapt_time == 0.4
    p.write_text("fusion_node:\n  ros__parameters:\n    noise:\n      accel: '1e-3'\n")
    with pytest.raises(fc.FusionConfigError, match="noise.accel"):
        fc.load_fusion_config(p, filters=None)


def test_a_targets_own_angular_acceleration_noise(tmp_path):
    """``<target>.ang_accel_noise`` sets fullperc's turn model for that target only (an arm-held tool turns far more
    smoothly than a hand-held instrument); unset, the node-wide ``fullperc.ang_accel_noise``; the paper filters'
    parameters are the same either way."""
    p = _write(tmp_path, {"targets": ["tool", "instrument"], "tool": {"ang_accel_noise": 0.005},
                          "fullperc": {"ang_accel_noise": 0.7}})
    tool = fc.load_fusion_config(p, target="tool").config
    inst = fc.load_fusion_config(p, target="instrument").config
    assert tool.params.ang_accel_noise == 0.005 and inst.params.ang_accel_noise == 0.7
    assert fc.spec("tool.ang_accel_noise").default is None and fc.spec("tool.ots_tool").default == "tool"
    plain = fc.load_fusion_config(_write(tmp_path, {"targets": ["tool"]})).config
    assert plain.params.ang_accel_noise == FullpercParams().ang_accel_noise
    for f in FilterParams.__dataclass_fields__:     # what the paper's four read
        assert getattr(tool.params, f) == getattr(plain.params, f), f


def test_a_targets_own_motion_model_and_hop_rule(tmp_path):
    """``<target>.accel_noise``, ``<target>.hop_to_bias`` and ``<target>.init_vel_std`` replace ``noise.accel``,
    ``hop_to_bias`` and ``init.vel_std`` for that target only -- every filter's (the paper's four read them too): a
    hand-held instrument walks where the arm moves the tool slowly, may be walking when first seen, and a jump of its
    OMC pose is not the sensor's. Unset: the node-wide values; a False is a value."""
    p = _write(tmp_path, {"targets": ["tool", "instrument"], "noise": {"accel": 0.07}, "hop_to_bias": True,
                          "init": {"vel_std": 0.2},
                          "instrument": {"accel_noise": 2.0, "hop_to_bias": False, "init_vel_std": 0.9}})
    tool = fc.load_fusion_config(p, target="tool").config
    inst = fc.load_fusion_config(p, target="instrument").config
    assert (tool.params.accel_noise, tool.params.hop_to_bias, tool.params.init_vel_std) == (0.07, True, 0.2)
    assert (inst.params.accel_noise, inst.params.hop_to_bias, inst.params.init_vel_std) == (2.0, False, 0.9)
    changed = {f for f in FullpercParams.__dataclass_fields__
               if getattr(tool.params, f) != getattr(inst.params, f)}
    assert changed == {"accel_noise", "hop_to_bias", "init_vel_std"}
    p2 = _write(tmp_path, {"targets": ["tool"], "hop_to_bias": False, "tool": {"hop_to_bias": True}})
    assert fc.load_fusion_config(p2).config.params.hop_to_bias is True
    assert fc.spec("x.hop_to_bias").default is None and fc.spec("x.accel_noise").default is None


@pytest.mark.parametrize("name", [tp.name for tp in fc.TARGET_PARAMS] + ["alarm", "noise", "fullperc", "global"])
def test_target_parameter_names_cannot_be_source_names(tmp_path, name):
    """A source named like a per-target parameter or a parameter group would share its dotted names: refused.
    sources.py sits below this table, so the table passes the names in (fc.source_name_clashes)."""
    p = _write(tmp_path, {"sources": ["omc", "ots", name], "omc": {"role": "global"}, "ots": {"role": "local"},
                          name: {"role": "local"}})
    with pytest.raises(fc.FusionConfigError, match=f"'{name}' clashes"):
        fc.load_fusion_config(p, filters=("cbkf",))
    assert {tp.name for tp in fc.TARGET_PARAMS} <= fc.source_name_clashes()


# the filter parameters the node does not expose: the paper's ablations (shrink_blocks, eq14_covariance), set in code
NOT_NODE_PARAMETERS = {"shrink_blocks", "eq14_covariance", "motion"}   # motion: per target, <target>.motion


def test_every_filter_field_is_set_by_exactly_one_row_with_the_dataclass_default():
    """The field mapping is the table's: every field of every registered parameter dataclass is set by one row of
    PARAMS (a new field without a row fails here), whose default is the dataclass's; a per-target row replaces a
    node-wide row of the same field and kind."""
    from fullperc_fusion.filters.registry import FILTERS

    assert all(issubclass(fc.FILTER_PARAMS, s.params) for s in FILTERS.values())
    rows = [p for p in fc.PARAMS if p.field]
    assert len({p.field for p in rows}) == len(rows)
    fields = {f.name for f in dataclasses.fields(fc.FILTER_PARAMS)}
    assert {p.field for p in rows} == fields - NOT_NODE_PARAMETERS
    for p in rows:
        assert p.default == getattr(fc.FILTER_PARAMS(), p.field), p.name
    by_field = {p.field: p for p in rows}
    for tp in fc.TARGET_PARAMS:
        if tp.field:
            assert tp.field in by_field and by_field[tp.field].kind == tp.kind, tp.name


def test_filter_params_builds_each_registered_filters_own_dataclass():
    """``filter_params(vals, FILTERS[name].params)``: that filter's dataclass from the same rows; the paper's get
    exactly the FilterParams fields of the one object every filter of a target gets."""
    from fullperc_fusion.filters.registry import FILTERS

    vals = fc.read_values(lambda n, d: {"noise.accel": 0.2, "max_gap": 0.7, "fullperc.sys_time": 2.5}.get(n))
    every = fc.filter_params(vals)
    assert type(every) is fc.FILTER_PARAMS and (every.accel_noise, every.max_gap_s, every.sys_time) == (0.2, 0.7, 2.5)
    for name, s in FILTERS.items():
        own = fc.filter_params(vals, s.params)
        assert type(own) is s.params, name
        assert all(getattr(own, f.name) == getattr(every, f.name) for f in dataclasses.fields(s.params)), name


@pytest.mark.parametrize("value", [-1.0, 0.0, 0.5, 1.0, 2.0, float("inf"), float("nan")])
def test_a_filter_rows_rule_accepts_what_the_filters_dataclass_accepts(value):
    """The node's rule of a filter parameter and the dataclass's own check (for direct callers) agree on every
    float row, so a value the node accepts never fails later in the filter, nor the other way round."""
    for p in fc.PARAMS:
        if not p.field or p.kind != "float":
            continue
        try:
            fc.convert(p, value)
            node_ok = True
        except ParameterError:
            node_ok = False
        try:
            dataclasses.replace(fc.FILTER_PARAMS(), **{p.field: value}).validate()
            dataclass_ok = True
        except ValueError:
            dataclass_ok = False
        assert node_ok == dataclass_ok, (p.name, value)


def test_rules_are_named_once_and_explain_the_error():
    from fullperc_fusion.pipeline import param_table as pt

    cases = [(pt.POSITIVE, 0.0, "must be finite and > 0"), (pt.NONNEGATIVE, float("nan"), "must be finite and >= 0"),
             (pt.COUNT, 0, "must be > 0"), (pt.at_least(2), 1, "must be >= 2"), (pt.NONEMPTY, "", "must not be empty"),
             (pt.finite_at_least(1.0), 0.5, "must be finite and >= 1"),
             (pt.UNIT_FRACTION, 1.5, "must be finite, > 0 and <= 1"), (pt.one_of(("a", "b")), "c", "one of ('a', 'b')"),
             (pt.one_of(("a", "b"), "a or b"), "c", "a or b")]
    for rule, bad, why in cases:
        assert not rule.check(bad) and rule.why == why
        kind = "str" if isinstance(bad, str) else "int" if isinstance(bad, int) else "float"
        with pytest.raises(ParameterError, match=re.escape(f"parameter 'x' = {bad!r} is invalid: {why}")):
            pt.convert(pt.Param("x", None, kind, *rule), bad)
    assert fc.spec("noise.global_std").check is pt.POSITIVE.check        # the rows name the shared rule
    assert fc.spec("hop_gate").why == pt.POSITIVE.why


def test_a_targets_motion_preset_sets_every_filters_motion_and_auto_none(tmp_path):
    """``<target>.motion``: a preset (filters/motion.py) sets accel_noise, init_vel_std, hop_to_bias and
    ang_accel_noise of every filter of that target and makes fullperc a single model ("fixed"); the target's own
    values win over its preset's; auto (the default) changes no field and makes fullperc the IMM ("auto")."""
    from fullperc_fusion.filters.motion import PRESETS

    p = _write(tmp_path, {"targets": ["tool", "instrument", "pointer"], "instrument": {"motion": "hand"},
                          "pointer": {"motion": "static", "init_vel_std": 0.05}})
    tool, inst, pointer = (fc.load_fusion_config(p, target=t).config.params for t in ("tool", "instrument", "pointer"))
    plain = FullpercParams()
    assert tool == dataclasses.replace(plain, motion="auto")
    assert inst == dataclasses.replace(plain, motion="fixed", **PRESETS["hand"])
    assert pointer == dataclasses.replace(plain, motion="fixed", **{**PRESETS["static"], "init_vel_std": 0.05})
    assert fc.spec("x.motion").default == "auto"
    with pytest.raises(fc.FusionConfigError, match="instrument.motion"):
        fc.load_fusion_config(_write(tmp_path, {"targets": ["instrument"], "instrument": {"motion": "walk"}}),
                              target="instrument")
