"""A filter lane: filters fused together on the same items, and everything the pipeline keeps of their run.

Why a unit of its own: fusion on arrival (:mod:`.arrival`) rewinds -- it puts the state before an item back and
fuses again from there. Everything that fusing an item changes therefore has to be restorable, and nothing else
may be touched by a restore. That is this object: its filters (their own ``snapshot()`` / ``restore()``, part of
the :class:`~fullperc_fusion.filters.api.Filter` protocol) and its :class:`LaneState`, which is copied whole --
every attribute, not a list of them -- so state added to it is rewound without further code
(test_pipeline_state.py). The pipeline's other attributes are constants or input-side state a rewind must not
undo (:class:`~.ordered.TargetPipeline`'s ``CONSTANT`` / ``KEPT``, held to ``vars(pipe)`` by the same test).

Lanes of a pipeline: ordered processing has one (every configured filter). Fusion on arrival has two, the live
lane (the primary filter, fused on arrival and rewound) and the side-by-side lane (the other filters, fused when
an item leaves the history; never rewound).

What a filter supports is what its registry entry declares (:func:`caps_of`), never guessed from its attributes.
A filter that declares ``models`` also follows the local chain's frame: it has ``express_in(T_frame, local)``
(:meth:`~fullperc_fusion.filters.fullperc.FullpercFilter.express_in`), and the pipeline adds the frame's own
covariance to its output (:mod:`.ordered`, "Frame covariance").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

from fullperc_fusion.filters.api import Capabilities, Filter
from fullperc_fusion.filters.registry import FILTERS
from fullperc_fusion.pipeline.target import FusedOutput

UNDECLARED = Capabilities()   # a name that is not registered: an observer in the filter table (the evaluator's taps)


def caps_of(name: str) -> Capabilities:
    """What filter ``name`` declares in the registry; :data:`UNDECLARED` for a name that is not registered (a tap
    the evaluator puts in a lane's filter table to record the measurements: it supports nothing beyond the
    protocol)."""
    spec = FILTERS.get(name)
    return UNDECLARED if spec is None else spec.caps


def _detached(v: Any) -> Any:
    """``v`` sharing nothing mutable with the lane: containers are copied (their items are values, never changed
    in place: outputs, stamps), anything else is a value itself."""
    return v.copy() if isinstance(v, dict | list | set) else v


@dataclass(eq=False)
class LaneState:
    """What a lane has fused besides its filters' own states. Every attribute is part of a snapshot (:meth:`copy`
    copies ``__dict__`` whole): values, or containers of values."""

    last_local_ns: int | None = None   # stamp of the newest local sample fused (FusedOutput.time_since_local)
    last_item_ns: int | None = None    # processing stamp of the newest item (a further source's lagged sample)
    last_output: dict[str, FusedOutput] = field(default_factory=dict)   # the newest output per filter

    def copy(self) -> LaneState:
        """A copy that shares nothing mutable with this one: a snapshot, and what a restore takes back from it."""
        c = LaneState.__new__(LaneState)
        c.__dict__.update({k: _detached(v) for k, v in self.__dict__.items()})
        return c


class LaneSnapshot(NamedTuple):
    """A lane's whole state as a value (:meth:`FilterLane.snapshot`); stays valid for any number of restores."""

    filters: tuple[object, ...]   # each filter's own snapshot(), in the lane's order
    state: LaneState


class FilterLane:
    """Filters fused together (``filters``: name -> filter, in output order) and their :class:`LaneState`.

    ``filters`` is the dict a caller may add an observer to (the evaluator's taps: ``pipe.filters[name] = tap``);
    ``models`` (a filter here declares ``models``: the pipeline builds the model covariances for this lane) is
    fixed at construction.
    """

    __slots__ = ("filters", "models", "state")

    def __init__(self, filters: dict[str, Filter]) -> None:
        self.filters = filters
        self.models = any(caps_of(name).models for name in filters)
        self.state = LaneState()

    def snapshot(self) -> LaneSnapshot:
        """Everything fusing an item changes in this lane, as a value."""
        return LaneSnapshot(tuple(f.snapshot() for f in self.filters.values()), self.state.copy())

    def restore(self, snap: LaneSnapshot) -> None:
        """Back to ``snap`` (:meth:`snapshot` of this lane; it stays valid)."""
        for f, s in zip(self.filters.values(), snap.filters, strict=True):
            f.restore(s)
        self.state = snap.state.copy()

    def reset(self) -> None:
        """Every filter forgets its state (a new timeline, arrival.py); the lane's own marks are kept."""
        for f in self.filters.values():
            f.reset()
