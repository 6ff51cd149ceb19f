"""fusion_node: driver poses in, fused target poses in ``base`` out. A thin ROS wrapper of :class:`FusionCore`.

Names (:mod:`fusion_interface`): every topic below is relative -- the names shown are those of the default namespace,
``-r __ns:=/or1`` puts every input and output under ``/or1`` -- but ``/tf``, ``/tf_static`` and ``/diagnostics``;
frames are ``frames.base`` / ``frames.omc`` / ``frames.ots`` / ``<target>.frame`` (defaults below). QoS, overrides,
incompatible-QoS warnings and the run-time parameters: :mod:`fusion_endpoints`.

Subscribes (per target, shared between targets where the topic is the same; prefixes and further local sources
from ``sources``, :mod:`sources`):
  omc/<body>/pose  for the target's OMC body, the base body and the OTS rig body (PoseStamped, ``omc``)
  ots/<tool>/pose  for the target's OTS tool and the base tool (PoseStamped, ``ots``)
  <prefix>/<tool>/pose  of every further local source: the target's tool and its base tool
  fullperc/<target>/region (fullperc_msgs/Region, optional: fills FusionStatus.region)
  with ``inputs: frames`` instead of the per-body pose and quality topics: <prefix>/bodies (TrackedBodies,
  one message per device frame with every body's pose and quality, as fullperc's drivers publish it)
Publishes:
  fullperc/<target>/pose      PoseStamped, frame ``base``, stamp = acquisition stamp of the newest sample
  fullperc/<target>/pose_cov  PoseWithCovarianceStamped (same stamp/frame)
  fullperc/<target>/status    fullperc_msgs/FusionStatus
  fullperc/<target>/velocity  TwistWithCovarianceStamped of the primary filter (``publish_velocity``; fusion_publish)
  fullperc/<target>/<filter>/pose and .../status  for every filter listed in ``filters`` (side by side; with
                               ``processing: arrival`` fused when an item leaves the history: final, ``history`` late)
  fullperc/<target>/final     PoseStamped (``processing: arrival``, ``publish_final``): the primary filter's estimate
                               of each item once it left the history -- final, equal to the offline evaluator's
  fullperc/poses               fullperc_msgs/FusedPoseArray: per wake-up every target's newest pose_cov (publish_poses)
  /tf                          tf2_msgs/TFMessage ``base`` -> ``<target>`` per fused output of the primary filter
                               (stamp = fused stamp; ``tf.rate``: at most that many per s of stamps), every
                               target's in one message per wake-up; ``tf.enabled``
  /tf_static                   (transient local) ``omc`` -> ``base`` (T_omc_base) and ``base`` -> ``ots``
                               (T_base_ots; not with ``local_chain: tracked``, where the OTS moves) once known, sent
                               again when they change (~/initialize, ~/calibrate, re-calibration); ``base`` ->
                               ``diana_base`` when ``tf.diana_base`` is given (fusion_node has no other source of it)
  /diagnostics                 one status per target: initialization, rejected input and why, silent sources,
                               and the alarms of fusion_health (WARN: hop rate, implausible bias of the global
                               source; ERROR: every sample of a source rejected), naming target and source;
                               WARN when the link monitor sees a bump of the static link (link and size named);
                               overload: queue_depth(_max), lag_ms / lag_max_ms (node clock - stamp of the newest
                               fused sample); per input wake-up, callback_delay / wakeup / received_to_published
                               _p50_ms, _p99_ms, _max_ms (reception -> callback -> published; fullperc_common.latency)
                               (the _max / _min / _pNN figures over every input callback since the last published
                               report), <omc|ots>_frames_lost / _samples_lost of the target's sources (TrackingQuality
                               frame-number gaps; visible frames whose pose never came); WARN when the lag stayed
                               above ``lag_warn`` for a whole period, or samples were lost (held problem_hold)
Services:
  ~/initialize (std_srvs/Trigger) re-estimates the static links of every target from the next samples
               (``static_links``: average of init_samples, or calibrate over calibration.duration).
  ~/calibrate  (std_srvs/Trigger) collects calibration.duration s of sightings (keep the setup still), estimates
               the links the chain needs (frame_chain.links_needed) with the robust calibration, and answers when
               done: on success the links of every target are swapped in one step, calibration.output is written
               first (if set), and the answer is success + a summary; a refusal (a body moved, too few sightings)
               answers success=false + the reason and keeps the old links. The node keeps fusing meanwhile.

Parameters: the table of :mod:`fullperc_fusion.fusion_config` (names, defaults, checks, units; the same
mapping the offline evaluator uses); config/fusion.yaml lists every one with its unit and default (``--help``). All
read-only but ``fusion_core.LIVE_PARAMS``, checked and applied at run time.

Publisher identity: :mod:`input_guard` (``publishers.allow``); the services log the nodes with a client of them.

What is decided -- routing, health, the flush policy (``processing``, ``clock``, ``idle_flush``), the time guard
(``max_future``), calibration, the diagnostics verdict, the /tf_static links -- is :mod:`fusion_core` (ROS-free,
unit-tested); this node keeps the parameters, publishers, subscriptions, message conversion, TF, services and timers.
"""

from __future__ import annotations

import contextlib
import sys
import time
from functools import partial

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TwistWithCovarianceStamped
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node, NodeNameNonExistentError
from rclpy.task import Future
from std_srvs.srv import Trigger

from fullperc_common import diagnostics as diag
from fullperc_common.drain import take_queued
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError
from fullperc_common.tf import Broadcaster, StaticBroadcaster, transform_stamped
from fullperc_fusion.fusion_config import read_values
from fullperc_fusion.fusion_core import DIAG_EVAL_PERIOD_S, FusionCore, Log
from fullperc_fusion.fusion_endpoints import Endpoints, Inputs, declare_row, live_parameters, quality_record
from fullperc_fusion.fusion_interface import POSES_TOPIC, output_topic
from fullperc_fusion.fusion_publish import OutputPublisher, PosesPublisher, publish_final, publish_outputs
from fullperc_fusion.input_guard import CHECK_PERIOD_S, gid_hex, node_fqn, service_callers_line
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.ordered import FusedOutput
from fullperc_msgs.msg import FusedPoseArray, FusionStatus, Region


class FusionNode(Node):
    def __init__(self, **kw) -> None:
        super().__init__("fusion_node", **kw)
        vals = read_values(partial(declare_row, self))   # every parameter of fusion_config.PARAMS, declared, checked
        self.core = core = FusionCore(vals, time.monotonic(), self.resolve_topic_name)
        # a callback takes *everything* queued (a queue holds at most qos_depth): with a cap per subscription, a node
        # seconds behind took 8 s of each 120 Hz topic but 16 s of the 60 Hz Vega's, and the next batch's OMC
        # samples were then older than the history -- dropped as late (a CI demo lost 249 instrument samples)
        self._take_max = vals["qos_depth"]
        self._ep = ep = Endpoints(self, vals)   # also remakes auto-QoS inputs best effort (timer)
        self._diag = diag.Diagnostics(self, hardware_id=f"fullperc_fusion {self.get_fully_qualified_name()}")
        self._cal_future: Future | None = None
        self._region: dict[str, int] = {}
        pubs: dict[tuple[str, str], tuple] = {}
        self._final_pubs: dict[str, object] = {}
        for t in core.targets:
            pubs[(t, "")] = (ep.publisher(PoseStamped, output_topic(t, "pose")),
                             ep.publisher(PoseWithCovarianceStamped, output_topic(t, "pose_cov")),
                             ep.publisher(FusionStatus, output_topic(t, "status")))
            if vals["publish_final"] and isinstance(core.pipes[t], ArrivalPipeline):
                self._final_pubs[t] = ep.publisher(PoseStamped, output_topic(t, "final"))
            for f in core.extra:
                pubs[(t, f)] = (ep.publisher(PoseStamped, output_topic(t, "pose", f)), None,
                                ep.publisher(FusionStatus, output_topic(t, "status", f)))
            ep.subscription(Region, output_topic(t, "region"), lambda m, t=t: self._region.__setitem__(t, int(m.label)))
        vel = {t: ep.publisher(TwistWithCovarianceStamped, output_topic(t, "velocity"))
               for t in core.targets if vals["publish_velocity"]}
        self._out_sets = {k: OutputPublisher(*v, status_rate=vals["status_rate"],
                                             frame=core.frames.base, vel_pub=vel.get(k[0]) if k[1] == "" else None)
                          for k, v in pubs.items()}
        self._poses = PosesPublisher(ep.publisher(FusedPoseArray, POSES_TOPIC) if vals["publish_poses"] else None,
                                     core.frames.base, core.targets, core.publish_error)
        self._in = Inputs(ep, core, vals["inputs"], self._on_input, self._on_quality)   # subscriptions, reading
        self._pub_counts: dict[str, int] = {}   # input topic -> its publisher count at the last check
        self.create_service(Trigger, "~/initialize", self._on_initialize)
        # own (reentrant) group: the answer waits for the collection, and the default group's callbacks (the data)
        # must run meanwhile; a second call is answered at once
        self.create_service(Trigger, "~/calibrate", self._on_calibrate, callback_group=ReentrantCallbackGroup())
        self._tf = Broadcaster(self, rate=vals["tf.rate"]) if vals["tf.enabled"] else None
        self._tf_static = StaticBroadcaster(self) if vals["tf.enabled"] else None
        self._send_static()
        self.create_timer(0.01, self._on_timer)
        self.create_timer(DIAG_EVAL_PERIOD_S, self._update_diagnostics)
        self.create_timer(CHECK_PERIOD_S, lambda: self._settle_inputs(self._guard_inputs()))
        self._update_diagnostics()
        # last: rclpy runs this callback for every parameter declared after it (the qos_overrides above)
        self.add_on_set_parameters_callback(live_parameters(core, self._apply_live, self.get_logger().info))
        self.get_logger().info(core.startup_message())

    def _apply_live(self, vals: dict) -> None:
        """What the node itself holds of a run-time set the core accepted: the status cap of every topic set."""
        for out in self._out_sets.values():
            out.status_rate = vals["status_rate"]

    def _log(self, lines: list[Log]) -> None:
        """The core's log lines. One call site per level: rclpy refuses a call site whose severity changes."""
        log = self.get_logger()
        for level, text in lines:
            if level == "error":
                log.error(text)
            elif level == "warning":
                log.warning(text)
            else:
                log.info(text)

    def _host_ns(self) -> int | None:
        """The node clock when the core polls with it (``clock: host``), else None (not read)."""
        return self.get_clock().now().nanoseconds if self.core.needs_clock else None

    # ---- input ------------------------------------------------------------------------------
    def _on_input(self, dev: str, body: str, data: bytes, info) -> None:
        """One executor callback: this message plus everything queued on every input, fused and published
        (:meth:`_fuse_inputs`); then the side-by-side filters' deferred work, an item at a time, each after fusing
        and publishing what arrived meanwhile (arrival.py: a live output waits for one item's side-by-side work, not
        for every due item's). At most as many items as waited when it began: the executor gets its turn (timers,
        services), and what is left waits for the next callback or the timer. ``info``: rclpy's message info (a
        required argument, so rclpy passes it), for the callback delay."""
        received = info.get("received_timestamp") if isinstance(info, dict) else None
        self._fuse_inputs(dev, body, data, received)
        for _ in range(max(self.core.side_backlog().values(), default=0)):
            self._fuse_inputs(None, "", b"", None)   # nothing queued: returns at once
            for t in self.core.side_backlog():
                self._publish(t, self.core.side_outputs(t, 1))
                self._publish_final(t)
            self._flush_wakeup()

    def _fuse_inputs(self, dev: str | None, body: str, data: bytes, received: int | None) -> None:
        """The message ``data`` of ``(dev, body)`` (``dev`` None: none) plus everything queued on every input, in stamp
        order (a link body's sample before a target sample of the same stamp: the same device frame, mapped with it),
        taken serialized and read by input_cdr (no Python message per sample); with ``inputs: frames`` each message is
        a source's TrackedBodies. The quality records taken with it (the frames', or the queued ones of the quality
        topics) go to the core first. The live outputs are published at once; ``received``: the message's reception
        time, for the callback delay."""
        wall = time.time_ns()
        batch, topics = self._in.take(dev, body, data, self._take_max)   # this message and everything queued
        if not topics:
            return
        batch.sort(key=self.core.batch_key)
        changed = self._guard_inputs(topics)   # before fusing any
        touched: set[str] = set()
        now, clock_ns = time.monotonic(), self.get_clock().now().nanoseconds   # time guard: 0 = sim time not started
        for args in self._in.take_qualities():   # the quality records taken with the batch, before its poses
            self.core.quality_rx(args[0], now)
            self.core.quality(*args)
        for t_ns, d, b, p, q in batch:
            touched.update(self.core.on_pose(d, b, t_ns, p, q, now, clock_ns))
        for t in touched:   # the live outputs first; the side-by-side filters' deferred work after (_on_input)
            self._publish(t, self.core.poll(t, self._host_ns()))
        self._flush_wakeup()
        for t in touched:
            self._publish_final(t)
            self._log(self.core.watch_links(t, time.monotonic()))
        clock = self.get_clock().now().nanoseconds   # 0: sim time not started, no lag known
        if self.core.input_done(batch, None if not received else wall - int(received), clock, time.monotonic(),
                                time.time_ns() - wall):
            self._update_diagnostics()   # its timer is a period late: an overloaded node runs no timer
        self._settle_inputs(changed)
        self._diag.publish_if_overdue()

    def _on_quality(self, key: tuple[str, str], data: bytes) -> None:
        """This quality message and every one queued behind it, taken serialized and read by input_cdr."""
        self.core.quality_rx(key, time.monotonic())
        changed = self._guard_inputs([self.core.quality_topics[key]])
        for m in [data, *take_queued(self._in.quality[key], self._take_max)]:
            self.core.quality(*quality_record(key, m))
        self._settle_inputs(changed)

    def _guard_inputs(self, topics=None) -> bool:
        """Publishers of ``topics`` (a callback's: read if their count changed or a name is unknown; None: all) to the
        guard; a topic acceptable again loses its queue (received while closed). True: one closed (or reopened)."""
        now, guard, logs = time.monotonic(), self.core.guard, []
        for topic in self._in.sub_of if topics is None else topics:
            n = self._in.sub_of[topic].get_publisher_count()   # writers matched to our reader (input_guard)
            if topics is not None and n == self._pub_counts.get(topic) and not guard.unresolved(topic):
                guard.touch(topic, now)
                continue
            self._pub_counts[topic] = n
            logs += self.core.publishers_seen(topic, [(node_fqn(i.node_namespace, i.node_name), gid_hex(
                i.endpoint_gid)) for i in self.get_publishers_info_by_topic(topic)], now)
        for topic in guard.draining():
            guard.drop(topic, len(take_queued(self._in.sub_of[topic], 1_000_000)))
        self._log(logs)
        return any(level != "info" for level, _ in logs)

    def _settle_inputs(self, changed: bool) -> None:
        """After the samples in hand: open the topics whose queue was discarded; a changed verdict is sent at once."""
        if (logs := self.core.guard.settle(time.monotonic())) or changed:
            self._log(logs)
            self._update_diagnostics()
            self._diag.publish()

    def close(self) -> None:
        """Shutdown (run_node, before it waits for the readers' acks): fuse and publish what the inputs still queue
        -- a node behind its inputs at SIGINT dropped that tail --, flush every history as final, and publish the
        final /diagnostics (lost samples settled)."""
        while first := next(((d, b, m[0]) for d, b, s in self._in.subs if (m := take_queued(s, 1))), None):
            self._on_input(*first, None)
        for t, outs in self.core.flush_all():
            self._publish(t, outs)
            self._publish_final(t)
        self._flush_wakeup()
        for key, sub in self._in.quality.items():
            while m := take_queued(sub, 1):
                self._on_quality(key, m[0])
        self.core.end_of_streams()   # nothing more comes: the last /diagnostics settles every count
        self._update_diagnostics()
        self._diag.publish()

    def _on_timer(self) -> None:
        self._ep.switch_pending()
        now = time.monotonic()
        if self.core.calibrating:
            self._finish_calibration(now)
        for t, outs in self.core.due_outputs(now, self._host_ns()):
            self._publish(t, outs)
            self._publish_final(t)
        self._flush_wakeup()

    # ---- services ---------------------------------------------------------------------------
    def _callers(self, service: str) -> str:
        """Who could have called ``service``: the nodes with a client of it (rclpy gives no caller identity)."""
        name, clients = self.resolve_service_name(service), []
        with contextlib.suppress(NodeNameNonExistentError):   # a node gone meanwhile
            clients = [node_fqn(ns, n) for n, ns in self.get_node_names_and_namespaces()
                       if any(s == name for s, _ in self.get_client_names_and_types_by_node(n, ns))]
        return service_callers_line(name, clients)

    def _on_initialize(self, _req, resp):
        resp.success = True
        resp.message = self.core.initialize()
        self.get_logger().info(f"{self._callers('~/initialize')}; {resp.message}")
        self._update_diagnostics()
        return resp

    async def _on_calibrate(self, _req, resp):
        """~/calibrate: answered when the collection is done (the executor keeps running every other callback)."""
        self.get_logger().info(self._callers("~/calibrate"))
        started, message = self.core.start_calibration(time.monotonic())
        if not started:
            resp.success = False
            resp.message = message
            return resp
        fut = self._cal_future = Future()
        self.get_logger().info(message)
        ok, message = await fut
        resp.success = ok
        resp.message = message
        return resp

    def _finish_calibration(self, now: float) -> None:
        """Poll the ~/calibrate run; when done: links swapped by the core (or kept), /tf_static, answer."""
        done = self.core.finish_calibration(now)
        if done is None:
            return
        fut, self._cal_future = self._cal_future, None
        if done.ok:
            self._send_static()
        self._log([(done.level, done.message)])
        if done.ok:
            self._update_diagnostics()
        if fut is not None:
            fut.set_result((done.ok, done.message))

    # ---- output -----------------------------------------------------------------------------
    def _send_static(self) -> None:
        """/tf_static: the static links, sent when they are first known and again whenever one changes."""
        if self._tf_static is None:
            return
        links = self.core.static_links_to_send()
        if links is None:
            return
        now = self.get_clock().now().nanoseconds
        try:
            self._tf_static.send([transform_stamped(now, p, c, T) for p, c, T in links])
        except ValueError as e:
            self.get_logger().error(f"/tf_static not sent: {e}")

    def _publish(self, target: str, outs: list[FusedOutput]) -> None:
        self._send_static()
        core, now = self.core, time.monotonic()
        core.note_skipped(target, now)
        tfs = publish_outputs(
            self._out_sets, target, outs, core.primary, core.extra, self._region.get(target, 0), poses=self._poses,
            on_primary=partial(core.primary_output, target, now), on_error=partial(core.publish_error, target),
            tf_of=None if self._tf is None or not self._tf.wanted() else
            lambda o: transform_stamped(o.t_ns, core.frames.base, core.frames.of(target), p=o.p, q_xyzw=o.q))
        if tfs:
            self._tf.add(tfs)   # sent at the end of the wake-up (_flush_wakeup), as fullperc/poses

    def _publish_final(self, target: str) -> None:
        """fullperc/<target>/final: the primary filter's estimates of the items that left the history."""
        publish_final(self._final_pubs.get(target), self.core.final_outputs(target), self.core.frames.base)

    def _flush_wakeup(self) -> None:
        """/tf and fullperc/poses: what this wake-up's outputs of every target added, one message each."""
        if self._tf is not None:
            self._tf.flush()
        self._poses.flush()

    def _update_diagnostics(self) -> None:
        for name, level, message, values in self.core.diagnostics(time.monotonic(), self._diag.published):
            self._diag.set(name, level, message, values)


def main(args=None) -> int:
    return run_node(FusionNode, "fusion_node", (ParameterError, ValueError), args,
                    params_file=("fullperc_fusion", "fusion.yaml"))


if __name__ == "__main__":
    sys.exit(main())
