"""FusionCore: what fusion_node decides, without ROS -- routing, health bookkeeping, flush policy, calibration,
the diagnostics verdict, the link watch and the choice of the /tf_static links.

Why: these decisions were methods of the node, reachable only through multi-process tests. Here every call takes
``now`` (monotonic seconds of the caller's clock; ``fusion_node`` passes ``time.monotonic()``) and stamps in ns, and
returns plain data -- fused outputs, log lines ``(level, text)`` with level ``info | warning | error``, diagnostic
statuses ``(name, level, message, values)``, static links ``(parent, child, T)`` -- which the node converts into
messages. The pipelines (:mod:`pipeline.ordered`, :mod:`pipeline.arrival`) are built here from the node's
parameter values (:func:`fusion_config.read_values`), one per target.

Routing: a pose of (device tag, body) feeds the pipeline of every target whose streams use that body (its own body,
the base marker, the rig); only a sample of a target's own body is a measurement of that target -- it counts for the
source's health (accepted / rejected, :mod:`fusion_health`), for the silence check and for the idle flush. A body no
target uses is routed nowhere. While ``~/calibrate`` runs, every OMC and OTS sighting also goes to its collection.
In an input batch a link body's sample goes before a target sample of the same stamp (the same device frame: the
target's sample is mapped with it).

``processing``: with ``arrival`` (default, :mod:`pipeline.arrival`) every sample is fused and published when it
arrives (pose, pose_cov, status, /tf: the newest estimate, stamps strictly increasing); a late sample rewinds and
replays within ``history``; ``slop`` pairs as before, ``reorder_delay`` and ``clock`` only decide which static links
an item is mapped with (as in ordered processing) and nothing waits; after ``idle_flush`` seconds without any target
sample the history is flushed and becomes final. With ``ordered`` the rest of this paragraph applies. ``clock``:
with ``stamps`` the synchronizer's notion of "now" is the newest stamp received, so output depends only on the data
(live, replayed bags, simulated time alike); after ``idle_flush`` seconds without any target sample everything
pending is flushed. With ``host`` "now" is the node clock, for deployments where the stamps are on that clock and
latency must not depend on traffic.

``max_future`` (time guard, either clock mode): a sample stamped more than this ahead of the node clock is rejected
before it reaches the pipeline's synchronizer (``rejected_future`` on /diagnostics, naming the source, the stamp and
how far ahead), so one bad stamp cannot move the watermark (ordered) or the history (arrival) an hour ahead and
stall the output; with arrival processing a sample older than the history is dropped as ``late``, named. The node
clock follows /clock under ``use_sim_time`` (replays keep working); while that clock has not started (time 0)
nothing is checked.

/tf_static: ``omc -> base`` (T_omc_base), ``base -> ots`` (T_base_ots, not with ``local_chain: tracked``, where
the OTS moves) and ``base -> <source>`` of every further local source, from the first target whose link is known;
``base -> diana_base`` when ``tf.diana_base`` is given. Sent when first known and again when one changes. Frame
names: the node's ``frames.*`` (:mod:`fusion_interface`).

Run-time parameters: :data:`LIVE_PARAMS` (:meth:`FusionCore.apply_live`), checked as at start-up; the rest read-only.

Publisher identity (:mod:`input_guard`, ``publishers.allow``): a sample or quality message of an input topic the
guard holds closed (a publisher on it that is not accepted) is dropped and counted -- it reaches no pipeline, no
health count and no calibration -- and every target that reads the topic is ERROR on /diagnostics, naming topic,
node and GID. While a publisher of any input has no name yet, *every* input's samples and quality messages are held
(at most the guard's 1 s): once it is named and accepted they are used in stamp order -- the order offline processing
sees them in (holding only that topic's samples put a driver's first Vega samples behind OMC samples they preceded,
and the static links averaged from the first samples came out different from the bag's evaluation); a refused
publisher's topic is dropped from them. The node feeds the guard from discovery (:meth:`FusionCore.publishers_seen`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple

import numpy as np

from fullperc_common.params import ParameterError
from fullperc_fusion.calibration.io import save_calibration
from fullperc_fusion.calibration.run import CalibrationRun, summary
from fullperc_fusion.calibration.se3_stats import CalibrationBodies
from fullperc_fusion.fusion_config import (
    BY_NAME,
    calibration_settings,
    convert,
    health_params,
    primary_and_extra,
    target_config,
)
from fullperc_fusion.fusion_health import GLOBAL, LOCAL, TargetHealth
from fullperc_fusion.fusion_interface import frames_of, input_topic
from fullperc_fusion.fusion_verdict import InputBook, Key, TargetVerdict
from fullperc_fusion.input_guard import InputGuard, Publisher
from fullperc_fusion.pipeline.arrival import ArrivalPipeline, make_pipeline
from fullperc_fusion.pipeline.frame_chain import links_needed, pose_to_T
from fullperc_fusion.pipeline.ordered import FusedOutput, TargetPipeline
from fullperc_fusion.pipeline.sources import Route, default_namespace, routes

HOLD_MAX = 10_000          # samples held in all while a publisher has no name (beyond: dropped, counted)
DIAG_EVAL_PERIOD_S = 0.5   # [s] the diagnostics' evaluation timer (published every 1 s by diag.Diagnostics)

Log = tuple[str, str]                                 # (info | warning | error, line)
Status = tuple[str, int, str, dict]                   # (name, level, message, values) of one diagnostic status
StaticLink = tuple[str, str, np.ndarray]              # (parent frame, child frame, T_parent_child)


# What fusion_node applies at run time (every other parameter is read-only): what judges or reports the estimates --
# the alarms, the overload threshold, the status rate -- never what changes one (noise, slop, history, chains): the
# live /final estimates must stay those the offline evaluator computes from the node's params file.
LIVE_PARAMS = ("alarm.hop_window", "alarm.hop_max", "alarm.bias_max", "alarm.reject_timeout", "lag_warn",
               "status_rate")


def check_live(vals: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """The values after a run-time set of ``changes`` (name -> raw value), checked as at start-up: each by its row,
    then the values together (:func:`health_params`). ParameterError naming the parameter and the check (a parameter
    not in :data:`LIVE_PARAMS`: read-only)."""
    new = dict(vals)
    for name, raw in changes.items():
        if name not in LIVE_PARAMS:
            raise ParameterError(f"parameter '{name}' is read-only: set it in the params file and restart the node")
        new[name] = convert(BY_NAME[name], raw)
    try:
        health_params(new)
    except ValueError as e:
        raise ParameterError(str(e)) from None
    return new


class CalibrationAnswer(NamedTuple):
    """How a ``~/calibrate`` run ended: the service's answer and the line to log at ``level``."""
    ok: bool
    message: str
    level: str


class FusionCore:
    """The ROS-free decisions of fusion_node for every target (module docstring); ``vals``: the node's parameter
    values (:func:`fusion_config.read_values`), ``now``: monotonic time [s] at construction; ``resolve``: the node's
    name resolution (``Node.resolve_topic_name``), applied to every input topic the core names -- the guard compares
    them with what discovery lists, and a namespaced node's inputs are ``/<ns>/omc/...``."""

    def __init__(self, vals: dict[str, Any], now: float, resolve: Callable[[str], str] = default_namespace) -> None:
        self.vals = vals
        self.targets: list[str] = list(vals["targets"])
        self.frames = frames_of(vals)
        self._resolve = resolve
        self.primary, self.extra = primary_and_extra(vals)
        self.filters = tuple(dict.fromkeys([self.primary, *self.extra]))
        self.clock_mode: str = vals["clock"]
        self.idle_flush: float = vals["idle_flush"]
        self.cal_duration: float = vals["calibration.duration"]
        self.cal_output: str = vals["calibration.output"]
        self.cal_timeout: float = vals["calibration.timeout"]
        self.cal_settings = calibration_settings(vals)
        self._vals = {k: vals[k] for k in ("local_chain", "init_samples", "static_links", "inputs")}
        d = vals["tf.diana_base"]
        self.T_base_diana = None if d is None else pose_to_T((np.asarray(d[:3]), np.asarray(d[3:])))
        health = health_params(vals)
        self.pipes: dict[str, TargetPipeline] = {}
        self.health: dict[str, TargetHealth] = {}
        self.routes: dict[str, list[Route]] = {}
        self.verdicts: dict[str, TargetVerdict] = {}
        self.last_rx: dict[str, dict[str, float | None]] = {}   # target -> device tag -> newest target sample
        self.last_target_rx = now                           # newest sample of any target's own body
        self.prefix: dict[str, str] = {}                    # device tag -> topic prefix
        self.local_k: dict[str, int] = {}                   # device tag -> local source index (omc: -1)
        self.diag_eval_at = now                             # the last diagnostics evaluation
        self._diag_sent = 0   # /diagnostics arrays sent before the last evaluation's values were set
        self._skipped_seen: dict[str, int] = {}
        self._link_state: dict[str, tuple[int | None, int]] = {}   # logged (bump start, recalibrations)
        self._static_key: tuple | None = None
        self._cal: CalibrationRun | None = None
        routed: dict[str, dict[str, list[str]]] = {}        # device tag -> body -> targets
        quality: dict[Key, str] = {}                        # (device tag, target body) -> its quality topic
        for t in self.targets:
            pipe = self.pipes[t] = make_pipeline(target_config(vals, t, self.filters))
            pipe.defer_side = True   # the side-by-side filters' work after the live outputs (side_outputs)
            c = pipe.config.chain
            extra_tools = "".join(f", {x.name} tool '{ch.cfg.ots_target}'" for x, ch in
                                  zip(pipe.config.sources.extras, pipe.extra_chains, strict=True))
            self.health[t] = TargetHealth(t, {GLOBAL: f"OMC body '{c.omc_target}'",
                                              LOCAL: f"OTS tool '{c.ots_target}'{extra_tools}"}, health,
                                             background=True)   # the stamp-offset estimate off the input thread
            self.verdicts[t] = TargetVerdict(t, vals["stale_timeout"], vals["problem_hold"])
            self._skipped_seen[t] = 0
            self._link_state[t] = (None, 0)
            rts = self.routes[t] = routes(pipe.config.sources, c, pipe.extra_chains)
            for r in rts:
                self.prefix[r.tag] = r.prefix
                self.local_k[r.tag] = r.k
                for b in r.bodies:
                    routed.setdefault(r.tag, {}).setdefault(b, []).append(t)
                quality.setdefault((r.tag, r.target),
                                   resolve(input_topic(r.prefix, r.target, "quality", vals["inputs"])))
            self.last_rx[t] = {r.tag: None for r in rts}
        self.targets_of = {d: {b: list(dict.fromkeys(ts)) for b, ts in r.items()} for d, r in routed.items()}
        self.quality_topics: dict[Key, str] = quality
        self.book = InputBook(quality, vals["stale_timeout"], vals["problem_hold"], vals["lag_warn"])
        self.topic_of: dict[Key, str] = {(d, b): topic for d, b, topic in self.pose_topics()}   # pose topics
        self.input_topics: dict[str, list[str]] = {   # target -> its pose and quality topics
            t: list(dict.fromkeys([*(self.topic_of[(r.tag, b)] for r in self.routes[t] for b in r.bodies),
                                   *(quality[(r.tag, r.target)] for r in self.routes[t])])) for t in self.targets}
        self._holding = False                     # a publisher of some input has no name yet: every input waits
        self._held: list[tuple] = []              # (topic, kind, args) held meanwhile, in arrival order
        self._released: list[tuple] = []          # held and then accepted: used first, in stamp order
        self.guard = InputGuard([*self.topic_of.values(), *quality.values()], vals["publishers.allow"] or (),
                                vals["problem_hold"])

    # ---- wiring -------------------------------------------------------------------------------------------------
    def pose_topics(self) -> list[tuple[str, str, str]]:
        """(device tag, body, resolved topic) of every pose stream a target uses: one per topic, or with ``inputs:
        frames`` each source's bodies topic for each of its bodies."""
        return [(dev, b, self._resolve(input_topic(self.prefix[dev], b, "pose", self._vals["inputs"])))
                for dev, rt in self.targets_of.items() for b in rt]

    def startup_message(self) -> str:
        links = next(iter(self.pipes.values())).chain.links
        given = "".join(f"{k} from {v}; " for k, v in links.sources.items())
        v = self._vals
        rest = (f"average of the first {v['init_samples']} samples" if v["static_links"] == "average"
                else f"calibrated over the first {self.cal_duration:g} s, average of the first samples meanwhile")
        return (f"fusing targets {self.targets} with {self.filters[0]} (side by side: {self.extra or 'none'}), "
                f"local chain '{v['local_chain']}', clock '{self.clock_mode}', static links: {given}"
                + (f"others: {rest}" if links.collecting else "all given"))

    # ---- input --------------------------------------------------------------------------------------------------
    def batch_key(self, item: tuple) -> tuple[int, bool]:
        """Sort key of an input batch's (stamp_ns, device, body, ...): stamp order, a link body's sample before a
        target sample of the same stamp."""
        return item[0], (item[1], item[2]) in self.book.loss

    def on_pose(self, dev: str, body: str, t_ns: int, p: np.ndarray, q: np.ndarray, now: float,
                clock_ns: int | None) -> list[str]:
        """Push one pose into the pipelines of the targets it feeds; returns those targets. ``clock_ns``: the node
        clock for the time guard (0 or None: not started, nothing checked)."""
        clock_ns = clock_ns or None
        topic = self.topic_of.get((dev, body), "")
        if self._hold(topic, "pose", (dev, body, t_ns, p, q)):
            return []
        if self._released:   # what was held, its publishers named and accepted since: first, in stamp order
            rel, self._released = self._released, []
            done: list[str] = []
            for kind, args in rel:
                if kind == "pose":
                    done += self.on_pose(*args, now, clock_ns)
                else:
                    self.quality(*args)
            return list(dict.fromkeys(done + self.on_pose(dev, body, t_ns, p, q, now, clock_ns)))
        if self._cal is not None and dev in ("omc", "ots"):
            self._cal.add(dev, body, t_ns, p, q)
        targets = self.targets_of.get(dev, {}).get(body, [])
        for t in targets:
            pipe = self.pipes[t]
            c = pipe.config.chain
            if dev == "omc":
                ok = pipe.push_omc(body, t_ns, (p, q), now_ns=clock_ns)
                if body == c.omc_target:
                    self._target_sample(t, "omc", GLOBAL, ok, now, t_ns, p)
            else:   # ots: the first local source; a further one by its index (sources.py)
                k = self.local_k[dev]
                ok = pipe.push_local(k, body, t_ns, (p, q), now_ns=clock_ns)
                if body == (c if k == 0 else pipe.extra_chains[k - 1].cfg).ots_target:
                    self._target_sample(t, dev, LOCAL, ok, now, t_ns, p)
        return targets

    def _target_sample(self, target: str, dev: str, source: str, accepted: bool, now: float, t_ns: int,
                       p: np.ndarray) -> None:
        self.last_rx[target][dev] = now
        self.last_target_rx = now
        h = self.health[target]
        if accepted:   # the stamp-offset watch pairs the global source with the first local one only
            h.accepted(source, now, t_ns, p if source == GLOBAL or self.local_k.get(dev) == 0 else None)
        else:   # the stamp of a sample refused for its pose times the run of refusals (fusion_health)
            h.rejected(source, now, (d := self.pipes[target].diag).last, t_ns=d.pose_refused(t_ns))

    def quality_rx(self, key: Key, now: float) -> None:
        """A quality callback of ``key`` ran at ``now`` (the stream is not silent)."""
        self.book.rx[key] = now

    def quality(self, key: Key, frame_number: int, t_ns: int, visible: bool, fit_error: float,
                markers_used: float) -> None:
        """One TrackingQuality of ``key``: the loss count; a visible OMC frame's quality to the pipelines of the
        targets of that body (the OMC model covariance of filters that use the models). Dropped on a closed topic."""
        if self._hold(self.quality_topics[key], "quality", (key, frame_number, t_ns, visible, fit_error, markers_used)):
            return
        self.book.loss[key].quality(frame_number, t_ns, visible)
        if key[0] == "omc" and visible:
            for t in self.targets_of["omc"].get(key[1], ()):
                self.pipes[t].push_omc_quality(key[1], t_ns, {"fit_error": fit_error, "markers_used": markers_used})

    def publishers_seen(self, topic: str, publishers: list[Publisher], now: float) -> list[Log]:
        """Discovery's publishers of an input topic ((node name, GID hex) each): the guard's verdict, log lines.
        Samples held while a publisher had no name are used (with the next sample) when it was named and accepted,
        else dropped."""
        logs = self.guard.update(topic, publishers, now)
        self._holding = any(self.guard.holding(x) for x in self.guard.topics)
        if not self._holding and self._held:   # everyone named: the accepted topics' samples, in stamp order
            held, self._held, keep = self._held, [], []
            for x, kind, args in held:
                if self.guard.is_open(x):
                    keep.append((kind, args))
                else:
                    self.guard.drop(x)
            self._released += sorted(keep, key=lambda r: (r[1][2], 1 + (tuple(r[1][:2]) in self.book.loss))
                                     if r[0] == "pose" else (r[1][2], 0))   # batch_key's order; a quality first
        return logs

    def _hold(self, topic: str, kind: str, args: tuple) -> bool:
        """True if a sample (``kind`` pose or quality) of ``topic`` is not to be used now: dropped (its topic is closed)
        or held (some input's publisher has no name yet; module docstring)."""
        if self._holding and (self.guard.is_open(topic) or self.guard.holding(topic)):
            if len(self._held) < HOLD_MAX:
                self._held.append((topic, kind, args))
                return True
        if self._holding or not self.guard.is_open(topic):
            self.guard.drop(topic)
            return True
        return False

    def input_done(self, batch: Sequence[tuple], delay_ns: int | None, clock_ns: int, now: float,
                   work_ns: int | None = None) -> bool:
        """The end of one input callback (:meth:`InputBook.callback`); True when the diagnostics' evaluation is a
        whole period late (an overloaded node runs input callbacks back to back and its executor no timer)."""
        self.book.callback(batch, delay_ns, clock_ns, now, work_ns)
        return now - self.diag_eval_at >= 2.0 * DIAG_EVAL_PERIOD_S

    def end_of_streams(self) -> None:
        """Shutdown: nothing more comes, the next diagnostics settle every lost-sample count."""
        self.book.end_of_streams()

    # ---- output -------------------------------------------------------------------------------------------------
    @property
    def needs_clock(self) -> bool:   # whether poll and due_outputs use the node clock (clock: host)
        return self.clock_mode == "host"

    def poll(self, target: str, clock_ns: int | None) -> list[FusedOutput]:
        """The outputs of ``target`` due after an input; ``clock_ns``: the node clock (used with ``clock: host``)."""
        return self.pipes[target].poll(clock_ns if self.needs_clock else None)

    def side_outputs(self, target: str, most: int | None = None) -> list[FusedOutput]:
        """Side-by-side outputs whose work waited for the live ones, of at most ``most`` items (ArrivalPipeline)."""
        return self.pipes[target].side_outputs(most)

    def side_backlog(self) -> dict[str, int]:   # target -> its items with deferred side-by-side work (arrival)
        return {t: n for t, p in self.pipes.items() if (n := getattr(p, "side_backlog", 0))}

    def due_outputs(self, now: float, clock_ns: int | None) -> Iterator[tuple[str, list[FusedOutput]]]:
        """The timer's flush policy (module docstring): (target, outputs) of every target with something due."""
        idle = now - self.last_target_rx > self.idle_flush
        for t, pipe in self.pipes.items():
            if isinstance(pipe, ArrivalPipeline):   # after idle_flush the history becomes final
                if idle and pipe.pending:
                    yield t, pipe.flush()
                elif pipe.waiting or pipe.side_backlog:   # a sample waiting for its partner, side-by-side work
                    yield t, pipe.poll() + pipe.side_outputs()
                continue
            if pipe.sync.pending == 0:
                continue
            yield t, (pipe.flush() if (idle and self.clock_mode == "stamps") else
                      pipe.poll(clock_ns if self.needs_clock else None))

    def flush_all(self) -> Iterator[tuple[str, list[FusedOutput]]]:
        """Shutdown: (target, outputs) of every target with something pending, all of it flushed."""
        for t, pipe in self.pipes.items():
            if pipe.pending if isinstance(pipe, ArrivalPipeline) else pipe.sync.pending:
                yield t, pipe.flush()

    def final_outputs(self, target: str) -> list[FusedOutput]:
        """The primary filter's outputs of the items that left ``target``'s history since the last call (arrival
        processing; the side-by-side filters' own topics carry their final estimates already)."""
        pipe = self.pipes[target]
        if not isinstance(pipe, ArrivalPipeline):
            return []
        return [o for o in pipe.take_final() if o.filter == self.primary]

    def note_skipped(self, target: str, now: float) -> None:
        """Before publishing: local samples the chain could not map since the last call count as rejected."""
        pipe = self.pipes[target]
        skipped = pipe.counts["local_skipped"]
        if skipped > self._skipped_seen[target]:
            self.health[target].rejected(LOCAL, now, pipe.problems.get("local_skipped", ""),
                                         skipped - self._skipped_seen[target])
            self._skipped_seen[target] = skipped

    def primary_output(self, target: str, now: float, o: FusedOutput) -> None:
        """One published output of the primary filter: its source bits, hop and bias to the health monitor."""
        self.health[target].output(now, o.sources, o.hop, o.bias)

    def publish_error(self, target: str, o: FusedOutput, why: str) -> None:
        """An output refused at publishing (non-finite pose): counted as the pipeline's ``publish_error``."""
        self.pipes[target].report_problem("publish_error", f"{o.filter}: {why}", o.t_ns)

    # ---- static links -------------------------------------------------------------------------------------------
    def static_links(self) -> list[StaticLink]:
        """(parent, child, T_parent_child) of the static links known now (the first target whose links are set)."""
        out: dict[str, StaticLink] = {}
        f = self.frames
        for pipe in self.pipes.values():
            L = pipe.chain.links
            if L.T_omc_base is not None:
                out.setdefault("base", (f.omc, f.base, L.T_omc_base))
            if L.T_base_ots is not None and pipe.config.chain.local_chain != "tracked":
                out.setdefault("ots", (f.base, f.ots, L.T_base_ots))
            for x, ch in zip(pipe.config.sources.extras, pipe.extra_chains, strict=True):   # base -> <source>
                if ch.links.T_base_ots is not None and ch.cfg.local_chain != "tracked":
                    out.setdefault(x.name, (f.base, x.name, ch.links.T_base_ots))
        if self.T_base_diana is not None:
            out["diana_base"] = (f.base, f.diana_base, self.T_base_diana)
        return list(out.values())

    def static_links_to_send(self) -> list[StaticLink] | None:
        """The static links when they differ from those returned last (first known, or one changed), else None."""
        links = self.static_links()
        key = tuple((p, c, T.tobytes()) for p, c, T in links)
        if not links or key == self._static_key:
            return None
        self._static_key = key
        return links

    def watch_links(self, target: str, now: float) -> list[Log]:
        """The start of a link bump, its end, and every re-calibration the monitor started, as log lines; the bump
        is remembered for the diagnostics (held ``problem_hold``)."""
        pipe = self.pipes[target]
        m = pipe.monitor
        start, n_recal = self._link_state[target]
        logs: list[Log] = []
        if m.bumped:
            self.verdicts[target].saw_bump(now, m.message(target))
            if m.first_bump_ns != start:
                logs.append(("warning", m.message(target)))
        elif start is not None and m.last is not None:
            logs.append(("info", m.message(target)))
        if pipe.counts["recalibrations"] > n_recal:
            logs.append(("warning", f"target '{target}': re-calibrating the static links over "
                                    f"{pipe.config.chain.calibration_duration_s:g} s after the bump; the old "
                                    "links stay in use meanwhile"))
        self._link_state[target] = (m.first_bump_ns if m.bumped else None, pipe.counts["recalibrations"])
        return logs

    # ---- services -----------------------------------------------------------------------------------------------
    def initialize(self) -> str:
        """~/initialize: every target re-estimates its static links from the next samples; the answer."""
        for pipe in self.pipes.values():
            pipe.request_initialize()
        c = next(iter(self.pipes.values())).config.chain
        how = (f"from the next {c.init_samples} samples per body" if c.static_links == "average" else
               f"by calibrating over the next {c.calibration_duration_s:g} s of sightings")
        return f"re-estimating static links of {list(self.pipes)} {how}; the previous links stay in use until then"

    @property
    def calibrating(self) -> bool:
        return self._cal is not None

    def start_calibration(self, now: float) -> tuple[bool, str]:
        """~/calibrate: start collecting the links the chain needs -> (True, the line to log); (False, why) while
        a run is going on already."""
        if self._cal is not None:
            return False, "a calibration is already running; call again when it has answered"
        c = next(iter(self.pipes.values())).config.chain
        links = links_needed(c)
        self._cal = CalibrationRun(links, CalibrationBodies.from_chain_config(c), self.cal_duration,
                                   self.cal_settings, now=now, timeout_s=self.cal_timeout,
                                   source="fusion_node ~/calibrate", background=True)
        return True, (f"~/calibrate: collecting {self.cal_duration:g} s of sightings for {list(links)}; keep the "
                      "OTS and the reference marker still")

    def finish_calibration(self, now: float) -> CalibrationAnswer | None:
        """Poll the run; when done (None before): refused -> links unchanged; else ``calibration.output`` is
        written first (if set; a write error keeps the links too) and the links of every target swapped in one
        step."""
        run = self._cal
        if run is None or not run.poll(now):
            return None
        self._cal = None
        if run.result is None:
            return CalibrationAnswer(False, f"calibration refused, links unchanged: {run.error}", "warning")
        cal = run.result
        written = ""
        if self.cal_output:
            try:
                save_calibration(self.cal_output, cal)
            except (OSError, ValueError) as e:
                return CalibrationAnswer(False, f"calibration not applied, links unchanged: cannot write "
                                                f"{self.cal_output}: {e}", "error")
            written = f"; written to {self.cal_output}"
        for pipe in self.pipes.values():
            pipe.apply_calibration(cal, "~/calibrate")
        return CalibrationAnswer(True, f"{summary(cal)}; links of {list(self.pipes)} swapped{written}", "info")

    # ---- run-time parameters ------------------------------------------------------------------------------------
    def apply_live(self, changes: dict[str, Any]) -> dict[str, Any]:
        """A run-time set of ``changes`` (name -> raw value): checked by :func:`check_live` (ParameterError naming the
        parameter and the check: nothing applied), then applied -- the alarm thresholds to every target's health
        monitor, ``lag_warn`` to the overload verdict. Returns the new values (the node applies ``status_rate``)."""
        new = check_live(self.vals, changes)
        health = health_params(new)
        for h in self.health.values():
            h.params = health
        self.book.lag_warn_s = new["lag_warn"]
        self.vals = new
        return new

    # ---- diagnostics --------------------------------------------------------------------------------------------
    def diagnostics(self, now: float, published: int) -> list[Status]:
        """One status per target (:mod:`fusion_verdict`); ``published``: /diagnostics arrays sent so far (the input
        load's report starts anew once the previous one went out)."""
        self.diag_eval_at = now
        self.book.load.begin_report(published > self._diag_sent)
        out = []
        for t, pipe in self.pipes.items():
            level, msgs, values = self.verdicts[t].evaluate(now, pipe, self.health[t], self.last_rx[t], self.primary)
            level = self.book.overload(now, self.routes[t], level, msgs, values)
            g_level, g_msgs, g_values = self.guard.status(self.input_topics[t], now)
            level, msgs = max(level, g_level), [*g_msgs, *msgs]   # a closed input first: it explains the rest
            values.update(g_values)
            out.append((f"target {t}", level, "; ".join(msgs) or "ok", values))
        self.book.load.reset_period()
        self._diag_sent = published
        return out
