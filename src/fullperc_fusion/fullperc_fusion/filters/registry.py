"""Every fusion filter by name: the one place a filter is registered (CONTRIBUTING.md, "How to add a filter").

:data:`FILTERS` maps a name to a :class:`FilterSpec`: the factory ``(params) -> Filter`` (:class:`~.api.Filter`),
the filter's own parameter dataclass, and its declared :class:`~.api.Capabilities`. Everything that lists, builds or
asks about filters derives from it: :func:`make_filter`, :func:`capabilities`, ``pipeline.ordered.FILTER_NAMES``
(the order of this dict is the evaluator's column order and the benchmarks'), and through FILTER_NAMES the checks
of ``TargetConfig`` and ``fusion_config`` (the ``filter`` / ``filters`` node parameters).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

from fullperc_fusion.filters.api import Capabilities, Filter
from fullperc_fusion.filters.fullperc import FullpercFilter
from fullperc_fusion.filters.fullperc_imm import FullpercImm
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.filters.paper_family import FilterParams, PassThrough
from fullperc_fusion.filters.paper_fast import ClosedFormFilter

FilterFactory = Callable[[FilterParams | None], Filter]


def _fullperc(params: FilterParams | None) -> Filter:
    """``fullperc``: the IMM over the motion presets when its ``motion`` is ``auto`` (:mod:`.fullperc_imm`), else
    the filter with the motion of its fields."""
    if isinstance(params, FullpercParams) and params.motion == "auto":
        return FullpercImm(params)
    return FullpercFilter(params)


@dataclass(frozen=True)
class FilterSpec:
    """One registry entry: how to build the filter, which parameters it takes, what it supports."""

    factory: FilterFactory
    params: type[FilterParams] = FilterParams
    caps: Capabilities = Capabilities()


_PAPER = Capabilities(batch=True)   # position only, fixed noise, replayable in paper_batch's closed-form loop

FILTERS: dict[str, FilterSpec] = {
    # the paper's four filters in closed form per axis (paper_fast; falls back to paper_family.FusionFilter, the
    # general form and the tests' reference, when a measurement's position covariance couples the axes)
    "cbkf": FilterSpec(partial(ClosedFormFilter, "cbkf"), FilterParams, _PAPER),   # the paper's method (default)
    "ckf": FilterSpec(partial(ClosedFormFilter, "ckf"), FilterParams, _PAPER),
    "bkf": FilterSpec(partial(ClosedFormFilter, "bkf"), FilterParams, _PAPER),
    "kf": FilterSpec(partial(ClosedFormFilter, "kf"), FilterParams, _PAPER),
    "omc": FilterSpec(PassThrough, FilterParams, _PAPER),             # the raw global source, for comparison
    # ours: CBKF's compensated position + per-measurement model covariance + orientation on SO(3); the fast form
    # (filters.fullperc) of the general fullperc_reference.FullpercReference, the tests' reference; with motion
    # auto one per motion preset as an IMM (filters.fullperc_imm)
    "fullperc": FilterSpec(_fullperc, FullpercParams, Capabilities(models=True, orientation=True)),
}


def spec(name: str) -> FilterSpec:
    """The registry entry of ``name``; ValueError naming the registered filters when there is none."""
    try:
        return FILTERS[name]
    except KeyError:
        raise ValueError(f"filter '{name}' is not one of {tuple(FILTERS)}") from None


def capabilities(name: str) -> Capabilities:
    """What filter ``name`` declares it supports."""
    return spec(name).caps


def own_params(name: str, params: FilterParams | None) -> FilterParams | None:
    """``params`` as filter ``name``'s own parameter dataclass: a target's configuration holds one object of the
    dataclass every registered one is a base of (``fullperc``'s, a superset); a filter whose own dataclass is a base of
    it gets a copy of its own fields only, so it cannot read (or come to depend on) another filter's parameters."""
    own = spec(name).params
    if params is None or type(params) is own or not isinstance(params, own):
        return params
    return own(**{f.name: getattr(params, f.name) for f in dataclasses.fields(own)})


def make_filter(name: str, params: FilterParams | None = None) -> Filter:
    """A new filter ``name`` (a key of :data:`FILTERS`) with its own fields of ``params`` (:func:`own_params`;
    default: its own parameter dataclass's defaults)."""
    return spec(name).factory(own_params(name, params))


def params_of_every_filter() -> type[FilterParams]:
    """The registered parameter dataclass that every registered filter's is a base of (FullpercParams: the paper's
    FilterParams plus fullperc's fields). One object of it serves every filter of a target (``TargetConfig.params``);
    a filter reads its own dataclass's fields only."""
    types = {s.params for s in FILTERS.values()}
    top = [t for t in types if all(issubclass(t, u) for u in types)]
    if len(top) != 1:
        raise TypeError("no registered parameter dataclass extends every other one: "
                        f"{sorted(t.__name__ for t in types)}")
    return top[0]
