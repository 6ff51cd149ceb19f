"""Replay of one bag: the raw driver topics through the fusion pipeline the way ``fusion_node`` runs it.

:func:`replay` reads the raw driver topics (``/omc/<body>/pose``, ``/ots/<tool>/pose``, ``/diana/joint_states``)
with :class:`fullperc_eval.bag.reader.BagReader`, in bag (receive) order, and feeds them into one
:class:`fullperc_fusion.pipeline.ordered.TargetPipeline` running every method side by side, pushing and polling like the
node does in its default ``clock: stamps`` mode (including its idle flush, emulated on bag time), so offline and
live give the same poses. By default it runs batched (:mod:`.batch`, the same result on arrays, falling back to
the message-by-message replay where it must; ``per_sample=True`` forces the latter). :func:`live_replay` instead
reads the fused poses ``fusion_node`` published live. The :class:`Replay` and the bag checks are in :mod:`.replay_data`.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.fast_decode import DecodeError, decode_tracking_quality
from fullperc_eval.bag.reader import BagReader, _raw_messages, decoded_messages, undecodable
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

from .config import METHODS, EvaluationError
from .on_time import on_time_order
from .replay_data import JOINT_TOPIC, JOINT_TYPE, POSE_TYPE, Outputs, Prepared, Replay, _stamp_ns, _task_name, prepare
from .sources import SourceTap

__all__ = ["JOINT_TOPIC", "JOINT_TYPE", "POSE_TYPE", "Outputs", "Prepared", "Replay", "live_replay",
           "omc_quality_by_stamp", "prepare", "replay"]

PROGRESS_EVERY_S = 2.0


def omc_quality_by_stamp(reader: BagReader, config: TargetConfig) -> dict[int, dict[str, float]]:
    """H3 hook (issue 18, fullperc): the OMC target body's TrackingQuality by header stamp, for
    ``push_omc(quality=...)``, so a filter that declares ``models`` gets the OMC model covariance offline as live.
    Empty when no configured filter uses the models or the bag has no quality topic."""
    from fullperc_fusion.filters.registry import FILTERS

    topic = f"/omc/{config.chain.omc_target}/quality"
    if topic not in reader.topics or not any(FILTERS[f].caps.models for f in config.filters if f in FILTERS):
        return {}
    # bulk-decoded (bag.fast_decode: the same values as rosbags' deserializer), in bag order: a later sample of a
    # stamp replaces an earlier one, as reading message by message did (that was a tenth of the replay's time)
    typ = reader.topics[topic].msgtype
    try:
        raw = _raw_messages(reader, [topic])
        qb = decode_tracking_quality(raw.data, lambda d: reader.deserialize(d, typ))
    except DecodeError as e:
        raise undecodable(reader, topic, typ, e) from None
    finally:
        reader.close()
    return {t: {"fit_error": fe, "markers_used": float(mu)}
            for t, fe, mu in zip(qb.t_ns.tolist(), qb.fit_error.tolist(), qb.markers_used.tolist(), strict=True)}


def replay(bag: str | Path, config: TargetConfig, idle_flush_s: float = 0.5, progress: bool = True,
           per_sample: bool = False, reader: BagReader | None = None, on_time: bool = False) -> Replay:
    """Run the pipeline over the raw measurements of ``bag`` the way fusion_node would have.

    By default through the batched replay (:mod:`.batch`: vectorised decoding, validation, mapping and the paper's
    filters in one loop -- the same result). Filters it has no batched form for (``fullperc``) are run per sample
    on their own and their outputs merged (filters are independent of one another; the per-sample run gives the
    counts, warnings and tap, which do not depend on the filters); anything else it does not support falls back to
    the per-sample replay of every filter (``Replay.fallback`` says why). ``per_sample`` forces the per-sample
    replay. ``reader``: the bag already opened (its metadata is not read again). ``on_time``: a pose sample the
    recorder got more than ``history`` (or the reorder window, if shorter) behind the others is fed where it would
    have been on time, and the idle flush follows the stamps (:mod:`.on_time`: the node's live estimates against the
    replay of its inputs); it runs per sample."""
    t_start = time.perf_counter()
    prep = prepare(bag, config, reader)
    fallback = "on-time order requested" if on_time else "per-sample replay requested"
    if not per_sample and not on_time:
        from .batch import BatchUnsupported, ItemTap, batch_replay, split_filters, unsupported_reason

        fast, slow = split_filters(config)
        try:
            if not slow:
                return batch_replay(prep, config, idle_flush_s, t_start)
            if fast and not unsupported_reason(dataclasses.replace(config, filters=fast)):
                tap = ItemTap()
                rep = _per_sample_replay(prep, dataclasses.replace(config, filters=slow), idle_flush_s, progress,
                                         t_start, taps={ItemTap.NAME: tap})
                fast_out = tap.outputs(config, fast)
                rep.outputs = {f: (fast_out if f in fast else rep.outputs)[f] for f in config.filters}
                rep.path, rep.seconds = "batched+per-sample", time.perf_counter() - t_start
                rep.fallback = f"per sample: {', '.join(slow)} (no batched form)"
                return rep
            fallback = f"no batched form for {', '.join(slow)}"
        except BatchUnsupported as e:
            fallback = str(e)
        if progress:   # why this bag takes the slow path (evaluate prints progress unless --quiet)
            print(f"note: per-sample replay of {Path(bag).name}: {fallback}", file=sys.stderr, flush=True)
        prep = prepare(bag, config)   # a fresh reader: the batched attempt may have read part of the bag
    rep = _per_sample_replay(prep, config, idle_flush_s, progress, t_start, on_time=on_time)
    rep.fallback = fallback
    return rep


def _per_sample_replay(prep: Prepared, config: TargetConfig, idle_flush_s: float, progress: bool,
                       t_start: float, taps: dict[str, Any] | None = None, on_time: bool = False) -> Replay:
    """The replay one message at a time through :class:`TargetPipeline` (the reference); ``taps``: further
    do-nothing filters that record what the filters get (batch.ItemTap); ``on_time``: see :func:`replay`."""
    reader, omc_topics, ots_topics, target_omc = prep.reader, prep.omc_topics, prep.ots_topics, prep.target_omc
    present, total, warnings = prep.present, prep.total, prep.warnings
    c = config.chain
    pipe = TargetPipeline(config)
    omc_quality = omc_quality_by_stamp(reader, config)   # H3 hook: OMC quality for fullperc's model covariance
    tap = SourceTap()   # hook: records the measurements the filters get (raw local chain for the evaluation)
    pipe.filters[SourceTap.NAME] = tap
    pipe.filters.update(taps or {})
    outs = {f: Outputs() for f in config.filters}
    joint_t: list[int] = []
    joint_q: list[np.ndarray] = []
    base_poses: list[np.ndarray] = []
    counts = {t: 0 for t in present}
    frames = {"omc": None, "ots": None}
    idle_ns = int(idle_flush_s * 1e9)
    last_target_at: int | None = None   # receive time (on_time: stamp) of the newest target sample
    joint_names: list[str] | None = None
    n = 0
    last_print = time.monotonic()

    def take(items) -> None:
        for o in items:
            r = outs[o.filter]
            r.t_ns.append(o.t_ns)
            r.p.append(o.p)
            r.sources.append(o.sources)
            r.hop.append(o.hop)
            r.bias.append(o.bias)
            r.q.append(o.q)
            r.cov.append(o.cov)
            r.orientation_source.append(o.orientation_source)

    try:
        # bulk-decoded (bag.fast_decode), in bag order; rosbags is opened only if a record needs it
        messages = decoded_messages(reader, present)
        if on_time:
            bound = min(config.history_ns, 2 * config.slop_ns + config.delay_ns)
            messages, moved = on_time_order(messages, {*omc_topics, *ots_topics}, bound)
            if moved:
                warnings.append(f"on time: {moved} samples the recorder got over {bound * 1e-9:g} s behind newer "
                                "ones fed where they would have been on time")
        for m in messages:
            n += 1
            counts[m.topic] += 1
            if m.topic == JOINT_TOPIC:
                names = m.names or []
                if joint_names is None:
                    joint_names = names
                q = m.position
                if names and names != joint_names:
                    raise EvaluationError(f"{JOINT_TOPIC}: joint names changed from {joint_names} to {names}")
                if q.shape != (7,):
                    raise EvaluationError(f"{JOINT_TOPIC}: expected 7 joint positions, got {q.shape[0]}")
                joint_t.append(m.t_ns)
                joint_q.append(q)
                continue
            t_ns = m.t_ns
            pose = (m.p, m.q)
            dev = "omc" if m.topic in omc_topics else "ots"
            if frames[dev] is None:
                frames[dev] = m.frame_id
                if m.frame_id != dev:
                    warnings.append(f"{m.topic}: frame_id '{m.frame_id}', expected '{dev}'")
            is_target = m.topic == target_omc or m.topic == f"/ots/{c.ots_target}/pose"
            if is_target:
                # fusion_node's idle flush: no target sample for idle_flush seconds -> process everything pending
                # (on_time: on the stamps, the timeline of a node that received every sample in time; on_time.py)
                at = t_ns if on_time else m.timestamp
                if last_target_at is not None and pipe.sync.pending and at - last_target_at > idle_ns:
                    take(pipe.flush())
                if on_time and last_target_at is not None:   # a moved sample's older stamp does not go back
                    at = max(at, last_target_at)
                last_target_at = at
            if dev == "omc":
                body = omc_topics[m.topic]
                pipe.push_omc(body, t_ns, pose, quality=omc_quality.get(t_ns) if body == c.omc_target else None)
                if body == c.omc_base:
                    base_poses.append(pose)
            else:
                pipe.push_ots(ots_topics[m.topic], t_ns, pose)
            take(pipe.poll())
            if progress and time.monotonic() - last_print >= PROGRESS_EVERY_S:
                last_print = time.monotonic()
                print(f"  {reader.path.name}: {n}/{total} messages ({100.0 * n / max(total, 1):.0f} %)",
                      file=sys.stderr, flush=True)
        take(pipe.flush())
    except BagError as e:
        raise EvaluationError(str(e)) from None
    finally:
        reader.close()
    if len(joint_t) < 2:
        raise EvaluationError(f"bag {str(reader.path)!r}: fewer than 2 joint states; no ground truth")
    if joint_names and len(joint_names) == 7:
        from fullperc_drivers.diana_kinematics import JOINT_NAMES

        if joint_names != list(JOINT_NAMES):
            raise EvaluationError(f"{JOINT_TOPIC}: joint names {joint_names}, expected {list(JOINT_NAMES)}")
    stats = pipe.stats()
    stats = {k: (v if isinstance(v, int | float | str | bool) else str(v)) for k, v in stats.items()}
    for key, why in pipe.problems.items():
        warnings.append(f"pipeline {key} ({pipe.counts[key]}x): {why}")
    return Replay(bag=reader.path, task=_task_name(reader), start_ns=reader.start_time,
                  outputs={f: o.arrays() for f, o in outs.items()}, joint_t_ns=np.asarray(joint_t, np.int64),
                  joint_q=np.asarray(joint_q, float), omc_base_poses=base_poses, counts=counts,
                  pipeline_stats=stats, warnings=warnings, messages=n, seconds=time.perf_counter() - t_start,
                  single_sources=tap.arrays())


def live_replay(bag: str | Path, target: str = "tool", primary: str = "cbkf", base_body: str = "base") -> Replay:
    """The fused poses that ``fusion_node`` published live and ``record`` stored, as a :class:`Replay`.

    ``--live`` evaluates these instead of re-running the filters, so a recording of the live graph can be
    compared with the offline replay of its own raw measurements (the demo and the system test do).
    Method ``f`` is read from ``/fullperc/<target>/<f>/pose`` (with fusion_node's processing on arrival the
    side-by-side filters publish final estimates there); the primary filter also from ``/fullperc/<target>/final``
    when recorded (arrival: its estimates once final, equal to the offline replay), else ``/fullperc/<target>/pose``.
    Sources, hop flags and biases are not in the pose topics (zeros here).
    """
    t_start = time.perf_counter()
    try:
        reader = BagReader(bag)
    except BagError as e:
        raise EvaluationError(str(e)) from None

    topics = {f"/fullperc/{target}/{f}/pose": f for f in METHODS}
    if f"/fullperc/{target}/{primary}/pose" not in reader.topics:
        final = f"/fullperc/{target}/final"
        topics[final if final in reader.topics else f"/fullperc/{target}/pose"] = primary
    present = [t for t in (*topics, JOINT_TOPIC, f"/omc/{base_body}/pose") if t in reader.topics]
    if not any(t in reader.topics for t in topics):
        raise EvaluationError(f"bag {str(reader.path)!r} holds no fused poses /fullperc/{target}/.../pose "
                              "(was fusion_node recorded?)")
    outs = {f: Outputs() for f in dict.fromkeys(topics[t] for t in topics if t in reader.topics)}
    joint_t: list[int] = []
    joint_q: list[np.ndarray] = []
    base_poses: list[tuple[np.ndarray, np.ndarray]] = []
    counts = {t: 0 for t in present}
    try:
        reader.open()
        for m in reader.messages(present):
            counts[m.topic] += 1
            msg = reader.deserialize(m.data, m.msgtype)
            if m.topic == JOINT_TOPIC:
                joint_t.append(_stamp_ns(msg.header))
                joint_q.append(np.asarray(msg.position, dtype=float))
                continue
            pp, qq = msg.pose.position, msg.pose.orientation
            p = np.array([pp.x, pp.y, pp.z])
            if m.topic in topics:
                o = outs[topics[m.topic]]
                o.t_ns.append(_stamp_ns(msg.header))
                o.p.append(p)
                o.sources.append(0)
                o.hop.append(False)
                o.bias.append(np.zeros(3))
                o.q.append(np.array([qq.x, qq.y, qq.z, qq.w]))
                o.cov.append(np.full((6, 6), np.nan))   # a PoseStamped carries no covariance
                o.orientation_source.append(0)
            else:
                base_poses.append((p, np.array([qq.x, qq.y, qq.z, qq.w])))
    except BagError as e:
        raise EvaluationError(str(e)) from None
    finally:
        reader.close()
    if len(joint_t) < 2:
        raise EvaluationError(f"bag {str(reader.path)!r}: fewer than 2 joint states; no ground truth")
    return Replay(bag=reader.path, task=_task_name(reader), start_ns=reader.start_time,
                  outputs={f: o.arrays() for f, o in outs.items()}, joint_t_ns=np.asarray(joint_t, np.int64),
                  joint_q=np.asarray(joint_q, float), omc_base_poses=base_poses, counts=counts,
                  pipeline_stats={}, warnings=[], messages=sum(counts.values()),
                  seconds=time.perf_counter() - t_start)
