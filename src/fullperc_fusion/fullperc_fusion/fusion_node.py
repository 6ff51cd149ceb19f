"""fusion_node: driver poses in, fused target poses in ``base`` out. A thin wrapper of TargetPipeline.

Subscribes (per target, shared between targets where the topic is the same; prefixes and further local sources
from ``sources``, :mod:`sources`):
  /omc/<body>/pose  for the target's OMC body, the base body and the OTS rig body (PoseStamped, ``omc``)
  /ots/<tool>/pose  for the target's OTS tool and the base tool (PoseStamped, ``ots``)
  <prefix>/<tool>/pose  of every further local source: the target's tool and its base tool
  /fullperc/<target>/region (fullperc_msgs/Region, optional: fills FusionStatus.region)
Publishes:
  /fullperc/<target>/pose      PoseStamped, frame ``base``, stamp = acquisition stamp of the newest sample
  /fullperc/<target>/pose_cov  PoseWithCovarianceStamped (same stamp/frame)
  /fullperc/<target>/status    fullperc_msgs/FusionStatus
  /fullperc/<target>/<filter>/pose and .../status  for every filter listed in ``filters`` (side by side; with
                               ``processing: arrival`` fused when an item leaves the history: final, ``history`` late)
  /fullperc/<target>/final     PoseStamped (``processing: arrival``, ``publish_final``): the primary filter's estimate
                               of each item once it left the history -- final, equal to the offline evaluator's
  /tf                          tf2_msgs/TFMessage ``base`` -> ``<target>`` per fused output of the primary filter
                               (stamp = fused stamp); with ``tf.enabled`` (default true)
  /tf_static                   (transient local) ``omc`` -> ``base`` (T_omc_base) and ``base`` -> ``ots``
                               (T_base_ots; not with ``local_chain: tracked``, where the OTS moves) once known, sent
                               again when they change (~/initialize, ~/calibrate, re-calibration); ``base`` ->
                               ``diana_base`` when ``tf.diana_base`` is given (fusion_node has no other source of it)
  /diagnostics                 one status per target: initialization, rejected input and why, silent sources,
                               and the alarms of fusion_health (WARN: hop rate, implausible bias of the global
                               source; ERROR: every sample of a source rejected), naming target and source;
                               WARN when the link monitor sees a bump of the static link (link and size named);
                               overload: queue_depth(_max), lag_ms / lag_max_ms (node clock - stamp of the newest
                               fused sample), callback_delay_max_ms (the _max / _min figures over every input
                               callback since the last published report), <omc|ots>_frames_lost / _samples_lost of the
                               target's sources (TrackingQuality frame-number gaps; visible frames whose pose never
                               came); WARN when the lag stayed above ``lag_warn`` for a whole period, or samples
                               were lost (held problem_hold)
Services:
  ~/initialize (std_srvs/Trigger) re-estimates the static links of every target from the next samples
               (``static_links``: average of init_samples, or calibrate over calibration.duration).
  ~/calibrate  (std_srvs/Trigger) collects calibration.duration s of sightings (keep the setup still), estimates
               the links the chain needs (frame_chain.links_needed) with the robust calibration, and answers when
               done: on success the links of every target are swapped in one step, calibration.output is written
               first (if set), and the answer is success + a summary; a refusal (a body moved, too few sightings)
               answers success=false + the reason and keeps the old links. The node keeps fusing meanwhile.

Parameters: the table of :mod:`fullperc_fusion.fusion_config` (names, defaults, checks, units; the same
mapping the offline evaluator uses); config/fusion.yaml lists every one with its unit and default (``--help``).

``processing``: with ``arrival`` (default, :mod:`arrival`) every sample is fused and published when it arrives
(pose, pose_cov, status, /tf: the newest estimate, stamps strictly increasing); a late sample rewinds and replays
within ``history``; ``slop`` pairs as before, ``reorder_delay`` and ``clock`` only decide which static links an
item is mapped with (as in ordered processing) and nothing waits. With ``ordered`` the rest of this paragraph applies.
``clock``: with ``stamps`` the synchronizer's notion of "now" is the newest stamp received,
so output depends only on the data (live, replayed bags, simulated time alike); after ``idle_flush``
seconds without any target sample everything pending is flushed. With ``host`` "now" is the node
clock, for deployments where the stamps are on that clock and latency must not depend on traffic.

``max_future`` (time guard, either clock mode): a sample stamped more than this ahead of the node clock is
rejected before it reaches the pipeline's synchronizer (``rejected_future`` on /diagnostics, naming the source,
the stamp and how far ahead), so one bad stamp cannot move the watermark (ordered) or the history (arrival) an hour
ahead and stall the output; with arrival processing a sample older than the history is dropped as ``late``, named. The
node clock follows /clock under ``use_sim_time`` (replays keep working); while that clock has not started
(time 0) nothing is checked.
"""

from __future__ import annotations

import sys
import time
from functools import partial

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from std_srvs.srv import Trigger

from fullperc_common import diagnostics as diag
from fullperc_common.drain import take_queued
from fullperc_common.node_main import run_node
from fullperc_common.params import ParameterError, declare
from fullperc_common.ros_conv import ns_to_stamp, pose_msg, pose_to_pq, stamp_to_ns
from fullperc_common.tf import Broadcaster, StaticBroadcaster, transform_stamped
from fullperc_fusion.calibration.io import save_calibration
from fullperc_fusion.calibration.run import CalibrationRun, summary
from fullperc_fusion.calibration.se3_stats import CalibrationBodies
from fullperc_fusion.fusion_config import (
    calibration_settings,
    health_params,
    primary_and_extra,
    read_values,
    spec,
    target_config,
)
from fullperc_fusion.fusion_health import GLOBAL, LOCAL, InputLoad, SourceLoss, TargetHealth
from fullperc_fusion.fusion_publish import OutputPublisher, publish_outputs
from fullperc_fusion.pipeline.arrival import ArrivalPipeline, make_pipeline
from fullperc_fusion.pipeline.frame_chain import links_needed, pose_to_T
from fullperc_fusion.pipeline.ordered import FusedOutput, TargetPipeline
from fullperc_fusion.pipeline.sources import routes
from fullperc_msgs.msg import FusionStatus, Region, TrackingQuality

# Diagnostics.set takes an int level (the diagnostic_msgs constants are bytes in rclpy).
OK, WARN, ERROR = (diag.as_level(v) for v in (diag.OK, diag.WARN, diag.ERROR))
DIAG_EVAL_PERIOD_S = 0.5   # [s] the diagnostics' evaluation timer (published every 1 s by diag.Diagnostics)
# [s] silence after which frames still waiting for their pose count as lost: > Fast DDS's 3 s heartbeat, after which
# a reliable reader gets a sample repaired (a demo: 166 OMC samples came 1-3 s late, each fused; 1 s counted them lost)
LOSS_SILENCE_S = 4.0
_PROBLEM_KEYS = ("rejected_nonfinite", "rejected_nonunit", "rejected_pose", "rejected_stamp", "rejected_future",
                 "late", "duplicate", "rejected_cov", "local_skipped", "filter_error", "nonfinite_output",
                 "publish_error", "calibration_refused", "timeline_restart")
# ROS type of a parameter declared without a default value (optional ones, empty lists)
_ROS_TYPES = {"str_list": Parameter.Type.STRING_ARRAY, "pose7": Parameter.Type.DOUBLE_ARRAY,
              "str": Parameter.Type.STRING, "float": Parameter.Type.DOUBLE, "bool": Parameter.Type.BOOL}


class FusionNode(Node):
    def __init__(self, **kw) -> None:
        super().__init__("fusion_node", **kw)
        vals = read_values(self._declare)   # every parameter of fusion_config.PARAMS, declared, converted, checked
        targets = vals["targets"]
        primary, extra = primary_and_extra(vals)
        local_chain = vals["local_chain"]
        self._clock_mode = vals["clock"]
        self._idle_flush = vals["idle_flush"]
        self._stale = vals["stale_timeout"]
        self._problem_hold = vals["problem_hold"]
        self._lag_warn = vals["lag_warn"]
        self._load = InputLoad()
        self._behind_ns = 0   # node clock - newest stamp, at the end of the last input callback
        self._diag_sent = 0   # /diagnostics arrays sent before the last evaluation's values were set
        self._diag_eval_at = time.monotonic()   # the last _update_diagnostics
        self._cal_duration = vals["calibration.duration"]
        self._cal_output = vals["calibration.output"]
        self._cal_timeout = vals["calibration.timeout"]
        self._cal_settings = calibration_settings(vals)
        self._cal_run: tuple[CalibrationRun, Future] | None = None
        health = health_params(vals)
        qos = QoSProfile(depth=vals["qos_depth"], reliability=ReliabilityPolicy.RELIABLE
                         if vals["qos_reliability"] == "reliable" else ReliabilityPolicy.BEST_EFFORT)

        self._primary = primary
        self._extra = extra
        filters = tuple(dict.fromkeys([primary, *self._extra]))
        self._diag = diag.Diagnostics(self, hardware_id="fullperc_fusion")
        self.pipes: dict[str, TargetPipeline] = {}
        self._pubs: dict[tuple[str, str], tuple] = {}
        self._final_pubs: dict[str, object] = {}
        self._loss: dict[tuple[str, str], SourceLoss] = {}   # (dev, target body): frames / samples never received
        self._loss_seen: dict[tuple[str, str], tuple[int, float]] = {}
        self._loss_rx: dict[tuple[str, str], float] = {}   # monotonic time of its newest pose or quality message
        self._quality_subs: dict[tuple[str, str], object] = {}
        self._region: dict[str, int] = {}
        self._last_rx: dict[str, dict[str, float]] = {}
        self._problem_seen: dict[str, dict[str, tuple[int, float]]] = {}
        self.health: dict[str, TargetHealth] = {}
        self._bump_seen: dict[str, tuple[float, str] | None] = {}   # when the link monitor last saw a bump, what
        self._link_state: dict[str, tuple[int | None, int]] = {}    # logged (bump start, recalibrations)
        self._skipped_seen: dict[str, int] = {}
        self._last_target_rx = time.monotonic()
        self._routes: dict[str, dict[str, list[str]]] = {}   # device tag (omc, ots, further source) -> body -> targets
        self._prefix: dict[str, str] = {}
        for t in targets:
            self.pipes[t] = make_pipeline(target_config(vals, t, filters))
            c = self.pipes[t].config.chain
            extra_tools = "".join(f", {x.name} tool '{ch.cfg.ots_target}'" for x, ch in
                                  zip(self.pipes[t].config.sources.extras, self.pipes[t].extra_chains, strict=True))
            self.health[t] = TargetHealth(t, {GLOBAL: f"OMC body '{c.omc_target}'",
                                              LOCAL: f"OTS tool '{c.ots_target}'{extra_tools}"}, health)
            self._skipped_seen[t] = 0
            self._bump_seen[t] = None
            self._link_state[t] = (None, 0)
            pipe = self.pipes[t]
            rts = routes(pipe.config.sources, c, pipe.extra_chains)
            for r in rts:
                self._prefix[r.tag] = r.prefix
                for b in r.bodies:
                    self._routes.setdefault(r.tag, {}).setdefault(b, []).append(t)
            self._pubs[(t, "")] = (
                self.create_publisher(PoseStamped, f"/fullperc/{t}/pose", qos),
                self.create_publisher(PoseWithCovarianceStamped, f"/fullperc/{t}/pose_cov", qos),
                self.create_publisher(FusionStatus, f"/fullperc/{t}/status", qos))
            if vals["publish_final"] and isinstance(self.pipes[t], ArrivalPipeline):
                self._final_pubs[t] = self.create_publisher(PoseStamped, f"/fullperc/{t}/final", qos)
            for dev, body, pre in ((r.tag, r.target, r.prefix) for r in rts):
                if (dev, body) not in self._loss:
                    self._loss[(dev, body)] = SourceLoss()
                    self._quality_subs[(dev, body)] = self.create_subscription(
                        TrackingQuality, f"{pre.rstrip('/')}/{body}/quality", partial(self._on_quality, (dev, body)),
                        qos)
            for f in self._extra:
                self._pubs[(t, f)] = (
                    self.create_publisher(PoseStamped, f"/fullperc/{t}/{f}/pose", qos), None,
                    self.create_publisher(FusionStatus, f"/fullperc/{t}/{f}/status", qos))
            self.create_subscription(Region, f"/fullperc/{t}/region",
                                     lambda m, t=t: self._region.__setitem__(t, int(m.label)), 10)
            self._last_rx[t] = {r.tag: None for r in rts}
            self._problem_seen[t] = {}
        self._out_sets = {k: OutputPublisher(*v, always_pose=k[1] == "", status_rate=vals["status_rate"])
                          for k, v in self._pubs.items()}
        self._targets_of = {d: {b: list(dict.fromkeys(ts)) for b, ts in r.items()} for d, r in self._routes.items()}
        self._local_k = {r.tag: r.k for r in rts}
        self._input_subs: list[tuple[str, str, object]] = []
        for dev, rt in self._targets_of.items():
            for b in rt:
                sub = self.create_subscription(PoseStamped, f"{self._prefix[dev].rstrip('/')}/{b}/pose",
                                               partial(self._on_input, dev, b), qos)
                self._input_subs.append((dev, b, sub))
        self.create_service(Trigger, "~/initialize", self._on_initialize)
        # own (reentrant) group: the answer waits for the collection, and the default group's callbacks (the data)
        # must run meanwhile; a second call is answered at once
        self.create_service(Trigger, "~/calibrate", self._on_calibrate, callback_group=ReentrantCallbackGroup())
        self._tf = Broadcaster(self) if vals["tf.enabled"] else None
        self._tf_static = StaticBroadcaster(self) if vals["tf.enabled"] else None
        d = vals["tf.diana_base"]
        self._T_base_diana = None if d is None else pose_to_T((np.asarray(d[:3]), np.asarray(d[3:])))
        self._static_key: tuple | None = None
        self._send_static()
        self.create_timer(0.01, self._on_timer)
        self.create_timer(DIAG_EVAL_PERIOD_S, self._update_diagnostics)
        self._update_diagnostics()
        links = next(iter(self.pipes.values())).chain.links
        given = "".join(f"{k} from {v}; " for k, v in links.sources.items())
        rest = (f"average of the first {vals['init_samples']} samples" if vals["static_links"] == "average"
                else f"calibrated over the first {self._cal_duration:g} s, average of the first samples meanwhile")
        self.get_logger().info(
            f"fusing targets {targets} with {filters[0]} (side by side: {self._extra or 'none'}), "
            f"local chain '{local_chain}', clock '{self._clock_mode}', static links: {given}"
            + (f"others: {rest}" if links.collecting else "all given"))

    def _declare(self, name: str, default):
        """fusion_config's getter: declare ``name`` (once, via params.declare) and return its value."""
        if self.has_parameter(name):
            return self.get_parameter(name).value
        p = spec(name)
        if default is None or (isinstance(default, list) and not default):
            default = _ROS_TYPES[p.kind]
        return declare(self, name, default, description=p.description)

    # ---- input ------------------------------------------------------------------------------
    def _on_input(self, dev: str, body: str, msg: PoseStamped, info) -> None:
        """One executor callback: this message plus everything queued on every input, in stamp order (a link
        body's sample before a target sample of the same stamp: the same device frame, mapped with it). ``info``:
        rclpy's message info (a required argument, so rclpy passes it), for the callback delay."""
        wall = time.time_ns()
        batch = [(stamp_to_ns(msg.header.stamp), dev, body, msg)]
        for d, b, sub in self._input_subs:
            batch.extend((stamp_to_ns(m.header.stamp), d, b, m) for m in take_queued(sub))
        batch.sort(key=lambda x: (x[0], (x[1], x[2]) in self._loss))
        touched: set[str] = set()
        for _t, d, b, m in batch:
            touched.update(self._on_pose(d, b, m))
        for t in touched:
            self._publish(t, self.pipes[t].poll(self._now_ns()))
            self._publish_final(t)
            self._watch_links(t)
        received = info.get("received_timestamp") if isinstance(info, dict) else None
        clock = self.get_clock().now().nanoseconds   # 0: sim time not started, no lag known
        self._load.callback(len(batch) - 1, None if not received else wall - int(received),
                            clock - batch[-1][0] if clock else None)
        self._behind_ns = clock - batch[-1][0] if clock else 0
        rx = time.monotonic()
        for d, b, m in ((d, b, m) for _t, d, b, m in batch if (d, b) in self._loss):
            self._loss[(d, b)].pose(stamp_to_ns(m.header.stamp))
            self._loss_rx[(d, b)] = rx
        self._timers_overdue()

    def close(self) -> None:
        """Shutdown (run_node, before it waits for the readers' acks): fuse and publish what the inputs still queue
        -- a node behind its inputs at SIGINT dropped that tail --, flush every history as final, and publish the
        final /diagnostics (lost samples settled)."""
        while first := next(((d, b, m[0]) for d, b, s in self._input_subs if (m := take_queued(s, 1))), None):
            self._on_input(*first, None)
        for t, pipe in self.pipes.items():
            if pipe.pending if isinstance(pipe, ArrivalPipeline) else pipe.sync.pending:
                self._publish(t, pipe.flush())
                self._publish_final(t)
        for key, sub in self._quality_subs.items():
            while m := take_queued(sub, 1):
                self._on_quality(key, m[0])
        for loss in self._loss.values():   # nothing more comes: the last /diagnostics settles every count
            loss.end_of_stream()
        self._update_diagnostics()
        self._diag.publish()

    def _on_quality(self, key: tuple[str, str], msg: TrackingQuality) -> None:
        """This quality message and every one queued behind it (one executor round each would fall behind)."""
        loss = self._loss[key]
        self._loss_rx[key] = time.monotonic()
        for m in [msg, *take_queued(self._quality_subs[key])]:
            loss.quality(int(m.frame_number), stamp_to_ns(m.header.stamp), bool(m.visible))
            if key[0] == "omc" and m.visible:   # H3: the OMC model covariance of filters with uses_models (fullperc)
                for t in self._targets_of["omc"].get(key[1], ()):
                    self.pipes[t].push_omc_quality(key[1], stamp_to_ns(m.header.stamp),
                                                   {"fit_error": float(m.fit_error),
                                                    "markers_used": float(m.markers_used)})

    def _publish_final(self, target: str) -> None:
        """/fullperc/<target>/final: the primary filter's estimates of the items that left the history (the
        side-by-side filters' own topics carry their final estimates already)."""
        pipe = self.pipes[target]
        if not isinstance(pipe, ArrivalPipeline):
            return
        outs = pipe.take_final()
        pub = self._final_pubs.get(target)
        if pub is None:
            return
        for o in outs:
            if o.filter != self._primary:
                continue
            ps = PoseStamped()
            ps.header.stamp = ns_to_stamp(o.t_ns)
            ps.header.frame_id = "base"
            try:
                ps.pose = pose_msg(o.p, o.q)
            except ValueError:
                continue
            pub.publish(ps)

    def _on_pose(self, dev: str, body: str, msg: PoseStamped) -> list[str]:
        """Push one pose into the pipelines of the targets it feeds; returns those targets."""
        t_ns = stamp_to_ns(msg.header.stamp)
        p, q = pose_to_pq(msg.pose)
        now = time.monotonic()
        clock_ns = self.get_clock().now().nanoseconds or None   # the time guard's clock; 0: sim time not started
        if self._cal_run is not None and dev in ("omc", "ots"):
            self._cal_run[0].add(dev, body, t_ns, p, q)
        targets = self._targets_of[dev][body]
        for t in targets:
            pipe = self.pipes[t]
            c = pipe.config.chain
            if dev == "omc":
                ok = pipe.push_omc(body, t_ns, (p, q), now_ns=clock_ns)
                if body == c.omc_target:
                    self._last_rx[t]["omc"] = now
                    self._last_target_rx = now
                    self._source_sample(t, GLOBAL, ok, now)
            else:   # ots: the first local source; a further one by its index (sources.py)
                k = self._local_k[dev]
                ok = pipe.push_local(k, body, t_ns, (p, q), now_ns=clock_ns)
                if body == (c if k == 0 else pipe.extra_chains[k - 1].cfg).ots_target:
                    self._last_rx[t][dev] = now
                    self._last_target_rx = now
                    self._source_sample(t, LOCAL, ok, now)
        return targets

    def _source_sample(self, target: str, source: str, accepted: bool, now: float) -> None:
        h = self.health[target]
        if accepted:
            h.accepted(source, now)
        else:
            h.rejected(source, now, self.pipes[target].last_problem)

    def _now_ns(self) -> int | None:
        return self.get_clock().now().nanoseconds if self._clock_mode == "host" else None

    def _on_timer(self) -> None:
        if self._cal_run is not None:
            self._finish_calibration()
        idle = time.monotonic() - self._last_target_rx > self._idle_flush
        for t, pipe in self.pipes.items():
            if isinstance(pipe, ArrivalPipeline):   # nothing waits; after idle_flush the history becomes final
                if idle and pipe.pending:
                    self._publish(t, pipe.flush())
                    self._publish_final(t)
                continue
            if pipe.sync.pending == 0:
                continue
            self._publish(t, pipe.flush() if (idle and self._clock_mode == "stamps") else pipe.poll(self._now_ns()))

    def _on_initialize(self, _req, resp):
        for pipe in self.pipes.values():
            pipe.request_initialize()
        c = next(iter(self.pipes.values())).config.chain
        how = (f"from the next {c.init_samples} samples per body" if c.static_links == "average" else
               f"by calibrating over the next {c.calibration_duration_s:g} s of sightings")
        resp.success = True
        resp.message = (f"re-estimating static links of {list(self.pipes)} {how}; the previous links stay in use "
                        "until then")
        self.get_logger().info(resp.message)
        self._update_diagnostics()
        return resp

    async def _on_calibrate(self, _req, resp):
        """~/calibrate: answered when the collection is done (the executor keeps running every other callback)."""
        if self._cal_run is not None:
            resp.success = False
            resp.message = "a calibration is already running; call again when it has answered"
            return resp
        c = next(iter(self.pipes.values())).config.chain
        links = links_needed(c)
        run = CalibrationRun(links, CalibrationBodies.from_chain_config(c), self._cal_duration, self._cal_settings,
                             now=time.monotonic(), timeout_s=self._cal_timeout, source="fusion_node ~/calibrate")
        fut = Future()
        self._cal_run = (run, fut)
        self.get_logger().info(f"~/calibrate: collecting {self._cal_duration:g} s of sightings for {list(links)}; "
                               "keep the OTS and the reference marker still")
        ok, message = await fut
        resp.success = ok
        resp.message = message
        return resp

    def _finish_calibration(self) -> None:
        """Poll the ~/calibrate run; when done: write the file, swap the links of every target, answer."""
        assert self._cal_run is not None
        run, fut = self._cal_run
        if not run.poll(time.monotonic()):
            return
        self._cal_run = None
        log = self.get_logger()
        if run.result is None:
            message = f"calibration refused, links unchanged: {run.error}"
            log.warning(message)
            fut.set_result((False, message))
            return
        cal = run.result
        written = ""
        if self._cal_output:
            try:
                save_calibration(self._cal_output, cal)
            except (OSError, ValueError) as e:
                message = f"calibration not applied, links unchanged: cannot write {self._cal_output}: {e}"
                log.error(message)
                fut.set_result((False, message))
                return
            written = f"; written to {self._cal_output}"
        for pipe in self.pipes.values():
            pipe.apply_calibration(cal, "~/calibrate")
        self._send_static()
        message = f"{summary(cal)}; links of {list(self.pipes)} swapped{written}"
        log.info(message)
        self._update_diagnostics()
        fut.set_result((True, message))

    def _watch_links(self, target: str) -> None:
        """Log the start of a link bump and every re-calibration the monitor started; remember the bump."""
        pipe = self.pipes[target]
        m = pipe.monitor
        start, n_recal = self._link_state[target]
        if m.bumped:
            self._bump_seen[target] = (time.monotonic(), m.message(target))
            if m.first_bump_ns != start:
                self.get_logger().warning(m.message(target))
        elif start is not None and m.last is not None:
            self.get_logger().info(m.message(target))
        if pipe.counts["recalibrations"] > n_recal:
            self.get_logger().warning(f"target '{target}': re-calibrating the static links over "
                                      f"{pipe.config.chain.calibration_duration_s:g} s after the bump; the old "
                                      "links stay in use meanwhile")
        self._link_state[target] = (m.first_bump_ns if m.bumped else None, pipe.counts["recalibrations"])

    # ---- output -----------------------------------------------------------------------------
    def _static_links(self) -> list[tuple[str, str, np.ndarray]]:
        """(parent, child, T_parent_child) of the static links known now (the first target whose links are set)."""
        out: dict[str, tuple[str, str, np.ndarray]] = {}
        for pipe in self.pipes.values():
            L = pipe.chain.links
            if L.T_omc_base is not None:
                out.setdefault("base", ("omc", "base", L.T_omc_base))
            if L.T_base_ots is not None and pipe.config.chain.local_chain != "tracked":
                out.setdefault("ots", ("base", "ots", L.T_base_ots))
            for x, ch in zip(pipe.config.sources.extras, pipe.extra_chains, strict=True):   # base -> <source>
                if ch.links.T_base_ots is not None and ch.cfg.local_chain != "tracked":
                    out.setdefault(x.name, ("base", x.name, ch.links.T_base_ots))
        if self._T_base_diana is not None:
            out["diana_base"] = ("base", "diana_base", self._T_base_diana)
        return list(out.values())

    def _send_static(self) -> None:
        """/tf_static: the static links, sent when they are first known and again whenever one changes."""
        if self._tf_static is None:
            return
        links = self._static_links()
        key = tuple((p, c, T.tobytes()) for p, c, T in links)
        if not links or key == self._static_key:
            return
        self._static_key = key
        now = self.get_clock().now().nanoseconds
        try:
            self._tf_static.send([transform_stamped(now, p, c, T) for p, c, T in links])
        except ValueError as e:
            self.get_logger().error(f"/tf_static not sent: {e}")

    def _publish(self, target: str, outs: list[FusedOutput]) -> None:
        self._send_static()
        now = time.monotonic()
        pipe, h = self.pipes[target], self.health[target]
        skipped = pipe.counts["local_skipped"]
        if skipped > self._skipped_seen[target]:     # local samples the chain could not map: rejected too
            h.rejected(LOCAL, now, pipe.problems.get("local_skipped", ""), skipped - self._skipped_seen[target])
            self._skipped_seen[target] = skipped
        tfs = publish_outputs(
            self._out_sets, target, outs, self._primary, self._extra, self._region.get(target, 0),
            on_primary=lambda o: h.output(now, o.sources, o.hop, o.bias),
            on_error=lambda o, why: pipe.report_problem("publish_error", f"{o.filter}: {why}", o.t_ns),
            tf_of=None if self._tf is None else
            lambda o: transform_stamped(o.t_ns, "base", target, p=o.p, q_xyzw=o.q))
        if tfs:
            self._tf.send(tfs)

    def _timers_overdue(self) -> None:
        """The diagnostics' evaluation and publishing from the input path when their timers are a period late: an
        overloaded node runs input callbacks back to back, and rclpy's EventsExecutor then ran neither timer."""
        if time.monotonic() - self._diag_eval_at >= 2.0 * DIAG_EVAL_PERIOD_S:
            self._update_diagnostics()
        self._diag.publish_if_overdue()

    def _update_diagnostics(self) -> None:
        now = time.monotonic()
        self._diag_eval_at = now
        self._load.begin_report(self._diag.published > self._diag_sent)
        for t, pipe in self.pipes.items():
            s = pipe.stats()
            values = {k: v for k, v in s.items() if k != "init_progress"}
            values.update({f"init_{k}": v for k, v in s["init_progress"].items()})
            level, msgs = OK, []
            for a in self.health[t].alarms(now):
                level = max(level, a.level)
                msgs.append(a.message)
            values.update(self.health[t].values(now))
            links = pipe.chain.links
            if s["global_link"] != "ready":
                level = WARN
                msgs.append(f"initializing: {links.describe()}")
            elif s["local_link"] != "ready":
                level = WARN
                msgs.append("local link not calibrated yet (the OTS must see the base marker, or give T_rig_ots)"
                            + (f": {links.describe()}" if links.collecting else ""))
            bump = self._bump_seen[t]
            if bump is not None and (pipe.monitor.bumped or now - bump[0] < self._problem_hold):
                level = max(level, WARN)
                msgs.append(bump[1] if pipe.monitor.bumped else f"{bump[1]} (cleared {now - bump[0]:.1f} s ago)")
            seen = self._problem_seen[t]
            for key in _PROBLEM_KEYS:
                n = pipe.counts[key]
                if n > seen.get(key, (0, 0.0))[0]:
                    seen[key] = (n, now)
            for key, (n, when) in seen.items():
                if now - when < self._problem_hold:
                    level = max(level, WARN)
                    msgs.append(f"{key} x{n}: {pipe.problems.get(key, '')}")
            rx = self._last_rx[t]
            for dev, name in (("omc", "OMC (global)"), ("ots", "OTS (local)"), *((d, f"{d} (local)") for d in rx
                                                                                 if d not in ("omc", "ots"))):
                last = rx[dev]
                if last is None:
                    msgs.append(f"no {name} sample received yet")
                    if dev == "omc":
                        level = max(level, WARN)
                elif now - last > self._stale:
                    msgs.append(f"no {name} sample for {now - last:.1f} s"
                                + (" (target occluded or out of the OTS volume: global only, bias compensated)"
                                   if dev == "ots" else ""))
                    if dev == "omc":
                        level = max(level, WARN)
            o = pipe.last_output.get(self._primary)
            if o is not None:
                values.update(bias_mm=np.round(1e3 * o.bias, 3).tolist(), last_stamp_ns=o.t_ns, nis=round(o.nis, 3))
            level = self._overload(t, now, level, msgs, values)
            self._diag.set(f"target {t}", level, "; ".join(msgs) or "ok", values)
        self._load.reset_period()
        self._diag_sent = self._diag.published

    def _overload(self, target: str, now: float, level: int, msgs: list[str], values: dict) -> int:
        """Queue depth, processing lag, callback delay and lost samples of ``target`` (WARN: lag above lag_warn,
        samples lost within problem_hold)."""
        values.update(self._load.values())
        lag = self._load.lag_min_ns
        if lag is not None and lag * 1e-9 > self._lag_warn:
            level = max(level, WARN)
            msgs.append(f"overload: processing lag {lag * 1e-6:.0f} ms or more since the last report > lag_warn "
                        f"{self._lag_warn * 1e3:g} ms (node clock - stamp of the newest fused sample; up to "
                        f"{self._load.depth_max} samples waiting)")
        pipe = self.pipes[target]
        for r in routes(pipe.config.sources, pipe.config.chain, pipe.extra_chains):
            dev, body = r.tag, r.target
            name = f"OMC body '{body}'" if dev == "omc" else f"OTS tool '{body}'" if dev == "ots" else \
                f"{dev} tool '{body}'"
            loss = self._loss.get((dev, body))
            if loss is None:
                continue
            # silent for LOSS_SILENCE_S while the node kept up (behind, its quality callbacks starve and the poses
            # still queue): what still waits for its pose will not get it
            if loss.pending and now - self._loss_rx.get((dev, body), now) > max(self._stale, LOSS_SILENCE_S) \
                    and self._behind_ns * 1e-9 <= self._stale:
                loss.end_of_stream()
            values[f"{dev}_frames_lost"] = loss.frames_lost
            values[f"{dev}_samples_lost"] = loss.samples_lost
            n, when = self._loss_seen.get((dev, body), (0, -1e9))
            if loss.lost > n:
                self._loss_seen[(dev, body)] = (loss.lost, now)
                n, when = loss.lost, now
            if n and now - when < self._problem_hold:
                level = max(level, WARN)
                msgs.append(f"lost samples of the {name}: {loss.samples_lost} poses never arrived (frames of the "
                            f"driver's TrackingQuality; {loss.frames_lost} frame-number gaps: quality messages "
                            "lost on the way, or device frames the driver never read -- its skipped_frames)")
        return level


def main(args=None) -> int:
    return run_node(FusionNode, "fusion_node", (ParameterError, ValueError), args,
                    params_file=("fullperc_fusion", "fusion.yaml"))


if __name__ == "__main__":
    sys.exit(main())
