"""``replay(on_time=True)``: a pose sample the recorder got far behind the others fed where it would have been on time.

Why: the replay feeds the recording in bag order, the order the *recorder* received the samples; that stands in for
the order fusion_node received them, and mostly it is (a device's latency delays both alike). The recorder is another
process, though: a reliable topic whose sample it got late -- a DDS repair of a lost packet holds the topic's later
samples until the heartbeat that repairs it, up to seconds on a loaded machine -- puts that topic's samples far behind
the others in the bag while the node, whose reader lost nothing, fused them in time. A CI demo saw three of the
instrument's OMC samples reach the recorder 2.66 s after their stamps: the bag-order replay dropped them as late
(the synchronizer's horizon had passed them), and a base sample of the same kind applied a static-link update 1.2 s
of stamps later than the node had; from there the replay's compensated filters were not the node's (CBKF MAE 2.82 mm
offline, 3.00 mm live, on the same stamps).

So, to compare the node with the replay of its inputs (the demo's live-against-offline check), a pose sample stamped
more than ``history`` (0.2 s: what fusion on arrival still fuses in order) or the synchronizer's reorder window
``2·slop + delay`` (58 ms by default; the bound is the shorter of the two) before the newest pose sample before it
in bag order is moved to just after the last pose sample placed before it stamped at or before it; every other
message keeps its place. Device latencies are far below that, so a recording without such a stall is replayed
exactly as by default (the committed bags: nothing moves at 58 ms). A sample the node itself got that late it
dropped and counted (its ``lost samples`` on /diagnostics), and the comparison counts what the node did not publish.

The replay's idle flush (no target sample for ``idle_flush``: everything pending is processed, which moves the
horizon to the newest stamp) then follows the stamps instead of the recorder's receive times: a recorder stall is a
gap in its receive times only, and another CI bag had a flush there make 67 of the instrument's OMC samples late
(stamped 3 ms before the horizon) that the node, which saw no pause, had fused. On the committed bags the stamps and
the receive times pause alike: the same flushes.

The default replay (``on_time=False``) keeps the bag order and the receive times: what a node that received as the
recorder did fuses.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, TypeVar


class _Stamped(Protocol):
    topic: str
    t_ns: int


M = TypeVar("M", bound=_Stamped)


def on_time_order(messages: Sequence[M], streams: set[str] | frozenset[str], late_ns: int) -> tuple[list[M], int]:
    """(``messages`` in bag order but for each sample of ``streams`` stamped more than ``late_ns`` before the newest
    sample of ``streams`` before it, which is moved to just after the last sample of ``streams`` placed before it and
    stamped at or before it; how many moved). Messages of other topics keep their places relative to the rest."""
    newest: int | None = None
    out: list[M] = []
    moved = 0
    for m in messages:
        if m.topic in streams:
            t = m.t_ns
            if newest is None or t > newest:
                newest = t
            elif t < newest - late_ns:
                j = len(out)   # back over the samples placed before it stamped after it (and other topics among them)
                while j > 0 and (out[j - 1].topic not in streams or out[j - 1].t_ns > t):
                    j -= 1
                out.insert(j, m)
                moved += 1
                continue
        out.append(m)
    return out, moved
