"""Every fusion filter by name: the one place a filter is registered (CONTRIBUTING.md, "How to add a filter").

:data:`FILTERS` maps a name to a factory ``(params: FilterParams | None) -> Filter`` (:class:`filter_api.Filter`).
Everything that lists or builds filters derives from it: :func:`make_filter`, ``pipeline.FILTER_NAMES`` (the
order of this dict is the evaluator's column order and the benchmarks'), and through FILTER_NAMES the checks of
``TargetConfig`` and ``fusion_config`` (the ``filter`` / ``filters`` node parameters).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

from .fast_filter import ClosedFormFilter
from .filter_api import Filter
from .filters import FilterParams, PassThrough
from .fullperc_filter import FullpercFilter

FilterFactory = Callable[[FilterParams | None], Filter]

FILTERS: dict[str, FilterFactory] = {
    # the paper's four filters in closed form per axis (fast_filter; falls back to filters.FusionFilter, the
    # general form and the tests' reference, when a measurement's position covariance couples the axes)
    "cbkf": partial(ClosedFormFilter, "cbkf"),   # the paper's method (default)
    "ckf": partial(ClosedFormFilter, "ckf"),
    "bkf": partial(ClosedFormFilter, "bkf"),
    "kf": partial(ClosedFormFilter, "kf"),
    "omc": PassThrough,                      # the raw global source, for comparison
    # ours (issue 18): CBKF's compensated position + per-measurement model covariance + orientation on SO(3); the
    # fast form (fullperc_filter) of the general fullperc_reference.FullpercReference, the tests' reference
    "fullperc": FullpercFilter,
}


def make_filter(name: str, params: FilterParams | None = None) -> Filter:
    """A new filter ``name`` (a key of :data:`FILTERS`) with ``params`` (default :class:`FilterParams`)."""
    try:
        factory = FILTERS[name]
    except KeyError:
        raise ValueError(f"filter '{name}' is not one of {tuple(FILTERS)}") from None
    return factory(params)
