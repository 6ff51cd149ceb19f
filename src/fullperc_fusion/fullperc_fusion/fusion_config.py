"""fusion_node's parameters in ONE table, and the one mapping from their values to a :class:`TargetConfig`.

Two users, one mapping, so live and offline cannot drift apart:

* ``fusion_node`` declares every parameter of :data:`PARAMS` (and :data:`TARGET_PARAMS` per target) through
  ``fullperc_common.params.declare`` and maps them with :func:`read_values` / :func:`target_config`;
* the offline evaluator calls :func:`load_fusion_config`: the same mapping over the node's params YAML
  (``config/fusion.yaml`` by default; ``fusion_node: ros__parameters:`` with nested keys for dotted names).

Each :class:`~.pipeline.param_table.Param` row holds the name (nested names use dots: ``noise.accel``), the default,
the kind of value, its one validity rule (:class:`~.pipeline.param_table.Rule`, named where several rows share it),
the unit, a description and, for a filter parameter, the field of the filters' parameter dataclass it sets. The
mapping is pure: it gets raw values from a ``get(name, default)`` callable and converts and checks them by the rows
(:func:`~.pipeline.param_table.convert`); a wrong value raises :class:`~fullperc_common.params.ParameterError` naming
the parameter. The filters' parameters are derived from the rows (:func:`filter_params`): the registry names each
filter's parameter dataclass (``filters.registry.FilterSpec.params``), a row names its field, and nothing copies the
fields by hand.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from fullperc_common.params import ParameterError
from fullperc_fusion.calibration.io import load_calibration
from fullperc_fusion.calibration.monitor import MonitorParams
from fullperc_fusion.calibration.se3_stats import CalibrationError, CalibrationSettings, StaticThresholds
from fullperc_fusion.filters.fullperc_params import HOP_INTO, HOP_NEEDS_LOCAL
from fullperc_fusion.filters.motion import MOTIONS, PRESETS, preset_fields
from fullperc_fusion.filters.paper_family import FilterParams
from fullperc_fusion.filters.registry import FILTERS, params_of_every_filter
from fullperc_fusion.fusion_health import HealthParams
from fullperc_fusion.fusion_interface import INTERFACE_PARAMS, TARGET_FRAME
from fullperc_fusion.pipeline.frame_chain import LOCAL_CHAINS, STATIC_LINK_MODES, ChainConfig
from fullperc_fusion.pipeline.ordered import FILTER_NAMES, TargetConfig
from fullperc_fusion.pipeline.param_table import (
    COUNT,
    NONEMPTY,
    NONNEGATIVE,
    POSITIVE,
    UNIT_FRACTION,
    Get,
    Param,
    at_least,
    convert,
    finite_at_least,
    one_of,
)
from fullperc_fusion.pipeline.sources import SOURCE_KEYS, device_param, read_source_values, source_param, source_set
from fullperc_fusion.pipeline.target import TIMING_PARAMS

# every method: the paper's five in the column order of its Table 1 (omc, kf, bkf, ckf, cbkf: the first five of
# the registry reversed), then every further registered filter (fullperc) in registry order
PAPER_ORDER = tuple(reversed(FILTER_NAMES[:5])) + FILTER_NAMES[5:]


FILTER_PARAMS = params_of_every_filter()
_F = FILTER_PARAMS()
_C, _T, _H, _S, _M = ChainConfig(), TargetConfig(), HealthParams(), CalibrationSettings(), MonitorParams()


def _filter_row(name: str, field: str, kind: str, check: Callable[[Any], bool] | None = None, why: str = "",
                unit: str = "", doc: str = "") -> Param:
    """The row (a :class:`Param`'s arguments) of a parameter that sets the filters' ``field``: its default is the
    dataclass's."""
    return Param(name, getattr(_F, field), kind, check, why, unit, doc, field)


PARAMS: tuple[Param, ...] = (
    Param("targets", ["tool"], "str_list", lambda v: len(v) > 0 and all(v), "at least one non-empty name", "",
          "fused targets; one output namespace fullperc/<target>/ each"),
    Param("sources", None, "str_list", None, "", "",
          "measurement sources (sources.py): one global, one or more local, a block '<name>: {role: ...}' each; "
          "none = the built-in omc (global, /omc) + ots (local, /ots)"),
    Param("omc_base_body", _C.omc_base, "str", *NONEMPTY, "",
          "OMC rigid body of the reference marker: the frame 'base' of every output"),
    Param("omc_rig_body", _C.omc_rig, "str", *NONEMPTY, "",
          "OMC rigid body attached to the OTS (paper eq. 1 {Robot})"),
    Param("ots_base_tool", _C.ots_base, "str", *NONEMPTY, "",
          "OTS tool on the reference marker (eq. 2)"),
    Param("local_chain", _C.local_chain, "str", *one_of(LOCAL_CHAINS), "",
          "static (OTS on a stand) | tracked (OTS moves, eq. 1 live) | direct (eq. 2 live)"),
    Param("init_samples", _C.init_samples, "int", *COUNT, "samples",
          "samples per body averaged into the static links"),
    Param("T_rig_ots", None, "pose7", None, "", "m, quaternion x y z w",
          "optional hand-eye calibration rig -> ots [x y z qx qy qz qw]"),
    Param("T_base_ots", None, "pose7", None, "", "m, quaternion x y z w",
          "optional fixed calibration of a stationary OTS [x y z qx qy qz qw]"),
    Param("calibration_file", "", "str", None, "", "",
          "calibration YAML (calibrate executable, ~/calibrate) whose links are used from the start; '' = none"),
    Param("static_links", _C.static_links, "str", *one_of(STATIC_LINK_MODES),
          "", "links not in calibration_file: calibrate over calibration.duration (average meanwhile) | average"),
    Param("calibration.duration", _C.calibration_duration_s, "float", *POSITIVE, "s",
          "sightings collected per calibration (static_links calibrate, ~/calibrate, re-calibration)"),
    Param("calibration.min_samples", _S.min_samples, "int", *at_least(2), "samples",
          "fewer sightings of a body in a collection: refused"),
    Param("calibration.max_drift", _S.static.max_drift_m, "float", *POSITIVE, "m",
          "a body whose mean moved more than this (and significantly) during a collection: refused"),
    Param("calibration.max_rot_drift", _S.static.max_drift_rad, "float", *POSITIVE, "rad",
          "the same for the rotation"),
    Param("calibration.output", "", "str", None, "", "",
          "~/calibrate writes its calibration YAML here; '' = not written"),
    Param("calibration.timeout", 10.0, "float", *POSITIVE, "s",
          "~/calibrate ends this long after calibration.duration even without enough sightings (then refused)"),
    Param("link_monitor.enabled", _M.enabled, "bool", None, "", "",
          "compare the OTS's live view of the base marker with the calibrated T_base_ots"),
    Param("link_monitor.trans_max", _M.trans_max_m, "float", *POSITIVE, "m",
          "window mean farther than this from the calibrated link: bumped"),
    Param("link_monitor.rot_max", _M.rot_max_rad, "float", *POSITIVE, "rad",
          "window mean turned more than this: bumped"),
    Param("link_monitor.window", _M.window_s, "float", *POSITIVE, "s",
          "sightings averaged per comparison (evaluated every half window)"),
    Param("link_monitor.recalibrate", _M.recalibrate, "bool", None, "", "",
          "a bump starts a re-calibration over calibration.duration (old links in use meanwhile)"),
    Param("filter", "cbkf", "str", *one_of(FILTER_NAMES), "",
          "primary filter (omc = raw OMC pass-through)"),
    Param("filters", None, "str_list", lambda v: all(f in FILTER_NAMES for f in v),
          f"every entry one of {FILTER_NAMES}", "", "side-by-side filters under fullperc/<target>/<filter>/"),
    _filter_row("noise.accel", "accel_noise", "float", *NONNEGATIVE, "m^2/s^3",
          "white-acceleration density q_a"),
    _filter_row("noise.bias_walk", "bias_walk", "float", *NONNEGATIVE, "m^2/s",
          "bias random walk q_b"),
    _filter_row("noise.global_std", "global_std", "float", *POSITIVE, "m", "OMC white noise per axis"),
    _filter_row("noise.local_std", "local_std", "float", *POSITIVE, "m", "OTS chain noise per axis"),
    _filter_row("init.pos_std", "init_pos_std", "float", *NONNEGATIVE, "m", "prior std of p"),
    _filter_row("init.vel_std", "init_vel_std", "float", *NONNEGATIVE, "m/s", "prior std of v"),
    _filter_row("init.bias_std", "init_bias_std", "float", *NONNEGATIVE, "m", "prior std of b"),
    _filter_row("hop_gate", "hop_gate", "float", *POSITIVE, "chi^2, 3 dof",
          "gate on the global NIS; above it the update is flagged as a hop"),
    _filter_row("hop_to_bias", "hop_to_bias", "bool", None, "", "",
          "a flagged hop goes into the bias (compensated filters)"),
    _filter_row("max_gap", "max_gap_s", "float", *POSITIVE, "s",
          "longer silence of both sources re-initialises p and v"),
    _filter_row("fullperc.ang_accel_noise", "ang_accel_noise", "float", *NONNEGATIVE, "rad^2/s^3",
          "fullperc: white angular-acceleration density q_alpha"),
    _filter_row("fullperc.motion_models", "motion_models", "str_list", lambda v: bool(v) and len(set(v)) == len(v)
          and set(v) <= set(PRESETS), f"distinct ones of {tuple(PRESETS)}", "",
          "fullperc: the motion presets a target with motion auto weighs (filters/motion.py)"),
    _filter_row("fullperc.motion_dwell", "motion_dwell", "float", *POSITIVE, "s",
          "fullperc: mean time a target keeps one motion (motion auto: the models' switching rate)"),
    _filter_row("fullperc.rot_bias_walk", "rot_bias_walk", "float", *NONNEGATIVE, "rad^2/s",
          "fullperc: random walk of the OMC's orientation bias"),
    _filter_row("fullperc.rot_global_std", "rot_global_std", "float", *POSITIVE, "rad",
          "fullperc: OMC orientation noise per axis when a sample has no covariance"),
    _filter_row("fullperc.rot_local_std", "rot_local_std", "float", *POSITIVE, "rad",
          "fullperc: OTS orientation noise per axis when a sample has no covariance"),
    _filter_row("fullperc.init_rot_std", "init_rot_std", "float", *NONNEGATIVE, "rad",
          "fullperc: prior std of the orientation"),
    _filter_row("fullperc.init_angvel_std", "init_angvel_std", "float", *NONNEGATIVE, "rad/s",
          "fullperc: prior std of the angular velocity"),
    _filter_row("fullperc.init_rot_bias_std", "init_rot_bias_std", "float", *NONNEGATIVE, "rad",
          "fullperc: prior std of the OMC's orientation bias"),
    _filter_row("fullperc.sys_time", "sys_time", "float", *POSITIVE, "s",
          "fullperc: correlation time of the OMC's systematic position error (Gauss-Markov bias part)"),
    _filter_row("fullperc.sys_std", "sys_std", "float", *POSITIVE, "m",
          "fullperc: its per-axis std for an OMC sample without a model (no quality)"),
    _filter_row("fullperc.rot_sys_time", "rot_sys_time", "float", *NONNEGATIVE, "s",
          "fullperc: correlation time of the OMC orientation bias's Gauss-Markov part; 0 = random walk alone"),
    _filter_row("fullperc.rot_sys_std", "rot_sys_std", "float", *NONNEGATIVE, "rad",
          "fullperc: stationary per-axis std of that part"),
    _filter_row("fullperc.rot_bias_length", "rot_bias_length", "float", *NONNEGATIVE, "m",
          "fullperc: distance over which the OMC orientation bias decays once the local source has lost the tool "
          "(0 = off)"),
    _filter_row("fullperc.bias_length", "bias_length", "float", *NONNEGATIVE, "m",
          "fullperc: distance over which the OMC position bias b decays once the local source lost the tool (0: off)"),
    _filter_row("fullperc.bias_field_std", "bias_field_std", "float", *NONNEGATIVE, "m",
          "fullperc: per-axis std of the OMC's position error field (b's far from where it was learnt; the output "
          "covariance takes |b|/sqrt(3) where the learnt b is larger)"),
    _filter_row("fullperc.bias_field_length", "bias_field_length", "float", *NONNEGATIVE, "m",
          "fullperc: that field's correlation length; with bias_length 0 the output covariance adds the field's "
          "change since the local source lost the tool (0 = off)"),
    _filter_row("fullperc.local_lost_s", "local_lost_s", "float", *POSITIVE, "s",
          "fullperc: time without a local sample after which the local source counts as having lost the tool"),
    _filter_row("fullperc.hop_into", "hop_into", "str", *one_of(HOP_INTO), "",
          "the global bias part a position hop goes into: b (the lasting compensation, CBKF's rule) | g "
          "(Gauss-Markov, forgotten over fullperc.sys_time)"),
    _filter_row("fullperc.hop_needs_local", "hop_needs_local", "str", *one_of(HOP_NEEDS_LOCAL), "",
          "when a position hop may go into the bias: once (the local source has seen the target) | always (while "
          "it sees it) | never (CBKF's rule)"),
    _filter_row("fullperc.hop_confirm", "hop_confirm", "int", *at_least(1), "samples",
          "OMC samples in a row over the hop gate, in one direction, that make a hop (1: each, CBKF's rule)"),
    _filter_row("fullperc.noise_adapt_time", "noise_adapt_time", "float", *NONNEGATIVE, "s",
          "time constant of the OMC white-noise scale learnt from its innovations (0 = off: the model as it is)"),
    _filter_row("fullperc.noise_adapt_max", "noise_adapt_max", "float", *finite_at_least(1.0), "",
                "largest scale of the OMC's white position variance"),
    _filter_row("fullperc.rot_noise_adapt_time", "rot_noise_adapt_time", "float", *NONNEGATIVE, "s",
          "time constant of the OMC rotation-noise scale learnt from (OMC, OTS) pairs (0 = off: the model as it is)"),
    _filter_row("fullperc.rot_noise_adapt_min", "rot_noise_adapt_min", "float", *UNIT_FRACTION, "",
                "smallest scale of the OMC's rotation variance"),
    _filter_row("fullperc.rot_noise_adapt_max", "rot_noise_adapt_max", "float", *finite_at_least(1.0), "",
                "largest scale of the OMC's rotation variance"),
    _filter_row("fullperc.rot_noise_length", "rot_noise_length", "float", *NONNEGATIVE, "m",
          "distance over which that scale returns to 1 once the local source has lost the tool (0 = kept)"),
    Param("fullperc.layout_file", "", "str", None, "", "",
          "fullperc: OR layout for the OMC model's view margin; '' = the installed or_layout.yaml, 'none' = none"),
    Param("fullperc.noise_model_file", "", "str", None, "", "",
          "fullperc: noise model of this installation's OMC (written by fit_noise_model); '' = the built-in one. "
          "Its omc_bias values replace fullperc.sys_time, sys_std, rot_sys_time, rot_sys_std, rot_bias_walk, "
          "rot_bias_length, bias_length, bias_field_std, bias_field_length"),
    *TIMING_PARAMS,   # slop ... partner_wait (pipeline/target.py)
    Param("lag_warn", 0.2, "float", *POSITIVE, "s",
          "processing lag (node clock - stamp of the newest fused sample) above this for a whole /diagnostics "
          "period -> WARN (overload; beyond `history` late samples are dropped)"),
    Param("stale_timeout", 1.0, "float", *POSITIVE, "s",
          "silence after which /diagnostics reports a source as silent"),
    Param("problem_hold", _H.hold_s, "float", *POSITIVE, "s",
          "a problem or alarm stays on /diagnostics this long after it was last seen"),
    Param("alarm.hop_window", _H.hop_window_s, "float", *POSITIVE, "s",
          "window of the hop-rate alarm"),
    Param("alarm.hop_max", _H.hop_max, "int", *at_least(1), "hops",
          "more hops than this within alarm.hop_window -> WARN"),
    Param("alarm.bias_max", _H.bias_max_m, "float", *POSITIVE, "m",
          "|bias| of the global source above this -> WARN"),
    Param("alarm.reject_timeout", _H.reject_timeout_s, "float", *POSITIVE, "s",
          "every sample of a source rejected for this long -> ERROR"),
    Param("publishers.allow", None, "str_list", lambda v: all(x.startswith("/") for x in v), "each starts with '/'",
          "", "who may publish on the inputs: node names ('/omc_driver') or namespaces ending in '/'; none = the "
          "first node seen on each input topic; any other publisher closes that input (ERROR; input_guard.py)"),
    Param("plausibility.max_speed", 2.0, "float", *POSITIVE, "m/s", "a target sample further than plausibility."
          "jump + max_speed x dt from its source's last accepted one is rejected (rejected_jump)"),
    Param("plausibility.jump", 0.01, "float", *POSITIVE, "m", "a sample's jump allowed beyond max_speed x dt"),
    *INTERFACE_PARAMS,   # topics, frames, QoS, optional outputs (fusion_interface.py)
)
"""Every node-wide parameter of fusion_node."""

# Per target; the name is "<target>.<suffix>"; a string's default (None) is the target's name, a number's none
# (the node-wide value applies). A row with a ``field`` replaces the node-wide row of that field for the target.
TARGET_PARAMS: tuple[Param, ...] = (
    Param("motion", "auto", "str", *one_of(MOTIONS), "",
          "how the target moves: auto (fullperc weighs fullperc.motion_models itself, the paper's filters keep the "
          "node-wide values) | arm | hand | static (a preset of every filter's motion values; filters/motion.py)"),
    Param("omc_body", None, "str", *NONEMPTY, "", "OMC rigid body of the target (global measurement)"),
    Param("ots_tool", None, "str", *NONEMPTY, "", "NDI tool of the target (local measurement)"),
    Param("ang_accel_noise", None, "float", *POSITIVE, "rad^2/s^3",
          "fullperc's white angular-acceleration density for this target (unset: fullperc.ang_accel_noise); how "
          "the target turns: an arm-held tool far more smoothly than a hand-held one",
          field="ang_accel_noise"),
    Param("accel_noise", None, "float", *POSITIVE, "m^2/s^3",
          "white-acceleration density q_a of every filter for this target (unset: noise.accel); how the target "
          "moves: an arm-held tool at a few cm/s, a hand-held instrument at up to ~1 m/s",
          field="accel_noise"),
    Param("hop_to_bias", None, "bool", None, "", "",
          "a flagged hop of this target goes into the bias (unset: hop_to_bias); false for a hand-held target, "
          "whose own motion a hop cannot be told from",
          field="hop_to_bias"),
    Param("init_vel_std", None, "float", *NONNEGATIVE, "m/s",
          "prior std of this target's velocity at (re)initialisation (unset: init.vel_std): its top speed; a target "
          "already moving when first seen otherwise puts its motion into the bias",
          field="init_vel_std"),
    TARGET_FRAME,
)

BY_NAME = {p.name: p for p in PARAMS}


def spec(name: str) -> Param:
    """The row of parameter ``name``: one of :data:`PARAMS`, ``<target>.<suffix>`` of :data:`TARGET_PARAMS`, a
    source block's ``<source>.<key>`` or a target's ``<target>.<source>`` device name (:mod:`.pipeline.sources`)."""
    if name in BY_NAME:
        return BY_NAME[name]
    target, _, suffix = name.rpartition(".")
    for tp in TARGET_PARAMS:
        if suffix == tp.name and target:
            return replace(tp, name=name, default=target if tp.kind == "str" and tp.default is None else tp.default)
    if target and suffix in SOURCE_KEYS:   # a source block (sources.py)
        return source_param(target, suffix)
    if target and "." not in target and "." not in suffix:   # <target>.<source>: the target's device of a source
        return device_param(target, suffix)
    raise KeyError(f"fusion_node has no parameter '{name}'")


# ------------------------------------------------------------------------------------------------ mapping
def read_values(get: Get, targets: list[str] | None = None) -> dict[str, Any]:
    """Every parameter of :data:`PARAMS` (and :data:`TARGET_PARAMS` of each target, by default those of the
    ``targets`` parameter) read through ``get(name, default)``, converted and checked."""
    vals = {p.name: convert(p, get(p.name, p.default)) for p in PARAMS}
    ts = vals["targets"] if targets is None else targets
    for t in ts:
        for tp in TARGET_PARAMS:
            p = spec(f"{t}.{tp.name}")
            vals[p.name] = convert(p, get(p.name, p.default))
    vals.update(read_source_values(get, vals, list(ts), source_name_clashes()))
    return vals


def source_name_clashes() -> set[str]:
    """The names a source may not take (sources.py): the first component of every node parameter's name (``noise``,
    ``alarm`` ...) and every per-target suffix (``omc_body`` ...), whose dotted names a source block would share."""
    return {p.name.split(".")[0] for p in PARAMS} | {tp.name for tp in TARGET_PARAMS}


def filter_params(vals: dict[str, Any], params_type: type[FilterParams] = FILTER_PARAMS) -> FilterParams:
    """The filters' parameters of dataclass ``params_type`` (by default :data:`FILTER_PARAMS`, the one object every
    filter of a target gets; a registry entry's own ``FILTERS[name].params`` gives that filter's alone): every
    field that a row of :data:`PARAMS` sets, from that row's value; the dataclass's defaults for the rest."""
    fields = {f.name for f in dataclasses.fields(params_type)}
    return params_type(**{p.field: vals[p.name] for p in PARAMS if p.field in fields}).validate()


def model_layout(vals: dict[str, Any], filters: tuple[str, ...]):
    """The layout for the OMC model's view margin when a filter uses the models (``fullperc.layout_file``), else
    None. A file that cannot be read raises ParameterError naming the parameter."""
    if not any(FILTERS[f].caps.models for f in filters if f in FILTERS):
        return None
    path = vals["fullperc.layout_file"]
    if path.strip().lower() == "none":
        return None
    from fullperc_fusion.margin.layout import LayoutError, default_layout_path, load_layout

    try:
        return load_layout(path or default_layout_path())
    except (LayoutError, FileNotFoundError) as e:
        raise ParameterError(f"parameter 'fullperc.layout_file' = {path!r}: {e}") from None


def noise_model(vals: dict[str, Any]):
    """The :class:`~.noise_model_file.NoiseModel` of ``fullperc.noise_model_file`` (the built-in one for '').
    A file that cannot be used raises ParameterError naming the parameter."""
    from fullperc_fusion.filters.noise_model_file import NoiseModel, NoiseModelError, load_noise_model

    path = vals["fullperc.noise_model_file"]
    if not path.strip():
        return NoiseModel()
    try:
        return load_noise_model(path)
    except NoiseModelError as e:
        raise ParameterError(f"parameter 'fullperc.noise_model_file' = {path!r}: {e}") from None


def health_params(vals: dict[str, Any]) -> HealthParams:
    return HealthParams(hop_window_s=vals["alarm.hop_window"], hop_max=vals["alarm.hop_max"],
                        bias_max_m=vals["alarm.bias_max"], reject_timeout_s=vals["alarm.reject_timeout"],
                        hold_s=vals["problem_hold"], offset_warn_s=max(vals["slop"] / 2, 1e-4)).validate()


def calibration_settings(vals: dict[str, Any]) -> CalibrationSettings:
    return CalibrationSettings(min_samples=vals["calibration.min_samples"], static=StaticThresholds(
        max_drift_m=vals["calibration.max_drift"], max_drift_rad=vals["calibration.max_rot_drift"]))


def monitor_params(vals: dict[str, Any]) -> MonitorParams:
    return MonitorParams(enabled=vals["link_monitor.enabled"], trans_max_m=vals["link_monitor.trans_max"],
                         rot_max_rad=vals["link_monitor.rot_max"], window_s=vals["link_monitor.window"],
                         recalibrate=vals["link_monitor.recalibrate"]).validate()


def primary_and_extra(vals: dict[str, Any]) -> tuple[str, list[str]]:
    """The primary filter and the side-by-side ones (without duplicates, the primary may be among them)."""
    return vals["filter"], list(dict.fromkeys(vals["filters"]))


def target_overrides(vals: dict[str, Any], target: str) -> dict[str, Any]:
    """The filter parameters ``target`` sets for itself: its ``motion`` preset's values (:mod:`.filters.motion`),
    over them each :data:`TARGET_PARAMS` row with a ``field`` given a value, and ``motion`` ("auto" for fullperc's
    IMM, else "fixed"). They replace the node-wide ones for that target only, so an arm-held tool and a hand-held
    instrument can share one node."""
    motion = vals.get(f"{target}.motion") or "auto"
    own = {tp.field: vals[f"{target}.{tp.name}"] for tp in TARGET_PARAMS
           if tp.field and vals.get(f"{target}.{tp.name}") is not None}
    return {**preset_fields(motion), **own, "motion": "auto" if motion == "auto" else "fixed"}


def _pose(v: list[float] | None):
    return None if v is None else (np.asarray(v[:3], float), np.asarray(v[3:], float))


def target_config(get: Get | dict[str, Any], target: str, filters: tuple[str, ...] | None = None) -> TargetConfig:
    """The :class:`TargetConfig` of ``target``: ``get(name, default)`` or values from :func:`read_values`.

    ``filters`` None: the node's, ``filter`` first then ``filters``; else exactly these.
    """
    vals = get if isinstance(get, dict) else read_values(get, [target])
    if f"{target}.omc_body" not in vals:
        raise ParameterError(f"target '{target}' is not in the values read (targets {vals['targets']})")
    if filters is None:
        primary, extra = primary_and_extra(vals)
        filters = tuple(dict.fromkeys([primary, *extra]))
    path = vals["calibration_file"]
    try:
        cal = load_calibration(path) if path else None
    except CalibrationError as e:
        raise ParameterError(f"parameter 'calibration_file' = {path!r}: {e}") from None
    try:
        base = ChainConfig(omc_target=vals[f"{target}.omc_body"], ots_target=vals[f"{target}.ots_tool"],
                            omc_base=vals["omc_base_body"], omc_rig=vals["omc_rig_body"],
                            ots_base=vals["ots_base_tool"], local_chain=vals["local_chain"],
                            init_samples=vals["init_samples"], T_rig_ots=_pose(vals["T_rig_ots"]),
                            T_base_ots=_pose(vals["T_base_ots"]), static_links=vals["static_links"],
                            calibration_duration_s=vals["calibration.duration"],
                            calibration_settings=calibration_settings(vals), calibration=cal,
                            calibration_file=path)
        sources, chain = source_set(vals, target, base)
        nm = noise_model(vals)
        params = nm.apply(filter_params(vals))
        params = replace(params, **target_overrides(vals, target)).validate()
        return TargetConfig(name=target, chain=chain, sources=sources, filters=tuple(filters),
                            params=params, omc_model=nm.omc, max_jump=vals["plausibility.jump"],
                            slop_ns=int(vals["slop"] * 1e9), delay_ns=int(vals["reorder_delay"] * 1e9),
                            max_future_ns=round(vals["max_future"] * 1e9), max_speed=vals["plausibility.max_speed"],
                            processing=vals["processing"], history_ns=int(round(vals["history"] * 1e9)),
                            partner_wait_ns=int(round(vals["partner_wait"] * 1e9)),
                            monitor=monitor_params(vals), layout=model_layout(vals, tuple(filters)))
    except ParameterError:
        raise
    except ValueError as e:   # checks of the dataclasses beyond the table's
        raise ParameterError(str(e)) from e


# ---------------------------------------------------------------------------------------------- the file
class FusionConfigError(ParameterError):
    """A fusion params file cannot be read or has a wrong value; the message names the file and the field."""


class LoadedConfig(NamedTuple):
    """``config, values = load_fusion_config(...)``."""

    config: TargetConfig
    values: dict[str, Any]


def default_fusion_config_path() -> Path:
    """The installed ``share/fullperc_fusion/config/fusion.yaml`` (the node's params file), else the source copy."""
    from fullperc_common.share import share_path

    try:
        return share_path("fullperc_fusion", "config", "fusion.yaml")
    except FileNotFoundError as e:
        raise FusionConfigError(f"{e}; pass the file explicitly") from None


def flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    """Nested YAML keys -> dotted parameter names, as ROS does for a params file."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


NODE_KEYS = ("/**/fusion_node", "fusion_node", "/fusion_node", "/**")
"""The keys a params file may give fusion_node's block under, in the order they are looked up."""


def node_key(doc: Any) -> str:
    """The key of fusion_node's block in a params file's YAML ``doc`` (the first of :data:`NODE_KEYS` present; the
    shipped files' ``/**/fusion_node`` when none is): a program that edits a copy must edit that block, not add one
    that the reader never looks at."""
    return next((k for k in NODE_KEYS if isinstance(doc, dict) and k in doc), NODE_KEYS[0])


def read_params_file(path: str | Path) -> dict[str, Any]:
    """The flat ``ros__parameters`` of fusion_node in a file (``/**/fusion_node:``, ``fusion_node:``, ``/**``)."""
    from fullperc_common.yaml_file import RosParamsLoader, load_yaml_file

    p = Path(path)
    data = load_yaml_file(p, "fusion config", FusionConfigError, RosParamsLoader) or {}   # numbers read as rcl does
    node = None
    if isinstance(data, dict):
        node = data[node_key(data)] if node_key(data) in data else data
    params = node.get("ros__parameters", node) if isinstance(node, dict) else None
    if not isinstance(params, dict):
        raise FusionConfigError(f"fusion config {p}: expected 'fusion_node: ros__parameters: {{...}}'")
    return flatten(params)


def load_fusion_config(path: str | Path | None = None, target: str = "tool",
                       filters: tuple[str, ...] | None = PAPER_ORDER) -> LoadedConfig:
    """TargetConfig of ``target`` from a fusion_node params file, mapped exactly as ``fusion_node`` maps its
    parameters; keys the file does not set take the node's defaults (an empty file = the node's defaults).

    ``filters``: the methods to run (default: all five, :data:`PAPER_ORDER`); None = the file's ``filter`` and
    ``filters`` as the node runs them. Returns ``(config, values)``: ``values`` = the file's flat keys updated
    with every parameter of the table as used (defaults filled in) and ``_source`` = the file.
    Raises :class:`FusionConfigError` (a ParameterError / ValueError) naming the file and the parameter.
    """
    p = Path(path) if path is not None else default_fusion_config_path()
    flat = read_params_file(p)
    try:
        vals = read_values(lambda name, default: flat.get(name), [target])
        cfg = target_config(vals, target, filters)
    except ParameterError as e:
        raise FusionConfigError(f"fusion config {p}: {e}") from None
    values = dict(flat)
    values.update(vals)
    values["_source"] = str(p)
    return LoadedConfig(cfg, values)
