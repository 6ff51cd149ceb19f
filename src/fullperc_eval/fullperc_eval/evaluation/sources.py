"""The single sources as the filters see them: a tap on the measurements fed to every filter.

Issue 18's orientation goal compares a fusing filter with "the better single source". The raw OMC is already a
method (the ``omc`` pass-through), but the raw local chain -- the Vega measurement mapped into ``base`` through the
static link (or eq. 1 / eq. 2) -- is not output by anything. Recomputing it beside the pipeline would be a second
implementation of the frame chain that could disagree with the first; instead :class:`SourceTap` sits in the
pipeline's filter table like a filter (the :class:`fullperc_fusion.filters.api.Filter` protocol), records each
:class:`~fullperc_fusion.filters.api.Measurement` exactly as the filters receive it and returns no step, so the
pipeline emits nothing for it and every other filter is untouched (filters are independent of one another).

``snapshot()`` / ``restore()`` keep it correct under a pipeline that rewinds and replays its filters: a restore
forgets what was recorded after the snapshot, so the record ends as the ordered processing's measurements.
"""

from __future__ import annotations

import numpy as np

from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL, Measurement

ROLES = {SOURCE_GLOBAL: "global", SOURCE_LOCAL: "local"}


class SourceTap:
    """A do-nothing filter that records the measurements it is given, per source role (see the module doc)."""

    kind = "source_tap"
    NAME = "_source_tap"   # its key in TargetPipeline.filters: not a registry name, never configured or output

    def __init__(self) -> None:
        self.records: list[Measurement] = []

    def reset(self) -> None:
        """Nothing to forget: the record is the evaluation's, not a state."""

    def predict(self, t_ns: int) -> None:
        """No state to move."""

    def update(self, *measurements: Measurement) -> None:
        self.records.extend(measurements)
        return None

    def snapshot(self) -> int:
        return len(self.records)

    def restore(self, snap: int) -> None:
        del self.records[int(snap):]

    def arrays(self) -> dict[str, dict[str, np.ndarray]]:
        """Per role ("global", "local"): ``t_ns`` (N,), ``p`` (N, 3) [m] and ``q`` (N, 4) x y z w in ``base``
        (NaN rows where a measurement had no orientation), in stamp order, one row per stamp."""
        out = {}
        for src, role in ROLES.items():
            ms = sorted({m.t_ns: m for m in self.records if m.source == src}.values(), key=lambda m: m.t_ns)
            out[role] = {"t_ns": np.array([m.t_ns for m in ms], dtype=np.int64),
                         "p": np.array([m.p for m in ms], dtype=float).reshape(len(ms), 3),
                         "q": np.array([np.full(4, np.nan) if m.q is None else m.q for m in ms],
                                       dtype=float).reshape(len(ms), 4)}
        return out
