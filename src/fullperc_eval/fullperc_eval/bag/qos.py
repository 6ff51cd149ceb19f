"""QoS profiles of recorded topics: the metadata v9 form (a list of maps with policy names) and rclpy's.

metadata.yaml v9 stores each publisher's offered QoS with policy *names* and durations as {sec, nsec}
(v8 stored the rmw enum integers in a YAML string; :func:`parse_qos` reads both). The recorder turns the
offers it sees (rclpy ``QoSProfile``) into this form (:func:`offered_qos_dict`); the player and the
``--qos-profile-overrides-path`` files go the other way (:func:`rclpy_qos_from_dict`, rclpy imported lazily:
writing and reading bags needs no rclpy).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import yaml

from .errors import BagError

INFINITE_SEC, INFINITE_NSEC = 9223372036, 854775807  # rmw "infinite" duration as rosbag2 writes it

# rmw enum values (v8 metadata) <-> names (v9 metadata), checked against rclpy in the reference notes.
_QOS_ENUMS: dict[str, tuple[str, ...]] = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": ("system_default", "automatic", "manual_by_node", "manual_by_topic", "unknown",
                   "best_available"),
}
_QOS_DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")


def _duration(ns: int | None) -> dict[str, int]:
    if ns is None or ns < 0 or ns >= INFINITE_SEC * 10**9 + INFINITE_NSEC:
        return {"sec": INFINITE_SEC, "nsec": INFINITE_NSEC}
    return {"sec": int(ns) // 10**9, "nsec": int(ns) % 10**9}


def make_qos(history: str | int = "keep_last", depth: int = 10, reliability: str | int = "reliable",
             durability: str | int = "volatile", deadline_ns: int | None = None, lifespan_ns: int | None = None,
             liveliness: str | int = "automatic", liveliness_lease_ns: int | None = None,
             avoid_ros_namespace_conventions: bool = False) -> dict[str, Any]:
    """One offered QoS profile in metadata v9 form; durations None/negative mean infinite."""
    return {
        "history": _qos_name("history", history),
        "depth": int(depth),
        "reliability": _qos_name("reliability", reliability),
        "durability": _qos_name("durability", durability),
        "deadline": _duration(deadline_ns),
        "lifespan": _duration(lifespan_ns),
        "liveliness": _qos_name("liveliness", liveliness),
        "liveliness_lease_duration": _duration(liveliness_lease_ns),
        "avoid_ros_namespace_conventions": bool(avoid_ros_namespace_conventions),
    }


def _qos_name(policy: str, value: str | int) -> str:
    names = _QOS_ENUMS[policy]
    if isinstance(value, bool):
        raise BagError(f"QoS {policy}: {value!r} is not a policy value")
    if isinstance(value, int):
        return names[value] if 0 <= value < len(names) else "unknown"
    v = str(value).strip().lower()
    if v.isdigit():
        return _qos_name(policy, int(v))
    if v not in names:
        raise BagError(f"QoS {policy}: unknown value {value!r} (one of {', '.join(names)})")
    return v


def _parse_duration(d: dict | None) -> int | None:
    d = d or {}
    ns = int(d.get("sec", INFINITE_SEC)) * 10**9 + int(d.get("nsec", INFINITE_NSEC))
    return None if ns >= INFINITE_SEC * 10**9 + INFINITE_NSEC else ns


def parse_qos(value: Any) -> list[dict[str, Any]]:
    """Offered QoS profiles from metadata (v9 list of maps, or v8 YAML string with ints) -> v9 form."""
    if value is None or value == "":
        return []
    if isinstance(value, str):
        try:
            value = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise BagError(f"offered_qos_profiles is not valid YAML: {err}") from None
        if value is None:
            return []
    if not isinstance(value, list):
        raise BagError(f"offered_qos_profiles must be a list, got {type(value).__name__}")
    out = []
    for prof in value:
        if not isinstance(prof, dict):
            raise BagError(f"offered_qos_profiles entry must be a map, got {prof!r}")
        try:
            deadline, lifespan, lease = (_parse_duration(prof.get(k)) for k in _QOS_DURATIONS)
            depth = int(prof.get("depth", 0))
        except (TypeError, ValueError, AttributeError) as err:
            raise BagError(f"offered_qos_profiles entry {prof!r} is malformed ({err})") from None
        out.append(make_qos(prof.get("history", "unknown"), depth,
                            prof.get("reliability", "unknown"), prof.get("durability", "unknown"),
                            deadline, lifespan, prof.get("liveliness", "unknown"), lease,
                            bool(prof.get("avoid_ros_namespace_conventions", False))))
    return out


def qos_yaml(profiles: Sequence[dict[str, Any]]) -> str:
    """The YAML string rosbag2 puts into MCAP channel metadata / sqlite topics.offered_qos_profiles."""
    return yaml.safe_dump(list(profiles), sort_keys=False, default_flow_style=False) if profiles else ""


def rclpy_qos_from_dict(d: dict[str, Any], depth_default: int = 10):
    """rclpy QoSProfile from a v9 profile map / override entry (``ros2 bag`` YAML keys)."""
    from rclpy.duration import Duration
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        LivelinessPolicy,
        QoSProfile,
        ReliabilityPolicy,
    )

    allowed = {"history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
               "liveliness_lease_duration", "avoid_ros_namespace_conventions"}
    unknown = set(d) - allowed
    if unknown:
        raise BagError(f"unknown QoS key(s) {sorted(unknown)} (allowed: {', '.join(sorted(allowed))})")

    def pol(cls, key, default):
        v = d.get(key, default)
        try:
            return cls.get_from_short_key(str(v)) if isinstance(v, str) else cls(int(v))
        except (KeyError, ValueError) as err:
            raise BagError(f"QoS {key}: invalid value {v!r}") from err

    def dur(key):
        v = d.get(key)
        if v is None:
            return Duration()
        sec, nsec = int(v.get("sec", 0)), int(v.get("nsec", 0))
        if sec < 0 or nsec < 0:
            raise BagError(f"QoS {key}: negative duration {v!r}")
        if (sec, nsec) == (INFINITE_SEC, INFINITE_NSEC):
            return Duration(nanoseconds=0)  # infinite offers are requested as "unspecified"
        return Duration(seconds=sec, nanoseconds=nsec)

    history = pol(HistoryPolicy, "history", "keep_last")
    if history == HistoryPolicy.UNKNOWN:  # a publisher cannot be created with UNKNOWN (reference §3.5)
        history = HistoryPolicy.KEEP_LAST
    depth = int(d.get("depth", depth_default) or depth_default)
    if depth < 0:
        raise BagError(f"QoS depth must be >= 0, got {depth}")
    rel = pol(ReliabilityPolicy, "reliability", "reliable")
    durab = pol(DurabilityPolicy, "durability", "volatile")
    live = pol(LivelinessPolicy, "liveliness", "system_default")
    if rel == ReliabilityPolicy.UNKNOWN:
        rel = ReliabilityPolicy.RELIABLE
    if durab == DurabilityPolicy.UNKNOWN:
        durab = DurabilityPolicy.VOLATILE
    if live == LivelinessPolicy.UNKNOWN:
        live = LivelinessPolicy.SYSTEM_DEFAULT
    return QoSProfile(history=history, depth=depth, reliability=rel, durability=durab, deadline=dur("deadline"),
                      lifespan=dur("lifespan"), liveliness=live,
                      liveliness_lease_duration=dur("liveliness_lease_duration"),
                      avoid_ros_namespace_conventions=bool(d.get("avoid_ros_namespace_conventions", False)))


def offered_qos_dict(q) -> dict[str, Any]:
    """rclpy QoSProfile (from get_publishers_info_by_topic) -> metadata v9 profile map."""
    return make_qos(int(q.history), int(q.depth), int(q.reliability), int(q.durability),
                           q.deadline.nanoseconds, q.lifespan.nanoseconds, int(q.liveliness),
                           q.liveliness_lease_duration.nanoseconds, bool(q.avoid_ros_namespace_conventions))
