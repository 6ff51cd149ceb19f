"""The drivers' one health ladder: events in, one (level, message, values) verdict out. Pure: no rclpy.

Why one ladder: a driver must never report OK while it publishes nothing. Each driver node feeds its
:class:`Health` the same kinds of events from its executor thread -- link up/down, every device frame (with its
frame number), every good output per item (a tool, a body, the arm) and every output it refused -- and
publishes :meth:`Health.verdict` through :class:`fullperc_common.diagnostics.Diagnostics`. Time comes from an
injectable clock, so the rules below are unit-tested without sleeping.

The rule (``stale_after_s`` = S, ``frames_stale_after_s`` = F, default S; ``reconnect_window_s`` = W):

* ERROR ``no <frame> received yet after t s (<why>)`` -- no device frame since start for more than F s.
  Before that: WARN ``no <frame> received yet (<why>)``.
* ERROR ``no new <frame>s for t s (<why>)`` -- no *new* frame for more than F s, where a frame whose number
  equals the previous one is not new. ``<why>`` is the first that applies: ``N reconnects in the last W s,
  last error: <reason>`` (N >= ``max_reconnects``); ``not connected: <reason>``; the same reconnect text for
  N >= 1; ``frame number frozen at <n> (k repeated)``; ``stream stopped``.
* While new frames arrive, per item (items the device refused are excluded, see below):
  - no item had a good output for more than S s and at least one was refused within S s: ERROR
    ``no good <output> for t s: every <output> refused (<item>: <reason>)``;
  - no item had a good output for more than S s, none refused: ``unseen_level`` (WARN for trackers, whose
    tools may all be out of view; ERROR for the arm) ``no <item> seen for t s (<names>)``;
  - otherwise each item without a good output for more than S s: WARN ``<item> '<name>' not seen for t s``,
    or ``<item> '<name>': every <output> refused for t s (<reason>)`` if it was refused within S s; an item
    with good outputs but also refusals within S s: WARN ``<item> '<name>': k <output>s refused in the last
    S s (<reason>)``. (A single item named like its kind, the arm, is just ``arm``.)
* An item the device refused for good (e.g. a tool ROM at PINIT): WARN ``<item> '<name>': <reason>``; ERROR
  ``every <item> refused by the device`` when no item is left.
* WARN ``link down, reconnecting (<reason>)`` from a :meth:`link_down` after the link had been up, and WARN
  ``link lost t s ago and re-established (<reason>)`` for ``link_hold_s`` (H) after it: a cut shorter than S would
  otherwise never leave OK (the driver reconnects in tens of ms), yet an OR user wants to see every link drop.
  Held only while frames are not already stale (then the ERROR above says it).
* WARN ``N reconnects in the last W s (last error: <reason>)`` when at least ``max_reconnects`` successful
  reconnects fell in the last W s, even while outputs flow.
* WARN ``k <problem> in the last S s (<detail>)`` for problems the node reports (decode errors, overflow),
  and whatever standing conditions the node passes to :meth:`Health.verdict`.
* OK ``<ok_text> at <rate> Hz`` when none of the above holds: the level returns to OK only once good
  outputs flow again.

The message joins every reason, worst first, with ``; ``. Levels are the ``diagnostic_msgs`` values
(0 OK, 1 WARN, 2 ERROR) as ints.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

OK, WARN, ERROR = 0, 1, 2


@dataclass
class HealthConfig:
    stale_after_s: float = 2.0  # an item with no good output for this long leaves OK
    frames_stale_after_s: float | None = None  # no new device frame for this long -> ERROR (None: stale_after_s)
    reconnect_window_s: float = 10.0  # reconnects are counted over this window
    max_reconnects: int = 3  # this many reconnects within the window -> WARN even while outputs flow
    rate_window_s: float = 1.0  # the reported rate counts new frames over this window
    link_hold_s: float = 1.0  # a link drop stays visible (WARN) this long after the link is back

    def validate(self) -> None:
        if not self.stale_after_s > 0:
            raise ValueError("stale_after_s must be > 0")
        if self.frames_stale_after_s is not None and not self.frames_stale_after_s > 0:
            raise ValueError("frames_stale_after_s must be > 0")
        if not (self.reconnect_window_s > 0 and self.max_reconnects >= 1 and self.rate_window_s > 0):
            raise ValueError("reconnect_window_s and rate_window_s must be > 0, max_reconnects >= 1")
        if not self.link_hold_s >= 0:
            raise ValueError("link_hold_s must be >= 0")

    @property
    def frames_after_s(self) -> float:
        return self.stale_after_s if self.frames_stale_after_s is None else self.frames_stale_after_s


@dataclass
class Verdict:
    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.level == OK


@dataclass
class _Item:
    added: float
    last_good: float | None = None
    good: int = 0
    refused: int = 0
    refused_times: deque = field(default_factory=deque)
    last_refused_reason: str = ""
    failed: str = ""  # permanent refusal by the device ("" = usable)


class Health:
    """Feed events from one thread (the executor); call :meth:`verdict` periodically (e.g. every 0.25 s).

    ``item_kind``/``output``/``frame`` are the words the messages use (``tool``/``pose``/``frame``,
    ``body``/``pose``/``frame``, ``arm``/``joint state``/``joint state``).
    """

    def __init__(self, items: Iterable[str] = (), config: HealthConfig | None = None, *,
                 item_kind: str = "tool", output: str = "pose", frame: str = "frame",
                 unseen_level: int = WARN, ok_text: str = "receiving",
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = config or HealthConfig()
        self.cfg.validate()
        self.clock = clock
        self.item_kind, self.output, self.frame_word = item_kind, output, frame
        self.unseen_level = unseen_level
        self.ok_text = ok_text
        self.t0 = clock()
        self.items: dict[str, _Item] = {}
        for i in items:
            self.add_item(i)
        self.connected = True
        self.link_reason = ""
        self._ever_up = False
        self._down_since_up = False
        self._lost_at: float | None = None  # last link_down after the link had been up
        self._lost_reason = ""
        self.frames = 0  # new frames
        self.repeats = 0  # frames that repeated the previous frame number
        self._repeats_since_new = 0
        self._last_number: int | None = None
        self._last_new: float | None = None
        self._new_times: deque[float] = deque()
        self.stalls = 0
        self._stalled = False
        self.reconnects = 0
        self._reconnect_times: deque[float] = deque()
        self.last_error = ""
        self._problems: dict[str, deque] = {}
        self._problem_detail: dict[str, str] = {}

    # ---- events ------------------------------------------------------------------------------------
    def add_item(self, name: str) -> None:
        if name not in self.items:
            self.items[name] = _Item(added=self.clock())

    def link_up(self) -> None:
        """The device link is (re)established; after a :meth:`link_down` this counts as one reconnect."""
        now = self.clock()
        if self._ever_up and self._down_since_up:
            self.reconnects += 1
            self._reconnect_times.append(now)
        self._ever_up = True
        self._down_since_up = False
        self.connected = True
        self.link_reason = ""

    def link_down(self, reason: str) -> None:
        if self._ever_up and self.connected:
            self._lost_at, self._lost_reason = self.clock(), reason
        self.connected = False
        self.link_reason = reason
        self.last_error = reason
        self._down_since_up = True

    def reconnect(self, reason: str = "") -> None:
        """One reconnect the node itself triggered (or observed) without separate up/down events."""
        self.reconnects += 1
        self._reconnect_times.append(self.clock())
        if reason:
            self.last_error = reason

    def frame(self, number: int | None = None) -> bool:
        """A device frame arrived; returns False (and counts a repeat) if it repeats the last frame number."""
        now = self.clock()
        if number is not None and number == self._last_number:
            self.repeats += 1
            self._repeats_since_new += 1
            return False
        self._last_number = number
        self._last_new = now
        self._repeats_since_new = 0
        self.frames += 1
        self._new_times.append(now)
        self._stalled = False
        return True

    def repeated(self, n: int = 1, number: int | None = None) -> None:
        """``n`` replies repeated a frame number the node already got (counted by a driver that dedupes)."""
        if n > 0:
            self.repeats += n
            self._repeats_since_new += n
            if number is not None:
                self._last_number = number

    def good(self, item: str) -> None:
        it = self._item(item)
        it.last_good = self.clock()
        it.good += 1

    def refused(self, item: str, reason: str) -> None:
        """An output of ``item`` was refused (non-finite, not a rotation, invalid sample...)."""
        it = self._item(item)
        it.refused += 1
        it.refused_times.append(self.clock())
        it.last_refused_reason = reason

    def item_failed(self, item: str, reason: str) -> None:
        """The device refused ``item`` for good (until :meth:`item_ok`), e.g. a tool ROM at PINIT."""
        self._item(item).failed = reason or "refused by the device"

    def item_ok(self, item: str) -> None:
        it = self._item(item)
        if it.failed:
            it.failed = ""
            it.added = self.clock()  # its staleness counts from now, not from its refusal

    def problem(self, kind: str, n: int = 1, detail: str = "") -> None:
        """``n`` soft errors of ``kind`` (e.g. ``decode errors``): WARN while any fell within stale_after_s."""
        if n <= 0:
            return
        q = self._problems.setdefault(kind, deque())
        now = self.clock()
        q.extend([now] * min(n, 10_000))
        if detail:
            self._problem_detail[kind] = detail

    def _label(self, name: str) -> str:
        return name if name == self.item_kind and len(self.items) == 1 else f"{self.item_kind} '{name}'"

    def _item(self, name: str) -> _Item:
        if name not in self.items:
            self.add_item(name)
        return self.items[name]

    # ---- verdict -----------------------------------------------------------------------------------
    def rate_hz(self, now: float | None = None) -> float:
        now = self.clock() if now is None else now
        w = self.cfg.rate_window_s
        while self._new_times and self._new_times[0] <= now - w:
            self._new_times.popleft()
        span = min(w, max(now - self.t0, 1e-9))
        return len(self._new_times) / span

    def recent_reconnects(self, now: float | None = None) -> int:
        now = self.clock() if now is None else now
        while self._reconnect_times and self._reconnect_times[0] < now - self.cfg.reconnect_window_s:
            self._reconnect_times.popleft()
        return len(self._reconnect_times)

    def _why_no_frames(self, now: float) -> str:
        n = self.recent_reconnects(now)
        reconnecting = (f"{n} reconnect{'s' if n != 1 else ''} in the last {self.cfg.reconnect_window_s:g} s, "
                        f"last error: {self.last_error or 'none'}")
        if n >= self.cfg.max_reconnects:
            return reconnecting
        if not self.connected:
            return f"not connected: {self.link_reason or 'no reason given'}"
        if n:
            return reconnecting
        if self._repeats_since_new:
            return f"frame number frozen at {self._last_number} ({self._repeats_since_new} repeated)"
        return "stream stopped"

    def verdict(self, conditions: Iterable[tuple[int, str]] = ()) -> Verdict:
        """The level, message and values now; ``conditions`` are the node's own standing (level, text) reasons."""
        now = self.clock()
        S, F = self.cfg.stale_after_s, self.cfg.frames_after_s
        reasons: list[tuple[int, str]] = []
        fw = self.frame_word
        frames_age = now - (self._last_new if self._last_new is not None else self.t0)
        frames_stale = frames_age > F
        if frames_stale and self._last_new is not None and not self._stalled:
            self.stalls += 1
            self._stalled = True
        if self._last_new is None:
            why = self._why_no_frames(now)
            why = "" if why == "stream stopped" else f" ({why})"
            if frames_stale:
                reasons.append((ERROR, f"no {fw} received yet after {frames_age:.1f} s{why}"))
            else:
                reasons.append((WARN, f"no {fw} received yet{why}"))
        elif frames_stale:
            reasons.append((ERROR, f"no new {fw}s for {frames_age:.1f} s ({self._why_no_frames(now)})"))
        else:
            reasons += self._item_reasons(now, S)
            if self._lost_at is not None and not self.connected:
                reasons.append((WARN, f"link down, reconnecting ({self._lost_reason or 'no reason given'})"))
            elif self._lost_at is not None and now - self._lost_at <= self.cfg.link_hold_s:
                reasons.append((WARN, f"link lost {now - self._lost_at:.1f} s ago and re-established "
                                      f"({self._lost_reason or 'no reason given'})"))
        for name, it in self.items.items():
            if it.failed:
                reasons.append((WARN, f"{self._label(name)}: {it.failed}"))
        if self.items and all(it.failed for it in self.items.values()):
            reasons.append((ERROR, f"every {self.item_kind} refused by the device"))
        n = self.recent_reconnects(now)
        if n >= self.cfg.max_reconnects and not frames_stale:
            reasons.append((WARN, f"{n} reconnects in the last {self.cfg.reconnect_window_s:g} s "
                                  f"(last error: {self.last_error or 'none'})"))
        for kind, q in self._problems.items():
            while q and q[0] < now - S:
                q.popleft()
            if q:
                detail = self._problem_detail.get(kind, "")
                reasons.append((WARN, f"{len(q)} {kind} in the last {S:g} s" + (f" ({detail})" if detail else "")))
        reasons += [(int(lvl), text) for lvl, text in conditions]
        rate = self.rate_hz(now)
        values = self.values(now, rate)
        if not reasons:
            return Verdict(OK, f"{self.ok_text} at {rate:.1f} Hz", values)
        reasons.sort(key=lambda r: -r[0])  # stable: worst first, then in the order found
        return Verdict(reasons[0][0], "; ".join(t for _, t in reasons), values)

    def _item_reasons(self, now: float, S: float) -> list[tuple[int, str]]:
        out: list[tuple[int, str]] = []
        live = {n: it for n, it in self.items.items() if not it.failed}
        for it in live.values():
            while it.refused_times and it.refused_times[0] < now - S:
                it.refused_times.popleft()

        def age(it: _Item) -> float:
            return now - (it.last_good if it.last_good is not None else max(it.added, self.t0))

        stale = {n: it for n, it in live.items() if age(it) > S}
        if live and len(stale) == len(live):
            t = min(age(it) for it in stale.values())
            refusing = [(n, it) for n, it in stale.items() if it.refused_times]
            if refusing:
                why = ", ".join(f"{n}: {it.last_refused_reason}" for n, it in refusing)
                out.append((ERROR, f"no good {self.output} for {t:.1f} s: every {self.output} refused ({why})"))
            else:
                out.append((self.unseen_level, f"no {self.item_kind} seen for {t:.1f} s ({', '.join(stale)})"))
            return out
        for n, it in live.items():
            if n in stale:
                if it.refused_times:
                    out.append((WARN, f"{self._label(n)}: every {self.output} refused for {age(it):.1f} s "
                                      f"({it.last_refused_reason})"))
                else:
                    out.append((WARN, f"{self._label(n)} not seen for {age(it):.1f} s"))
            elif it.refused_times:
                k = len(it.refused_times)
                out.append((WARN, f"{self._label(n)}: {k} {self.output}{'s' if k != 1 else ''} refused in the "
                                  f"last {S:g} s ({it.last_refused_reason})"))
        return out

    def values(self, now: float | None = None, rate: float | None = None) -> dict[str, str]:
        now = self.clock() if now is None else now
        rate = self.rate_hz(now) if rate is None else rate
        ages = []
        for n, it in self.items.items():
            if it.failed:
                ages.append(f"{n}=refused")
            elif it.last_good is None:
                ages.append(f"{n}=never")
            else:
                ages.append(f"{n}={now - it.last_good:.2f}")
        return {"rate_hz": f"{rate:.1f}", "stalls": str(self.stalls), "repeated_frames": str(self.repeats),
                "reconnects_recent": str(self.recent_reconnects(now)),
                "last_good_s_ago": " ".join(ages),
                "refused_outputs": str(sum(it.refused for it in self.items.values()))}
