"""Measurement sources by configuration (issue 18 item 1): one global source and one or more local ones.

Why: the node used to hard-code one global (OMC, ``/omc/<body>/pose``) and one local (OTS, ``/ots/<tool>/pose``)
source; a second local tracker (an Atracsys, a second Vega) meant editing code. Now a params file lists them::

    sources: [omc, ots, atracsys]
    omc:      {role: global, topic_prefix: omc}
    ots:      {role: local, topic_prefix: ots, chain: static, noise_model: vega}
    atracsys: {role: local, topic_prefix: atracsys, chain: static, base_tool: base, noise_std: 2.0e-4}
    tool:     {omc_body: tool, ots_tool: tool, atracsys: tool}     # per target: the device name per source

Rules (checked at start, :class:`~fullperc_common.params.ParameterError` naming the parameter, exit 2):
exactly one ``global`` source -- the filters carry one bias state for it -- and at least one ``local``; every
listed name needs its block (``<name>.role``); names are lower-case identifiers that clash neither with each
other, a target, a node parameter or group (``noise``, ``alarm`` ...), nor with ``global`` / ``local`` (the
synchronizer's stream names). Without ``sources`` the built-in pair omc + ots applies and the legacy parameters
(``omc_base_body``, ``local_chain``, ``T_base_ots``, ``<target>.omc_body`` ...) are its settings, unchanged; with
it they stay the settings of the global and of the *first* local source unless that source's block overrides
them (``T_base`` / ``T_rig`` may not be given twice).

Fusion with more than one local source keeps the filters' contract (at most one global and one local
measurement per update, :func:`filter_api.split_update`): the global samples pair (``slop``) with the *first*
local source exactly as before, and every sample of a further local source is its own local-only item, sorted
by stamp among the others (:class:`synchronizer.ApproxSync`, one stream per source). Why not "pair with the
nearest local of any source": it would change which local a global sample pairs with whenever a second tracker
is added, i.e. the paper's pairing and every pinned result, and it makes the pairing depend on two trackers'
relative phase; a local-only update is what the filters already do while the OMC is occluded, and the bias stays
observable from the global samples (paired or alone). An item of a further source whose stamp lies inside the
previous pair's slop window is fused as a lagged measurement at that pair's stamp (filter_api.Filter.update),
as the pair itself fuses its older sample. Each local sample goes through its own source's chain
(:class:`frame_chain.FrameChain`: ``static`` with its own ``T_base_<name>`` from the calibration file, the
parameter or the same average / calibrate estimation from the sightings of its ``base_tool``; ``tracked`` with
the OMC pose of its ``rig_body`` and ``T_rig_<name>``; ``direct``) and gets its own noise (:func:`fixed_cov`).

Noise: ``noise_std`` [m, per axis] gives the source's samples the covariance diag(std^2 x3, rot_std^2 x3) for
every filter (the paper's filters use its position block: the same as ``noise.global_std`` / ``local_std`` for
that source). Without it: ``noise_model: vega`` (default of the first local source) uses the Vega's distance
model plus the link covariance (:func:`measurement_models.local_covariance`) for filters that declare ``models``
and the fixed ``noise.local_std`` for the paper's; ``omc`` (the global default) the OMC model; ``std`` (default
of a further local source) the diagonal of ``noise.local_std`` / ``global_std``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from fullperc_common.params import ParameterError
from fullperc_fusion.calibration.se3_stats import LINK_NAMES, Calibration
from fullperc_fusion.filters.api import ROLE_LABELS, Role
from fullperc_fusion.pipeline.frame_chain import LOCAL_CHAINS, ChainConfig
from fullperc_fusion.pipeline.param_table import NONEMPTY, POSITIVE, Get, Param, Rule, bad_value, convert, one_of

ROLES = ROLE_LABELS   # a source's ``role``: filters.api.Role's labels
GLOBAL, LOCAL = Role.GLOBAL.label, Role.LOCAL.label
GLOBAL_MODELS = ("omc", "std")
LOCAL_MODELS = ("vega", "std")
DEFAULT_NAMES = ("omc", "ots")
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
# names no source may take beyond the caller's (the node's parameters and per-target suffixes): the synchronizer's
# stream names of the two roles, and the reference frame (its links are T_base_<source>)
_RESERVED = {*ROLE_LABELS, "base"}

# the keys of a source block, each a row of fusion_config's kind (what --help and docs/nodes.md show) with its rule;
# noise_model's rule depends on the role (_MODEL_RULE)
SOURCE_KEYS: dict[str, Param] = {p.name: p for p in (
    Param("role", None, "str", *one_of(ROLES), "", "global (exactly one) | local (one or more)"),
    Param("topic_prefix", None, "str", lambda v: v.strip("/") != "" and not v.startswith("~"),
          "a topic prefix such as atracsys (relative: under the node's namespace) or /atracsys (absolute)", "",
          "pose topic <prefix>/<device>/pose, quality .../quality; default <name> (relative)"),
    Param("noise_std", None, "float", *POSITIVE, "m",
          "per-axis position noise of its samples (replaces noise.global_std / local_std)"),
    Param("noise_model", None, "str", None, "", "",
          "omc | std (global); vega | std (local): the covariance of filters that declare models"),
    Param("chain", None, "str", *one_of(LOCAL_CHAINS), "",
          "local: static | tracked | direct (first local: local_chain, further: static)"),
    Param("base_tool", None, "str", None, "", "",
          "local: its tool on the reference marker (first local: ots_base_tool, further: base)"),
    Param("rig_body", None, "str", None, "", "",
          "local: the OMC body on the tracker (first local: omc_rig_body, further: <name>_rig)"),
    Param("T_base", None, "pose7", None, "", "m, quaternion x y z w",
          "local: fixed link base -> tracker (static chain)"),
    Param("T_rig", None, "pose7", None, "", "m, quaternion x y z w",
          "local: hand-eye link rig -> tracker (tracked chain)"),
)}
_MODEL_RULE = {GLOBAL: Rule(lambda v: v in GLOBAL_MODELS, f"one of {GLOBAL_MODELS} for the global source"),
               LOCAL: Rule(lambda v: v in LOCAL_MODELS, f"one of {LOCAL_MODELS} for a local source")}


def source_param(source: str, key: str, default: Any = None) -> Param:
    """The row of ``<source>.<key>`` (a key of :data:`SOURCE_KEYS`) with ``default``."""
    row = SOURCE_KEYS[key]
    return replace(row, name=f"{source}.{key}", default=default, doc=f"source '{source}': {row.doc}")


def device_param(target: str, source: str) -> Param:
    """The row of ``<target>.<source>``: the target's device name on that source (default: resolved by
    :func:`read_source_values`)."""
    return Param(f"{target}.{source}", None, "str", *NONEMPTY, "", f"device name of target '{target}' for source "
                 f"'{source}'")


def default_namespace(topic: str) -> str:
    """A topic name resolved as in the default namespace without remapping (offline use, the evaluator reading a bag,
    the unit tests): a relative name gets a leading ``/``."""
    return topic if topic.startswith("/") else f"/{topic}"


@dataclass(frozen=True, eq=False)
class SourceSpec:
    """One source of a target. ``chain``: the frame chain of a *further* local source (None for the global and
    the first local source, whose chain is ``TargetConfig.chain``)."""

    name: str
    role: str
    topic_prefix: str
    noise_std: float | None = None
    noise_model: str = "std"
    chain: ChainConfig | None = None

    def topic(self, device: str, what: str = "pose") -> str:
        return f"{self.topic_prefix.rstrip('/')}/{device}/{what}"


@dataclass(frozen=True, eq=False)
class SourceSet:
    """The sources of one target: ``glob`` and ``locals`` (``locals[0]`` pairs with the global source)."""

    glob: SourceSpec = field(default_factory=lambda: SourceSpec("omc", GLOBAL, "omc", None, "omc"))
    locals: tuple[SourceSpec, ...] = field(default_factory=lambda: (SourceSpec("ots", LOCAL, "ots", None, "vega"),))

    @property
    def extras(self) -> tuple[SourceSpec, ...]:
        """The further local sources (each its own synchronizer stream, never paired)."""
        return self.locals[1:]

    @property
    def stream_names(self) -> tuple[str, ...]:
        """Synchronizer stream names: global, local (the first local source), then the further sources' names."""
        return (*ROLE_LABELS, *(s.name for s in self.extras))


def read_source_values(get: Get, vals: dict[str, Any], targets: list[str], taken: set[str]) -> dict[str, Any]:
    """The values of every source block (``<source>.<key>``) and per-target device name (``<target>.<source>``)
    when ``sources`` is given, converted and checked by their rows (:data:`SOURCE_KEYS`); {} without it (the
    built-in omc + ots, nothing more is read).

    ``taken``: the names a source must not take beyond its own reserved ones -- the first components of the node's
    parameter names (``noise``, ``alarm`` ...) and the per-target parameter suffixes (``omc_body`` ...); the caller
    derives them from its table.
    """
    names = vals.get("sources") or []
    if not names:
        return {}
    out: dict[str, Any] = {}
    seen: set[str] = set()
    for s in names:
        if not _NAME.match(s):
            raise bad_value("sources", names, f"'{s}' is not a lower-case identifier ([a-z][a-z0-9_]*)")
        if s in seen:
            raise bad_value("sources", names, f"'{s}' is listed twice")
        if s in targets or s in taken or s in _RESERVED:
            raise bad_value("sources", names, f"'{s}' clashes with a target or a parameter name; rename the source")
        seen.add(s)
    roles = {}
    for s in names:
        role = convert(source_param(s, "role"), get(f"{s}.role", None))
        if role is None:
            raise ParameterError(f"source '{s}' (parameter 'sources') has no block: give '{s}: {{role: global|local, "
                                 "...}'")
        roles[s] = role
    glob = [s for s in names if roles[s] == GLOBAL]
    loc = [s for s in names if roles[s] == LOCAL]
    if len(glob) != 1:
        raise bad_value("sources", names, f"exactly one source needs role global (the filters carry one bias state "
                                          f"for it), got {glob or 'none'}")
    if not loc:
        raise bad_value("sources", names, "at least one source needs role local")
    if "ots" in names and "ots" != loc[0] or "omc" in names and "omc" != glob[0]:
        raise bad_value("sources", names, "the names omc and ots are kept for the global and the first local source "
                                          "(the legacy parameters are theirs)")
    out["_global"], out["_locals"] = glob[0], loc

    def rd(s: str, key: str, default: Any, rule: Rule | None = None) -> Any:
        p = source_param(s, key, default)
        if rule is not None:
            p = replace(p, check=rule.check, why=rule.why)
        v = convert(p, get(p.name, default))
        out[p.name] = v
        return v

    for s in names:
        out[f"{s}.role"] = roles[s]
        rd(s, "topic_prefix", s)
        rd(s, "noise_std", None)
        first = s == loc[0]
        if roles[s] == GLOBAL:
            rd(s, "noise_model", "omc", _MODEL_RULE[GLOBAL])
            continue
        rd(s, "noise_model", "vega" if first else "std", _MODEL_RULE[LOCAL])
        rd(s, "chain", vals["local_chain"] if first else "static")
        rd(s, "base_tool", vals["ots_base_tool"] if first else "base")
        rd(s, "rig_body", vals["omc_rig_body"] if first else f"{s}_rig")
        for key, legacy in (("T_base", "T_base_ots"), ("T_rig", "T_rig_ots")):
            v = rd(s, key, None)
            if first and v is not None and vals[legacy] is not None:
                raise ParameterError(f"parameter '{s}.{key}' and '{legacy}' both give the link of source '{s}'; "
                                     "give it once")
            if first and v is None:
                out[f"{s}.{key}"] = vals[legacy]
    for t in targets:
        for s in names:
            legacy = f"{t}.omc_body" if s == glob[0] else f"{t}.ots_tool" if s == loc[0] else None
            p = device_param(t, s)
            dev = convert(p, get(p.name, None))
            out[p.name] = dev if dev is not None else (vals[legacy] if legacy else t)
    return out


def source_set(vals: dict[str, Any], target: str, base: ChainConfig) -> tuple[SourceSet, ChainConfig]:
    """The target's :class:`SourceSet` and its first local source's chain (``base`` with the source block's
    settings); ``base`` unchanged and the built-in omc + ots without ``sources``."""
    cal0 = base.calibration   # the first local source's chain: the file's links of the built-in names only
    if cal0 is not None and set(cal0.links) - set(LINK_NAMES):
        cal0 = replace(cal0, links={k: v for k, v in cal0.links.items() if k in LINK_NAMES})
    if not vals.get("sources"):
        return SourceSet(), (base if cal0 is base.calibration else replace(base, calibration=cal0))
    g, locs = vals["_global"], vals["_locals"]
    spec = {s: SourceSpec(s, vals[f"{s}.role"], vals[f"{s}.topic_prefix"], vals[f"{s}.noise_std"],
                          vals[f"{s}.noise_model"]) for s in (g, *locs)}

    def chain_of(s: str, cal: Calibration | None) -> ChainConfig:
        T_base, T_rig = vals[f"{s}.T_base"], vals[f"{s}.T_rig"]
        return replace(base, calibration=cal, omc_target=vals[f"{target}.{g}"], ots_target=vals[f"{target}.{s}"],
                       ots_base=vals[f"{s}.base_tool"], omc_rig=vals[f"{s}.rig_body"],
                       local_chain=vals[f"{s}.chain"], T_base_ots=_pose(T_base), T_rig_ots=_pose(T_rig))

    first = chain_of(locs[0], cal0)
    extras = []
    for s in locs[1:]:
        cal = renamed_calibration(base.calibration, s)
        for key in ("T_base", "T_rig"):
            if vals[f"{s}.{key}"] is not None and cal is not None and f"{key}_ots" in cal.links:
                raise ParameterError(f"parameter '{s}.{key}' is also in the calibration file "
                                     f"{base.calibration_file!r} as {key}_{s}; give it once")
        extras.append(replace(spec[s], chain=chain_of(s, cal)))
    return SourceSet(spec[g], (spec[locs[0]], *extras)), first


def _pose(v: list[float] | None):
    return None if v is None else (np.asarray(v[:3], float), np.asarray(v[3:], float))


def renamed_calibration(cal: Calibration | None, source: str) -> Calibration | None:
    """The calibration file's links of a further local source as its chain names them: T_omc_base, and
    T_base_<source> / T_rig_<source> as T_base_ots / T_rig_ots."""
    if cal is None:
        return None
    links = {k: v for k, v in cal.links.items() if k == "T_omc_base"}
    for key in ("T_base", "T_rig"):
        if f"{key}_{source}" in cal.links:
            links[f"{key}_ots"] = cal.links[f"{key}_{source}"]
    return replace(cal, links=links)


def fixed_cov(spec: SourceSpec, rot_std: float) -> np.ndarray | None:
    """diag(noise_std^2 x3, rot_std^2 x3) for a source with ``noise_std`` (module docstring), else None."""
    if spec.noise_std is None:
        return None
    return np.diag([spec.noise_std**2] * 3 + [rot_std**2] * 3)


def model_cov_std(spec: SourceSpec, default_std: float, rot_std: float) -> np.ndarray:
    """The covariance a model-using filter gets from a ``noise_model: std`` source: diag of its noise_std, or of
    the filters' fixed noise for its role (``default_std``) without one."""
    std = spec.noise_std if spec.noise_std is not None else default_std
    return np.diag([std**2] * 3 + [rot_std**2] * 3)


class Route(NamedTuple):
    """One device stream a target's pipeline takes in (fusion_node's subscriptions): ``tag`` omc (the global
    source), ots (the first local) or the further source's name; ``k`` -1 global, else the local source index."""

    tag: str
    k: int
    prefix: str
    bodies: tuple[str, ...]   # every body / tool of this device the pipeline uses (target first)
    target: str               # the target's own body / tool (its samples are measurements)


def routes(sources: SourceSet, chain: ChainConfig, extra_chains: list) -> list[Route]:
    """The device streams of one target (``TargetPipeline.config.sources``, ``.config.chain``, ``.extra_chains``)."""
    c = chain
    rigs = tuple(ch.cfg.omc_rig for ch in extra_chains)
    out = [Route("omc", -1, sources.glob.topic_prefix, (c.omc_target, c.omc_base, c.omc_rig, *rigs), c.omc_target),
           Route("ots", 0, sources.locals[0].topic_prefix, (c.ots_target, c.ots_base), c.ots_target)]
    for k, (x, ch) in enumerate(zip(sources.extras, extra_chains, strict=True), start=1):
        out.append(Route(x.name, k, x.topic_prefix, (ch.cfg.ots_target, ch.cfg.ots_base), ch.cfg.ots_target))
    return out
