"""fusion_node's ROS endpoints: the QoS of its topics, publishers and subscriptions that take QoS overrides and say
when a peer's QoS is incompatible, and the run-time parameter callback.

Why its own module: fusion_node is the node's I/O loop; how an endpoint is made (QoS, overrides, events) and how a
run-time set is judged are decisions of their own, said once here for every topic of the node (issue 39).

QoS (:mod:`fusion_interface` says why): subscriptions ``qos_reliability`` (default ``auto``: reliable, remade best
effort when a best-effort publisher appears on the topic -- :class:`InputSubscription`), publishers reliable; depth
``qos_depth``, keep last. Each topic publisher and subscription is
made with ``QoSOverridingOptions.with_default_policies()``, so ``qos_overrides.<topic>.<publisher|subscription>.
<history|depth|reliability>`` parameters (``<topic>`` the *resolved* name: ``/or1/omc/tool/pose`` under ``/or1``)
replace the profile at start; rclpy declares them read-only. /tf, /tf_static and /diagnostics keep the fixed QoS of
fullperc_common's helpers: tf2's listeners and diagnostic_aggregator expect exactly those.

Incompatible QoS: a publisher and a subscription whose QoS cannot match never exchange a sample, and DDS says so only
through an event. Every endpoint registers ``incompatible_qos`` and logs one WARN per event naming the resolved
topic, the side, the policy and the remedy (a reliable subscription cannot be served by a best-effort publisher).

Run-time parameters (:func:`fusion_core.check_live`): every parameter of the node is declared read-only -- rclpy then
refuses a run-time set with "Trying to set a read-only parameter: <name>." before any callback -- except those of
:data:`~fusion_core.LIVE_PARAMS`, which :func:`live_parameters` validates with the start-up checks and applies, or
refuses naming the parameter and the check. Parameters that are not the node's (``use_sim_time``) pass through.
"""

from __future__ import annotations

import copy
import inspect
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from fullperc_common.drain import take_queued
from fullperc_common.executor_choice import adapt_subscription
from fullperc_common.params import ParameterError, declare
from fullperc_fusion.fusion_config import BY_NAME, spec
from fullperc_fusion.fusion_core import LIVE_PARAMS, FusionCore
from fullperc_fusion.input_cdr import bodies_from_cdr, pose_from_cdr, quality_from_cdr


def input_qos(vals: dict[str, Any]) -> QoSProfile:
    """The subscriptions' profile: ``qos_reliability`` (auto | best_effort | reliable; auto starts reliable), keep last
    ``qos_depth``."""
    return QoSProfile(depth=vals["qos_depth"], history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if vals["qos_reliability"] in ("reliable", "auto")
                      else ReliabilityPolicy.BEST_EFFORT)


def output_qos(vals: dict[str, Any]) -> QoSProfile:
    """The publishers' profile: reliable (matches reliable and best-effort readers), keep last ``qos_depth``."""
    return QoSProfile(depth=vals["qos_depth"], history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


def policy_name(kind: Any) -> str:
    """rclpy's policy kind (an int or QoSPolicyKind) as its name: ``RELIABILITY``, ``DURABILITY`` ..."""
    try:
        return QoSPolicyKind(int(kind)).name
    except (ValueError, TypeError):
        return str(kind)


def incompatible_line(topic: str, side: str, policy: str, total: int) -> str:
    """The WARN of an incompatible-QoS event on ``topic`` for this node's ``side`` (publisher | subscription)."""
    other = "subscription" if side == "publisher" else "publisher"
    hint = ""
    if policy == "RELIABILITY":
        hint = ("; a best-effort publisher cannot serve a reliable subscription: use qos_reliability: best_effort or "
                f"qos_overrides.{topic}.subscription.reliability" if side == "subscription" else
                "; a reliable subscription needs a reliable publisher: qos_overrides."
                f"{topic}.publisher.reliability")
    return (f"incompatible QoS on {topic}: this node's {side} and a {other} disagree on {policy} ({total} such "
            f"{other}s so far); no sample flows between them{hint}")


class InputSubscription:
    """An input subscription that ``qos_reliability: auto`` can remake best effort: everything else (``handle``,
    ``msg_type``, ``topic_name`` ...) is the current rclpy subscription's, so the node's takes, the guard's drains and
    rclpy see one object whichever profile it has now."""

    def __init__(self, sub: Any, callback: Callable) -> None:
        self.sub = sub
        self.callback = callback
        self.switched = False

    def __getattr__(self, name: str) -> Any:
        return getattr(self.sub, name)


def switch_line(topic: str) -> str:
    """The WARN of ``qos_reliability: auto`` remaking the subscription of ``topic`` best effort."""
    return (f"a best-effort publisher on {topic}: its subscription is now best effort (qos_reliability: auto), which "
            "every publisher matches; samples this node's reader misses are no longer re-sent by reliable "
            "publishers -- make the driver reliable, or set qos_reliability: best_effort to start that way")


class Endpoints:
    """Makes fusion_node's topic publishers and subscriptions (module docstring): ``node.create_publisher`` /
    ``create_subscription`` with the node's profiles, QoS overrides and the incompatible-QoS warning. Each endpoint
    gets a new profile: rclpy applies the ``qos_overrides`` of a topic to the profile object it is given, so one shared
    profile would carry one topic's override to every endpoint made after it."""

    def __init__(self, node: Any, vals: dict[str, Any]) -> None:
        self.node = node
        self.vals = vals
        self.auto = vals["qos_reliability"] == "auto"
        self._to_switch: list[InputSubscription] = []   # auto: remade best effort at the next switch_pending()
        # the parameters the user gave (command line, params file): an explicit qos_overrides reliability is kept.
        # rclpy declares every qos_overrides row with the profile's value, so has_parameter cannot tell.
        self._given = set(getattr(node, "_parameter_overrides", {}) or {})

    def _warn(self, topic: str, side: str, info: Any, wrapped: InputSubscription | None = None) -> None:
        policy = policy_name(info.last_policy_kind)
        if (wrapped is not None and policy == "RELIABILITY" and not wrapped.switched and wrapped not in self._to_switch
                and f"qos_overrides.{topic}.subscription.reliability" not in self._given):
            self._to_switch.append(wrapped)   # not here: this callback belongs to the subscription to be destroyed
            return
        self.node.get_logger().warning(incompatible_line(topic, side, policy, int(info.total_count)))

    def switch_pending(self) -> list[str]:
        """``auto``: remake best effort each input subscription a best-effort publisher was incompatible with (an
        explicit ``qos_overrides`` reliability is kept and only warned about). What the old reader still queued is
        taken first and handed to the callback (nothing received is lost); the new reader's profile is the old one
        (overrides included) but best effort. Returns the topics switched (one WARN each)."""
        done = []
        while self._to_switch:
            w = self._to_switch.pop(0)
            old, topic = w.sub, w.sub.topic_name
            queued = take_queued(old, 1_000_000)
            qos = copy.copy(old.qos_profile)
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
            self.node.destroy_subscription(old)
            w.sub = self.node.create_subscription(
                old.msg_type, topic, w.callback, qos, raw=bool(getattr(old, "raw", False)),
                event_callbacks=SubscriptionEventCallbacks(incompatible_qos=partial(self._warn, topic, "subscription")))
            adapt_subscription(self.node, w.sub)   # on the EventsExecutor, as the node's other (msg, info) callbacks
            w.switched = True
            wants_info = len(inspect.signature(w.callback).parameters) > 1
            for m in queued:
                if wants_info:
                    w.callback(m, None)
                else:
                    w.callback(m)
            self.node.get_logger().warning(switch_line(topic))
            done.append(topic)
        return done

    def publisher(self, msg_type: Any, topic: str) -> Any:
        name = self.node.resolve_topic_name(topic)
        return self.node.create_publisher(
            msg_type, topic, output_qos(self.vals), qos_overriding_options=QoSOverridingOptions.with_default_policies(),
            event_callbacks=PublisherEventCallbacks(incompatible_qos=partial(self._warn, name, "publisher")))

    def subscription(self, msg_type: Any, topic: str, callback: Callable, raw: bool = False) -> Any:
        """An input subscription; with ``auto`` an :class:`InputSubscription` that :meth:`switch_pending` may remake.
        ``raw``: the callback gets the serialized message (bytes), and so do takes of its queue."""
        name = self.node.resolve_topic_name(topic)
        wrapped = InputSubscription(None, callback) if self.auto else None
        sub = self.node.create_subscription(   # a profile of its own: rclpy writes a topic's overrides into it
            msg_type, topic, callback, input_qos(self.vals), raw=raw,
            qos_overriding_options=QoSOverridingOptions.with_default_policies(),
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=partial(self._warn, name, "subscription",
                                                                                wrapped=wrapped)))
        if wrapped is None or sub.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
            return sub
        wrapped.sub = sub
        return wrapped


def input_sample(dev: str, body: str, data: bytes) -> tuple:
    """(stamp_ns, device, body, p, q) of one serialized PoseStamped of an input subscription (made ``raw``): an item
    of fusion_node's input batch (``FusionCore.batch_key``), read by :mod:`.input_cdr`."""
    t_ns, p, q = pose_from_cdr(data)
    return t_ns, dev, body, p, q


def quality_record(key: tuple[str, str], data: bytes) -> tuple:
    """FusionCore.quality's arguments for one serialized TrackingQuality of ``key`` (device tag, body), read by
    :mod:`.input_cdr`: (key, frame_number, stamp_ns, visible, fit_error, markers_used)."""
    t_ns, visible, fit_error, number, markers = quality_from_cdr(data)
    return key, number, t_ns, visible, fit_error, float(markers)


class FrameReader:
    """Reads the TrackedBodies messages of ``inputs: frames`` (:mod:`.input_cdr`) into what the per-body topics give:
    a call returns the frame's input-batch items (as :func:`input_sample`'s) of the visible bodies a target uses
    (``pose_keys``: FusionCore.topic_of's), and keeps the quality records of the bodies whose TrackingQuality the core
    reads (``quality_keys``: FusionCore.quality_topics') for :meth:`take_qualities` -- the node hands them to the core
    before the batch's poses, after the publisher check. Other bodies of the frame are skipped."""

    def __init__(self, pose_keys: Iterable[tuple[str, str]], quality_keys: Iterable[tuple[str, str]]) -> None:
        self.pose_keys, self.quality_keys = set(pose_keys), set(quality_keys)
        self._qualities: list[tuple] = []

    def __call__(self, dev: str, _body: str, data: bytes) -> list[tuple]:
        t_ns, bodies = bodies_from_cdr(data)
        out = []
        for name, visible, v, fit, number, markers in bodies:
            if (dev, name) in self.quality_keys:   # the arguments of FusionCore.quality
                self._qualities.append(((dev, name), number, t_ns, visible, fit, float(markers)))
            if visible and (dev, name) in self.pose_keys:
                out.append((t_ns, dev, name, np.array(v[:3]), np.array(v[3:])))
        return out

    def take_qualities(self) -> list[tuple]:
        """The quality records read since the last call, in the order read."""
        got, self._qualities = self._qualities, []
        return got


class Inputs:
    """fusion_node's input subscriptions (made ``raw``: serialized messages, read by :mod:`.input_cdr`) and their
    reading. ``per_body`` (``inputs``): a PoseStamped subscription per pose topic of the core and a TrackingQuality one
    per quality topic (``quality``: key -> subscription, the node's ``on_quality``); ``frames``: one TrackedBodies
    subscription per source, whose frames give both (:class:`FrameReader`). ``subs``: (device, body -- '' for a
    frames topic --, subscription) of the inputs that call ``on_input(device, body, data, info)``; ``sub_of``: every
    input topic -> its subscription."""

    def __init__(self, ep: Endpoints, core: FusionCore, inputs: str, on_input: Callable, on_quality: Callable) -> None:
        from geometry_msgs.msg import PoseStamped

        from fullperc_msgs.msg import TrackedBodies, TrackingQuality

        frames = inputs == "frames"
        self.frames = FrameReader(core.topic_of, core.quality_topics) if frames else None
        self._qualities: list[tuple] = []
        self.quality_topic = core.quality_topics
        self.quality = {} if frames else {
            k: ep.subscription(TrackingQuality, t, partial(on_quality, k), raw=True)
            for k, t in core.quality_topics.items()}
        topics = {t: (d, "" if frames else b) for d, b, t in core.pose_topics()}   # topic -> (device, body)
        self.topic = {v: t for t, v in topics.items()}
        self.subs = [(d, b, ep.subscription(TrackedBodies if frames else PoseStamped, t, partial(on_input, d, b),
                                            raw=True)) for t, (d, b) in topics.items()]
        self.sub_of = {t: s for (*_, s), t in zip(self.subs, topics, strict=True)} | {
            core.quality_topics[k]: s for k, s in self.quality.items()}

    def read(self, dev: str, body: str, data: bytes) -> list[tuple]:
        """The input-batch items of one message of ``(dev, body)``'s subscription."""
        return self.frames(dev, body, data) if self.frames is not None else [input_sample(dev, body, data)]

    def take(self, dev: str | None, body: str, data: bytes, most: int) -> tuple[list[tuple], set[str]]:
        """The items of ``data`` (a message of ``(dev, body)``; ``dev`` None: none) and of everything queued on every
        input (at most ``most`` per subscription), unsorted, and the topics they came from. Per body, the quality
        topics' queues are taken too (:meth:`take_qualities`): a node behind its inputs holds a frame's quality record
        beside its pose, and fusing the pose first would leave the record to a later callback -- too late once the
        item has left the history (the sample then fused without its model covariance)."""
        batch, topics = ([], set()) if dev is None else (self.read(dev, body, data), {self.topic[(dev, body)]})
        for d, b, sub in self.subs:
            if msgs := take_queued(sub, most):
                topics.add(self.topic[(d, b)])
                batch.extend(x for m in msgs for x in self.read(d, b, m))
        for key, sub in self.quality.items():
            if msgs := take_queued(sub, most):
                topics.add(self.quality_topic[key])
                self._qualities.extend(quality_record(key, m) for m in msgs)
        return batch, topics

    def take_qualities(self) -> list[tuple]:
        """The quality records taken since the last call, in the order taken (FusionCore.quality's arguments): the
        frames' (``frames``), or those :meth:`take` took from the quality topics' queues (``per_body``)."""
        got, self._qualities = self._qualities, []
        return got + self.frames.take_qualities() if self.frames is not None else got


# ROS type of a parameter declared without a default value (optional ones, empty lists)
_ROS_TYPES = {"str_list": Parameter.Type.STRING_ARRAY, "pose7": Parameter.Type.DOUBLE_ARRAY,
              "str": Parameter.Type.STRING, "float": Parameter.Type.DOUBLE, "bool": Parameter.Type.BOOL}


def declare_row(node: Any, name: str, default: Any) -> Any:
    """fusion_config's getter for the node: declare ``name`` once (``params.declare``, the row's description),
    read-only unless it is one of :data:`~fusion_core.LIVE_PARAMS`, and return its value."""
    if node.has_parameter(name):
        return node.get_parameter(name).value
    p = spec(name)
    if default is None or (isinstance(default, list) and not default):
        default = _ROS_TYPES[p.kind]
    return declare(node, name, default, description=p.description, read_only=name not in LIVE_PARAMS)


def live_parameters(core: FusionCore, applied: Callable[[dict[str, Any]], None],
                    log: Callable[[str], None]) -> Callable[[list], SetParametersResult]:
    """The node's ``add_on_set_parameters_callback``: a set of the node's live parameters is checked and applied by
    ``core.apply_live`` (then ``applied(new values)`` for what the node itself holds, e.g. ``status_rate``) or refused
    with the check's message; a parameter of the table that is not live is refused as read-only (rclpy refuses those
    first, by their descriptor); any other name (``use_sim_time``, rclpy's own) passes."""
    def on_set(params: list) -> SetParametersResult:
        ours = {p.name: p.value for p in params if p.name in BY_NAME or p.name in core.vals}
        if not ours:
            return SetParametersResult(successful=True)
        try:
            new = core.apply_live(ours)
        except ParameterError as e:
            return SetParametersResult(successful=False, reason=str(e))
        applied(new)
        log("run-time parameters applied: " + ", ".join(f"{k} = {new[k]!r}" for k in ours))
        return SetParametersResult(successful=True)
    return on_set
