"""Which target samples a pipeline takes by their stamps: duplicate, late, and the timeline restart -- the one
implementation of these rules, used by the synchronizer (ordered processing) and by fusion on arrival.

Per synchronizer stream (global, the first local, each further local source) a sample at t is

* ``duplicate`` when its stream already has t: a sample admitted and not released yet (pending in the
  synchronizer, or in the arrival history), or the stream's last released one. The first sample wins; equal
  stamps on different streams are not duplicates (they pair).
* ``late`` when t is before the *horizon*: the processing stamp of the last item released (emitted by the
  synchronizer; left the arrival history, its outputs final). Fusing it would need the filters before that item.
  A further source's item can be stamped before the previous pair's processing stamp (synchronizer.py), so
  releasing it never moves the horizon back.
* ``restart`` (only with a ``history``, i.e. fusion on arrival): the stamps went back for good -- a bag played
  again, a clock reset, one stamp far ahead that no clock could check. Samples behind the newest admitted stamp
  by more than the history are a *late run*; once the run's own stamps span more than the history the caller
  ends its history, restarts the filters (:meth:`StampRules.restart`) and takes the sample. Only a stream that
  went back against its own stamps says the stamps went back for good: a source whose samples come late but in
  order (its driver starved on a busy machine: seen 1.3 s behind) is dropped as late -- restarting for it put
  the output a second back in time -- and its run restarts only after :data:`LATE_SOURCE_SPAN_NS` of its stamps
  (its clock may have been reset while the stream that ran ahead fell silent: the node must not stall).
  Ordered processing has no history and no restart: its synchronizer keeps dropping such samples as late.

Otherwise ``ok``: the caller :meth:`~StampRules.admit`\\ s it and later :meth:`~StampRules.release`\\ s the item it
ends up in. The rules count nothing themselves: the synchronizer counts per stream in its own counters, the
pipelines report the problem (:meth:`StampRules.message` is the text both give).
"""

from __future__ import annotations

from typing import Final, Protocol

OK: Final = "ok"
LATE: Final = "late"
DUPLICATE: Final = "duplicate"
RESTART: Final = "restart"
LATE_SOURCE_SPAN_NS = 5_000_000_000   # [ns] of a late source's own (in-order) stamps before it restarts the timeline


class _Stamped(Protocol):
    @property
    def t_ns(self) -> int: ...


class Item(Protocol):
    """What :meth:`StampRules.release` reads of an item: a :class:`~.synchronizer.SyncItem` (not imported: the
    synchronizer is built on these rules)."""

    @property
    def t_ns(self) -> int: ...

    @property
    def glob(self) -> _Stamped | None: ...

    @property
    def local(self) -> _Stamped | None: ...

    @property
    def source(self) -> int: ...


class StampRules:
    """The state the rules need, per stream of ``names`` (the synchronizer's stream names); see the module
    docstring. ``history_ns``: fusion on arrival's history, which enables the restart rule (None: ordered)."""

    __slots__ = ("_late_run", "_own_newest", "history_ns", "horizon_ns", "names", "newest_ns", "pending", "released")

    def __init__(self, names: tuple[str, ...], history_ns: int | None = None) -> None:
        self.names = tuple(names)
        self.history_ns = None if history_ns is None else int(history_ns)
        self.pending: tuple[set[int], ...] = tuple(set() for _ in self.names)   # admitted, not released
        self.released: list[int | None] = [None] * len(self.names)   # each stream's last released stamp
        self.horizon_ns: int | None = None   # processing stamp of the last item released
        self.newest_ns: int | None = None    # newest stamp admitted, any stream (the synchronizer's watermark)
        self._own_newest: list[int | None] = [None] * len(self.names)   # newest stamp seen per stream (restart)
        self._late_run: int | None = None    # first stamp of a run of samples all behind the history (restart)

    def check(self, stream: int, t: int) -> str:
        """The verdict on a sample of ``stream`` at ``t``: DUPLICATE, LATE, RESTART (end the history, then
        :meth:`restart` and admit it) or OK. Only the restart rule's own bookkeeping changes here."""
        if t in self.pending[stream] or self.released[stream] == t:
            return DUPLICATE
        if self.history_ns is not None and self._restarts(stream, t):
            return RESTART
        if self.horizon_ns is not None and t < self.horizon_ns:
            return LATE
        return OK

    def _restarts(self, stream: int, t: int) -> bool:
        own = self._own_newest[stream]
        if own is None or t > own:
            self._own_newest[stream] = t
        if self.newest_ns is None or t >= self.newest_ns - self.history_ns:
            self._late_run = None
            return False
        span = self.history_ns if own is not None and t < own else max(self.history_ns, LATE_SOURCE_SPAN_NS)
        if self._late_run is None:
            self._late_run = t
            return False
        return t - self._late_run > span

    def admit(self, stream: int, t: int) -> None:
        """``t`` of ``stream`` taken (after an OK or RESTART verdict)."""
        self.pending[stream].add(t)
        if self.newest_ns is None or t > self.newest_ns:
            self.newest_ns = t

    def release(self, item: Item) -> None:
        """``item`` is final: its samples are the last released of their streams, its stamp the horizon."""
        if item.glob is not None:
            self.pending[0].discard(item.glob.t_ns)
            self.released[0] = item.glob.t_ns
        if item.local is not None:
            s = 1 + item.source
            self.pending[s].discard(item.local.t_ns)
            self.released[s] = item.local.t_ns
        self.horizon_ns = item.t_ns if not item.source or self.horizon_ns is None else max(self.horizon_ns, item.t_ns)

    def restart(self) -> None:
        """A new timeline: no horizon, no newest stamp, nothing released (the history ended: nothing pending)."""
        self.horizon_ns = self.newest_ns = self._late_run = None
        self.released = [None] * len(self.names)
        self._own_newest = [None] * len(self.names)

    def message(self, verdict: str, what: str, t: int) -> str:
        """The problem text of a verdict other than OK for ``what`` (source and body, e.g. "OMC body 'tool'")."""
        if verdict == DUPLICATE:
            return f"{what}: duplicate stamp {t} ns; dropped"
        if verdict == RESTART:
            return (f"{what}: stamps went back to {t} ns, {(self.newest_ns - t) * 1e-9:.3f} s before the newest "
                    f"({self.newest_ns} ns), for more than the history; history ended, filters restarted")
        if self.history_ns is None:
            return (f"{what}: sample at {t} ns is older than the processed horizon {self.horizon_ns} ns (time went "
                    "backwards or arrived too late); dropped")
        return (f"{what}: sample at {t} ns is older than the history ({self.history_ns * 1e-9:g} s): "
                f"{(self.newest_ns - t) * 1e-9:.3f} s behind the newest sample ({self.newest_ns} ns), "
                f"before the last item that left the history ({self.horizon_ns} ns); dropped")
