"""Publisher identity on fusion_node's inputs: per input topic, who may publish on it, and whether it is open.

Why: any process on the DDS domain can publish on ``/omc/tool/pose``, and fusion_node fused whatever arrived. A second
node publishing poses 20 mm off moved the fused pose by up to 615 mm while the Vega did not see the tool, and
/diagnostics said nothing (issue 40). A misconfigured second driver (two OR PCs started the same launch) does the same.

What can be known: rclpy (Jazzy) gives no publisher per message -- its message info holds only timestamps -- but
discovery lists every topic's publishers with their node's name and namespace and the endpoint's GID
(``Node.get_publishers_info_by_topic``). So the decision is per topic, not per message:

* identity is the publisher's fully qualified node name (namespace + name). The GID is recorded for the messages
  only, so a restarted legitimate driver (new GID, same node name) is accepted again;
* accepted: with ``publishers.allow`` the nodes it names (``/omc_driver``) or the nodes under a namespace it names
  (``/or1/``); without it, the first node seen publishing on each topic, alone (two or more at the first look: none
  is taken until one is alone; a node whose name discovery does not know yet is never taken);
* **fail closed**: a topic with any publisher that is not accepted -- including two processes publishing under the
  one accepted name (a restarted driver whose old endpoint has not expired yet, or two drivers started with the same
  name: they cannot be told apart) -- is *closed*: every sample arriving on it is dropped and counted, since nothing
  says which of its publishers sent it. The target's inputs on it stop (never a pose mixed from two sources), its
  status is ERROR naming topic, node and GID. The topic stays closed until its set of publishers is acceptable
  again; then what its reader queued meanwhile is discarded too (:meth:`InputGuard.settle`: the samples received
  while it was closed may be the last of the intruder's), and it opens;
* a publisher discovery has not named yet (``_NODE_NAME_UNKNOWN_``: its first samples can come tens to hundreds of
  ms before its name) is not accepted either, but its topic is *held* rather than closed: nothing is fused, the
  samples are kept (by the core), and no ERROR is raised yet. Named and accepted (with no other change) -> the held
  samples are used, so a driver's first samples are not lost at every start; named and refused, gone, or not named
  within :data:`UNNAMED_GRACE_S` (a DDS writer outside ROS never is) -> they are dropped and the topic is closed as
  above (or discarded and opened, when only accepted publishers are left).

How fusion_node feeds it: every input topic (pose and quality) is read every :data:`CHECK_PERIOD_S`, and each input
callback counts the publishers of the topics in its batch before fusing any sample of it, re-reading a topic whose
count changed or whose publisher has no name yet. The count is of the writers matched to the topic's reader
(``Subscription.get_publisher_count``): a publisher's samples reach the reader only once it is matched, so a new one
is counted before its first sample is taken; ~1 us per topic against ~5 us for the graph's ``count_publishers``, in
every callback. A topic no check has looked at yet is open (the core's unit tests and offline use have no graph);
fusion_node checks a topic before it fuses its first sample. ROS-free; every call takes ``now`` (monotonic seconds).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

ERROR, WARN = 2, 1   # diagnostic_msgs levels
UNKNOWN = ("_NODE_NAME_UNKNOWN_", "_NODE_NAMESPACE_UNKNOWN_")   # rmw_dds_common's names before discovery knows them
CHECK_PERIOD_S = 0.25   # [s] fusion_node re-reads every input topic's publishers: a second one is named within 1 s
UNNAMED_GRACE_S = 1.0   # [s] a publisher discovery does not name within this is refused (a DDS writer outside ROS)
PREFIX_HEX = 24   # hex digits of the DDS GUID prefix (12 bytes) at the start of a GID: one per process (participant)

Log = tuple[str, str]                   # (info | warning | error, line)
Publisher = tuple[str, str]             # (fully qualified node name, GID as hex)


def node_fqn(namespace: str, name: str) -> str:
    """The fully qualified node name of rclpy's (namespace, name): ``/`` + ``n`` -> ``/n``, ``/or1`` -> ``/or1/n``."""
    return f"{namespace.rstrip('/')}/{name}"


def gid_hex(gid: Iterable[int]) -> str:
    """An endpoint GID (rclpy's list of byte values) as a hex string, the form every message names."""
    return bytes(gid).hex()


def is_unknown(fqn: str) -> bool:
    """True for a name discovery does not know yet (rmw's placeholders), or one that is not fully qualified."""
    return not fqn.startswith("/") or any(u in fqn.split("/") for u in UNKNOWN)


def allowed(allow: Sequence[str], fqn: str) -> bool:
    """``fqn`` is named by ``allow``: equal to an entry, or under an entry ending in ``/`` (a namespace)."""
    return any(fqn == a or (a.endswith("/") and fqn.startswith(a)) for a in allow)


def service_callers_line(service: str, clients: Sequence[str]) -> str:
    """The log line of a service call: who could have called (rclpy gives a service no caller identity)."""
    who = ", ".join(f"'{c}'" for c in clients) or "none (a client that is gone already, or not yet discovered)"
    return (f"{service} called; rclpy gives no caller identity -- nodes with a client of {service}: {who}")


@dataclass
class TopicState:
    """What the guard knows of one input topic."""

    accepted: str | None = None                           # the first node seen (no allow-list)
    publishers: list[Publisher] = field(default_factory=list)
    refused: list[tuple[str, str, str]] = field(default_factory=list)   # (node, GID, why) not accepted
    open: bool = True
    draining: bool = False                                # acceptable again, its queue not discarded yet
    dropped: int = 0                                      # samples dropped since start
    closed_at: float | None = None
    dropped_at_close: int = 0
    checked_at: float | None = None                       # the last check
    detect_s: float | None = None                         # the check gap when it last stopped being used
    reopened: tuple[float, str] | None = None             # when it last opened again, and the line said then
    gids: dict[str, set[str]] = field(default_factory=dict)   # accepted node -> every GID it published with
    held_since: float | None = None                       # samples held: publishers discovery has not named yet
    held_gids: set[str] = field(default_factory=set)      # their GIDs
    hold_gap: float | None = None                         # the check gap when the hold began (nothing used since)
    release: bool = False                                 # they were named and accepted: the held samples count


class InputGuard:
    """The accepted publishers and the open/closed verdict of every input topic (module docstring). ``allow``: the
    ``publishers.allow`` parameter (empty: first node seen); ``hold_s``: how long a WARN follows a reopening."""

    def __init__(self, topics: Iterable[str], allow: Sequence[str] = (), hold_s: float = 3.0) -> None:
        self.allow = tuple(allow)
        self.hold_s = hold_s
        self.topics: dict[str, TopicState] = {t: TopicState() for t in topics}

    # ---- the graph ------------------------------------------------------------------------------------------------
    def update(self, topic: str, publishers: Sequence[Publisher], now: float) -> list[Log]:
        """The publishers discovery lists on ``topic`` now; log lines for what changed (accepted, closed, open)."""
        st = self.topics[topic]
        logs: list[Log] = []
        pubs = sorted(set(publishers))
        prev_check, st.checked_at = st.checked_at, now
        if not self.allow and st.accepted is None:
            names = {n for n, _ in pubs}
            if len(names) == 1 and not is_unknown(next(iter(names))):
                st.accepted = next(iter(names))
                logs.append(("info", f"input {topic}: accepting publisher '{st.accepted}' (the first node seen "
                                      f"publishing on it; GID {pubs[0][1]})"))
        refused = self._refused(st, pubs)
        new = [(n, g) for n, g in pubs if self._accepts(st, n) and st.gids.get(n) and g not in st.gids[n]]
        if new and not refused:
            logs.append(("info", f"input {topic}: accepted publisher with a new GID (a restarted driver): "
                                 + ", ".join(f"'{n}' GID {g}" for n, g in new)))
        for n, g in pubs:
            if self._accepts(st, n):
                st.gids.setdefault(n, set()).add(g)
        st.publishers = pubs
        unnamed = {g for n, g, _ in refused if is_unknown(n)}
        held = st.held_since is not None
        if refused and len(unnamed) == len(refused) and (st.open or held) \
                and now - (st.held_since or now) <= UNNAMED_GRACE_S:   # only nameless ones: hold, not an error yet
            if not held:   # the topic stops being used here: this check's gap is the detection's if it closes
                st.hold_gap = None if prev_check is None else now - prev_check
            st.open, st.held_gids = False, (st.held_gids if held else set()) | unnamed
            st.held_since = st.held_since if held else now
            st.refused = refused
            return logs
        if held:   # named now (or gone, or the grace passed): release what was held, or close as any other
            st.held_since, st.closed_at, st.dropped_at_close = None, st.held_since, st.dropped
            st.release = not refused and st.held_gids <= {g for _, g in pubs}
            st.open = st.release
            if st.release:
                logs.append(("info", f"input {topic}: publishers named now, accepted: "
                                     + ", ".join(f"'{n}'" for n in dict.fromkeys(n for n, _ in pubs))
                                     + "; the samples held meanwhile are used"))
        if refused and (refused != st.refused or held):
            if st.open or st.draining or held:
                st.open, st.draining, st.closed_at, st.dropped_at_close = False, False, now, st.dropped
                st.detect_s = st.hold_gap if held else None if prev_check is None else now - prev_check
            logs.append(("error", self.closed_line(topic, st, refused)))
        elif not refused and not st.open and not st.draining:
            st.draining = True
        st.refused = refused
        return logs

    def touch(self, topic: str, now: float) -> None:
        """A check of ``topic`` that found nothing changed (its publisher count): the detection gap starts anew."""
        self.topics[topic].checked_at = now

    def _accepts(self, st: TopicState, fqn: str) -> bool:
        if is_unknown(fqn):
            return False
        return allowed(self.allow, fqn) if self.allow else fqn == st.accepted

    def _refused(self, st: TopicState, pubs: list[Publisher]) -> list[tuple[str, str, str]]:
        """(node, GID, why) of every publisher that closes the topic."""
        out = []
        procs: dict[str, set[str]] = {}
        for n, g in pubs:
            if not self._accepts(st, n):
                why = ("its node's name is not discovered yet" if is_unknown(n) else
                       "not in publishers.allow" if self.allow else
                       "several nodes at the first look: none taken" if st.accepted is None else
                       f"the accepted publisher is '{st.accepted}'")
                out.append((n, g, why))
            else:
                procs.setdefault(n, set()).add(g[:PREFIX_HEX])
        for n, g in pubs:
            if len(procs.get(n, ())) > 1:
                out.append((n, g, "the same node name from several processes (a restarted driver whose old "
                                  "endpoint has not expired yet, or two drivers of one name)"))
        return out

    @staticmethod
    def closed_line(topic: str, st: TopicState, refused: list[tuple[str, str, str]]) -> str:
        who = "; ".join(f"'{n}' GID {g} ({why})" for n, g, why in refused)
        return (f"input {topic} closed: publisher {who}; every sample on it is dropped until its publishers are "
                "accepted ones only (no publisher per message in rclpy: nothing it sends may reach the fused pose)")

    def settle(self, now: float) -> list[Log]:
        """Open every topic that became acceptable again, once the caller discarded (:meth:`drop`) what its reader
        had queued: those samples were received while it was closed. Returns the log lines."""
        logs: list[Log] = []
        for topic, st in self.topics.items():
            if st.draining:
                st.open, st.draining = True, False
                line = (f"input {topic} open again after {now - (st.closed_at or now):.1f} s closed: "
                        f"{st.dropped - st.dropped_at_close} samples dropped meanwhile; publishers "
                        + ", ".join(f"'{n}'" for n in dict.fromkeys(n for n, _ in st.publishers)))
                st.reopened = (now, line)
                logs.append(("warning", line))
        return logs

    def unresolved(self, topic: str) -> bool:
        """``topic`` is closed by a publisher whose node name discovery does not know yet: worth re-reading at once
        (the name follows within milliseconds to a few hundred), not only when the publisher count changes."""
        st = self.topics.get(topic)
        return st is not None and any(is_unknown(n) for n, _, _ in st.refused)

    def holding(self, topic: str) -> bool:
        """``topic``'s samples are held (not fused, not dropped yet): a publisher on it has no name yet."""
        st = self.topics.get(topic)
        return st is not None and st.held_since is not None

    def take_release(self, topic: str) -> bool:
        """True once after the held samples of ``topic`` turned out to be from accepted publishers only."""
        st = self.topics[topic]
        release, st.release = st.release, False
        return release

    def draining(self) -> list[str]:
        """The topics whose reader queue the caller must discard before :meth:`settle` opens them."""
        return [t for t, st in self.topics.items() if st.draining]

    # ---- the samples ----------------------------------------------------------------------------------------------
    def is_open(self, topic: str) -> bool:
        """Whether a sample of ``topic`` may be fused now (unknown topics: yes, the guard is not about them)."""
        st = self.topics.get(topic)
        return st is None or st.open

    def drop(self, topic: str, n: int = 1) -> None:
        """``n`` samples of ``topic`` dropped (closed, or discarded at reopening)."""
        self.topics[topic].dropped += n

    @property
    def dropped(self) -> dict[str, int]:
        """Samples dropped per topic since start."""
        return {t: st.dropped for t, st in self.topics.items()}

    # ---- diagnostics ----------------------------------------------------------------------------------------------
    def status(self, topics: Iterable[str], now: float) -> tuple[int, list[str], dict]:
        """(level, messages, values) of the inputs ``topics`` of one target: ERROR while one is closed (topic, node,
        GID named), WARN for ``hold_s`` after one opened again; values: the closed topics, the samples dropped
        (total and per topic), ``input_detect_ms`` (the gap between the check that saw the last closing and the one
        before it: how late the node can have seen a change its graph already knew)."""
        level, msgs = 0, []
        closed, held, by_topic, detect = [], [], {}, None
        for t in topics:
            st = self.topics[t]
            if st.dropped:
                by_topic[t] = st.dropped
            if st.detect_s is not None:
                detect = st.detect_s if detect is None else max(detect, st.detect_s)
            if st.held_since is not None:
                held.append(t)
            elif not st.open:
                closed.append(t)
                level = ERROR
                msgs.append(self.closed_line(t, st, st.refused) + f" ({st.dropped - st.dropped_at_close} "
                            f"dropped, closed {now - (st.closed_at or now):.1f} s)" if st.refused else
                            f"input {t} closed: its publishers are acceptable again, its queue is being discarded")
            elif st.reopened is not None and now - st.reopened[0] < self.hold_s:
                level = max(level, WARN)
                msgs.append(st.reopened[1])
        values = {"inputs_closed": ", ".join(closed) or "none", "inputs_held": ", ".join(held) or "none",
                  "input_dropped": sum(by_topic.values()),
                  "input_dropped_by_topic": "; ".join(f"{t}: {n}" for t, n in by_topic.items()) or "none",
                  "input_detect_ms": None if detect is None else round(1e3 * detect, 1)}
        return level, msgs, values
