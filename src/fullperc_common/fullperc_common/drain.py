"""Take the messages already queued on subscriptions, without one executor round per message.

rclpy's executor spends ~130 µs of Python per callback (measured in bag_record); the take itself costs a
few µs. A node fed by several high-rate topics (fusion: OMC 240 Hz + OTS 400 Hz, each with two bodies)
would spend most of a core in the executor, fall behind, and -- worse -- deliver the topics' backlogs
round-robin, so newer samples of one topic overtake older ones of another. Draining every input
subscription in one callback and sorting by stamp fixes both.

This uses ``Subscription.handle.take_message``, the call rclpy 7.1's executor itself makes; if rclpy's
internals change, :func:`take_queued` returns nothing and callers keep working one message per callback.
"""

from __future__ import annotations

from typing import Any


def take_one(sub, raw: bool = False) -> tuple[Any, dict] | None:
    """The oldest message waiting on ``sub`` as (message, message info), or None when its queue is empty; the
    message serialized (bytes) with ``raw``. With :func:`take_queued`, the place that knows rclpy's take
    (``Subscription.handle``, rclpy 7.1's ``_take_subscription``): raises AttributeError or TypeError if that moved,
    and each caller decides how to go on (:func:`take_queued`; ``fullperc_eval.bag.record``)."""
    handle = sub.handle
    with handle:
        return handle.take_message(sub.msg_type, raw)


def take_queued(sub, limit: int = 1000, raw: bool | None = None) -> list[Any]:
    """Up to ``limit`` messages waiting on ``sub`` (oldest first); [] if unsupported. ``raw``: serialized (bytes)
    or deserialized; by default what the subscription's callback gets (its ``raw``)."""
    out: list[Any] = []
    handle = getattr(sub, "handle", None)
    if handle is None:
        return out
    if raw is None:
        raw = bool(getattr(sub, "raw", False))
    try:   # take_one's call, its lookups made once: fusion_node drains every input per callback, most of them empty
        msg_type = sub.msg_type
        with handle:
            take = handle.take_message
            for _ in range(limit):
                taken = take(msg_type, raw)
                if taken is None:
                    break
                out.append(taken[0])
    except (AttributeError, TypeError):
        return out
    return out
