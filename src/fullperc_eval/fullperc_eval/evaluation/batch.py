"""Batched replay of one bag (issue 16 item 6): the per-sample replay's result, computed on arrays.

Why: :func:`.replay.replay` pushes every message through
:class:`~fullperc_fusion.pipeline.ordered.TargetPipeline`, which validates it, maps it into ``base``, builds
:class:`~fullperc_fusion.filters.api.Measurement` objects and steps every filter once per item:
~1.3 s for a 28 s bag, 12k measurements/s, while decoding alone runs at ~200k/s.
Offline, the whole recording is known at once, so most of that work can be done on arrays:

1. decoding: the raw MCAP records of each topic decoded in bulk (:mod:`fullperc_eval.bag.fast_decode`) into
   arrays; nothing is built per message;
2. validation of every pose at once (stamp > 0, finite, quaternion within 1e-2 of unit norm: the tests of
   :func:`~fullperc_fusion.calibration.poses.pose_to_T`), and the target samples' matrices with pose_to_T's formulas;
3. the control flow in bag order, as the per-sample replay runs it, but only what decides something, through
   the pipeline's own stages (``TargetPipeline``'s "Stages": ``push_*`` without the validation done in step 2):
   its static-link estimation and link monitor (``observe_omc`` / ``observe_ots`` with the matrices of step 2 --
   the same code, so the links come from exactly the same samples; once the links are final, OMC base / rig
   samples change nothing and are skipped, the OTS's base sightings still feed the monitor, whose window means are
   computed together after the loop: ``defer_link_checks`` / ``resolve_link_checks``), its synchronizer
   under its stamp rules (``enqueue``, payload = the sample's index; ``poll_items`` / ``flush_items``) with the
   idle flush, and for each item the links in use when it came out;
4. mapping into ``base``: one stacked matrix product per link estimate and stream (``inv(T_omc_base) @ T``,
   ``T_base_ots @ T``), quaternions with :func:`~fullperc_common.transforms.T_to_pq`'s closed form vectorised;
5. filtering: :func:`fullperc_fusion.filters.paper_batch.run_closed_form` (KF/BKF/CKF/CBKF in one loop on floats) and
   the ``omc`` pass-through as a selection;
6. the outputs, the single-source tap, the counts and the warnings assembled as the per-sample replay does.

The result equals the per-sample replay's (test_batch.py: bit-identical outputs and identical evaluation on
the sample bags and synthetic streams). What it does not reproduce raises :class:`BatchUnsupported` and
:func:`.replay.replay` runs the per-sample path instead: a filter other than the paper's five (``fullperc``, a
re-registered name), a local chain other than ``static``, link re-calibration on a bump, further local sources or
fixed source noise (sources by configuration), a device covariance, any invalid sample (bad stamp, NaN,
non-unit quaternion), a late or duplicate sample, a refused static-link calibration, a bump seen by the link
monitor, a filter step that would raise, an output that is not finite,
joint states that are not 7 named positions, a record the bulk decoder cannot read.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np

from fullperc_common.transforms import T_to_pq, inv_T
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.fast_decode import DecodeError, decode_joint_states, decode_pose_stamped
from fullperc_eval.bag.reader import _raw_messages
from fullperc_fusion.filters.api import SOURCE_GLOBAL, SOURCE_LOCAL
from fullperc_fusion.filters.paper_batch import BatchUnsupported, run_closed_form
from fullperc_fusion.filters.paper_family import FILTER_KINDS
from fullperc_fusion.filters.registry import capabilities
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline
from fullperc_fusion.pipeline.sources import default_namespace
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL

from .config import EvaluationError
from .replay_data import JOINT_TOPIC, Prepared, Replay, _task_name

__all__ = ["BatchUnsupported", "batch_replay", "split_filters", "unsupported_reason"]

_UNIT_TOL = 1e-2   # pose_to_T's default


def _batched(f: str) -> bool:
    """True for a filter whose registry entry declares ``batch`` (the paper's five; a name registered to another
    implementation declares what that one supports)."""
    return capabilities(f).batch


def split_filters(config: TargetConfig) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(filters with a batched form, the others) of ``config``, each in the configured order."""
    fast = tuple(f for f in config.filters if _batched(f))
    return fast, tuple(f for f in config.filters if f not in fast)


def unsupported_reason(config: TargetConfig) -> str:
    """Why the batched replay cannot run ``config`` ('' when it can): see the module docstring."""
    for f in config.filters:
        if not _batched(f):
            return f"filter '{f}' has no batched form"
    c = config.chain
    if c.local_chain != "static":
        return f"local chain '{c.local_chain}' (batched: static only)"
    if config.monitor.recalibrate:
        return "link monitor re-calibration (links may change on a bump)"
    if c.omc_target in (c.omc_base, c.omc_rig) or c.ots_target == c.ots_base:
        return "a target body that is also a link body"
    src = config.sources   # sources by configuration: the built-in omc + ots pair only
    if src.extras:
        return "further local sources"
    if any(s.noise_std is not None for s in (src.glob, *src.locals)):
        return "a source with its own noise_std"
    # names as resolved in the default namespace (a bag records them absolute): omc and /omc are the same topics
    if tuple(default_namespace(s.topic_prefix).rstrip("/") for s in (src.glob, src.locals[0])) != ("/omc", "/ots"):
        return "sources on other topics"
    return ""


def _decode(prep: Prepared):
    """Per topic: (bag-order indices, decoded batch); the bag order as (topic index, index within topic)."""
    reader = prep.reader
    try:
        raw = _raw_messages(reader, prep.present)
    except BagError:
        raise
    except Exception as err:  # noqa: BLE001 - a decompressor's own error on a damaged chunk (e.g. ZstdError)
        raise EvaluationError(f"bag {str(reader.path)!r} is corrupt: {type(err).__name__}: {err}") from None
    per: dict[str, tuple] = {}
    for k, topic in enumerate(prep.present):
        idx = np.flatnonzero(raw.topic == k)
        typ = reader.topics[topic].msgtype
        recs = [raw.data[i] for i in idx]
        try:
            if topic == JOINT_TOPIC:
                per[topic] = (idx, decode_joint_states(recs, lambda d, ty=typ: reader.deserialize(d, ty)))
            else:
                per[topic] = (idx, decode_pose_stamped(recs, lambda d, ty=typ: reader.deserialize(d, ty)))
        except DecodeError as e:
            raise BatchUnsupported(f"{topic}: a record the bulk decoder cannot read ({e})") from None
    within = np.zeros(len(raw.topic), np.int64)
    for idx, _ in per.values():
        within[idx] = np.arange(len(idx))
    return raw, per, within


def _validate(pb) -> None:
    """pose_to_T's tests on every sample of one topic at once; BatchUnsupported on the first failure."""
    if pb.t_ns.size and not (pb.t_ns > 0).all():
        raise BatchUnsupported("a sample with an invalid stamp")
    if not (np.isfinite(pb.p).all() and np.isfinite(pb.q).all()):
        raise BatchUnsupported("a non-finite sample")
    if pb.q.size and not (np.abs(_norm(pb.q) - 1.0) <= _UNIT_TOL).all():
        raise BatchUnsupported("a non-unit quaternion")


def _norm(q: np.ndarray) -> np.ndarray:
    """np.linalg.norm of each row, bit for bit: the same BLAS dot per row (stacked matmul of a row and itself)."""
    return np.sqrt((q[:, None, :] @ q[:, :, None])[:, 0, 0])


def _matrices(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N, 4, 4) transforms with pose_to_T's arithmetic: q / numpy norm, then quat_to_R_rows (normalise again)."""
    n1 = _norm(q)
    x, y, z, w = (q[:, 0] / n1, q[:, 1] / n1, q[:, 2] / n1, q[:, 3] / n1)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    T = np.zeros((len(p), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = 2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = 2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T


def _to_pq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_to_pq of each transform: R_to_quat's closed form vectorised (same branches, same operations); rows where
    it defers to scipy (not orthogonal to its tolerance, det <= 0, non-finite) go through T_to_pq itself."""
    a, b, c = T[:, 0, 0], T[:, 0, 1], T[:, 0, 2]
    d, e, f = T[:, 1, 0], T[:, 1, 1], T[:, 1, 2]
    g, h, i = T[:, 2, 0], T[:, 2, 1], T[:, 2, 2]
    tol_d = 1e-12 + 1e-5
    ok = ((np.abs(a * a + b * b + c * c - 1.0) <= tol_d) & (np.abs(d * d + e * e + f * f - 1.0) <= tol_d)
          & (np.abs(g * g + h * h + i * i - 1.0) <= tol_d) & (np.abs(a * d + b * e + c * f) <= 1e-12)
          & (np.abs(a * g + b * h + c * i) <= 1e-12) & (np.abs(d * g + e * h + f * i) <= 1e-12))
    ok &= a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0.0
    tr = a + e + i
    k = np.zeros(len(T), np.int64)
    best = a.copy()
    m = e > best
    k[m], best[m] = 1, e[m]
    m = i > best
    k[m], best[m] = 2, i[m]
    k[tr > best] = 3
    cand = np.stack([
        np.stack([1 - tr + 2 * a, d + b, g + c, h - f], axis=1),
        np.stack([b + d, 1 - tr + 2 * e, h + f, c - g], axis=1),
        np.stack([c + g, f + h, 1 - tr + 2 * i, d - b], axis=1),
        np.stack([h - f, c - g, d - b, 1 + tr], axis=1)])
    qq = cand[k, np.arange(len(T))]
    x, y, z, w = qq[:, 0], qq[:, 1], qq[:, 2], qq[:, 3]
    n = np.sqrt(x * x + y * y + z * z + w * w)
    q = np.stack([x / n, y / n, z / n, w / n], axis=1)
    ok &= np.isfinite(q).all(axis=1)
    q[q[:, 3] < 0] *= -1.0
    P = T[:, :3, 3].copy()
    for r in np.flatnonzero(~ok):
        P[r], q[r] = T_to_pq(T[r])
    return P, q


def batch_replay(prep: Prepared, config: TargetConfig, idle_flush_s: float, t_start: float) -> Replay:
    """The per-sample replay's :class:`Replay` of the prepared bag, batched (module docstring); BatchUnsupported
    when it cannot be (the caller then runs the per-sample replay)."""
    why = unsupported_reason(config)
    if why:
        raise BatchUnsupported(why)
    reader = prep.reader
    c = config.chain
    try:
        raw, per, within = _decode(prep)
    except BagError as e:
        raise BatchUnsupported(f"decoding: {e}") from None
    finally:
        reader.close()
    warnings = list(prep.warnings)
    # ---- joint states (ground truth): 7 named positions each, else the per-sample path says what is wrong
    jidx, jb = per[JOINT_TOPIC]
    from fullperc_drivers.diana_kinematics import JOINT_NAMES

    names0 = jb.names[0] if jb.names else None
    if len(jb.t_ns) < 2 or any(len(q) != 7 for q in jb.position) or \
            any((nm or []) and nm != names0 for nm in jb.names) or (names0 and names0 != list(JOINT_NAMES)):
        raise BatchUnsupported("joint states that are not 7 named positions")
    # ---- pose topics: validated at once
    role: dict[str, tuple[str, str]] = {}
    for t, body in prep.omc_topics.items():
        role[t] = ("omc", body)
    for t, tool in prep.ots_topics.items():
        role[t] = ("ots", tool)
    poses = {t: per[t][1] for t in prep.present if t != JOINT_TOPIC}
    for pb in poses.values():
        _validate(pb)
    for pb in poses.values():
        if not np.array_equal(np.unique(pb.t_ns), np.sort(pb.t_ns)):
            raise BatchUnsupported("duplicate stamps in a stream")
    topic_names = prep.present
    ots_target_topic = f"/ots/{c.ots_target}/pose"
    # frame ids: the first message of each device in bag order, as the per-sample loop checks them
    first: dict[str, tuple[int, str]] = {}
    for t in poses:
        dev = role[t][0]
        i0 = int(per[t][0][0]) if len(per[t][0]) else None
        if i0 is not None and (dev not in first or i0 < first[dev][0]):
            first[dev] = (i0, t)
    for dev, (_, t) in sorted(first.items(), key=lambda kv: kv[1][0]):
        fid = poses[t].frame_id[0]
        if fid != dev:
            warnings.append(f"{t}: frame_id '{fid}', expected '{dev}'")

    # ---- control flow in bag order: links (the pipeline's own estimation and monitor), synchronizer, idle flush
    pipe = TargetPipeline(config)
    pipe.defer_link_checks()   # the monitor's window means computed together after the loop (the same checks)
    links = pipe.chain.links
    # what fusing the items would count (TargetPipeline.poll), in the order of the first increment as a
    # Counter keeps it: the per-sample pipeline's key order
    counted: Counter[str] = Counter()
    kind_of = []   # per topic index: 0 joint, 1 target global, 2 target local, 3 omc link body, 4 ots base
    for t in topic_names:
        if t == JOINT_TOPIC:
            kind_of.append(0)
        elif t == prep.target_omc:
            kind_of.append(1)
        elif t == ots_target_topic:
            kind_of.append(2)
        else:
            kind_of.append(3 if role[t][0] == "omc" else 4)
    stamps = {k: poses[t].t_ns.tolist() for k, t in enumerate(topic_names) if t != JOINT_TOPIC}
    idle_ns = int(idle_flush_s * 1e9)
    last_recv: int | None = None
    # emitted items: (global index or -1, local index or -1, T_omc_base in use, T_base_ots in use)
    emitted: list[tuple[int, int, np.ndarray | None, np.ndarray | None]] = []

    def take(items) -> None:
        Tob, Tbo = links.T_omc_base, links.T_base_ots
        for it in items:
            ig = -1 if it.glob is None else it.glob.payload
            il = -1 if it.local is None else it.local.payload
            use_g = ig >= 0 and Tob is not None
            use_l = il >= 0 and Tbo is not None
            if ig >= 0 and not use_g:
                counted["waiting_for_links"] += 1
            if il >= 0 and not use_l:
                counted["waiting_for_links"] += 1
            if not (use_g or use_l):
                continue
            counted["items"] += 1
            emitted.append((ig if use_g else -1, il if use_l else -1, Tob if use_g else None, Tbo if use_l else None))

    what = {1: f"OMC body '{c.omc_target}'", 2: f"OTS tool '{c.ots_target}'"}
    # the target samples' positions as 3x4 [0 | p] blocks: what admit's plausibility check reads of a pose
    tpos: dict[int, np.ndarray] = {}
    for k, t in enumerate(topic_names):
        if kind_of[k] in (1, 2):
            tpos[k] = np.zeros((len(poses[t].p), 3, 4))
            tpos[k][:, :, 3] = poses[t].p
    mats = {k: list(_matrices(poses[t].p, poses[t].q)) for k, t in enumerate(topic_names) if kind_of[k] >= 3}
    # the messages other than joint states, in bag order (the joint states only feed the ground truth)
    kind_arr = np.asarray(kind_of, dtype=np.int64)[raw.topic] if len(kind_of) else np.zeros(0, np.int64)
    sel = np.flatnonzero(kind_arr != 0)
    admit, poll_items = pipe.admit, pipe.poll_items
    for kind, k, j, recv in zip(kind_arr[sel].tolist(), raw.topic[sel].tolist(), within[sel].tolist(),
                                raw.timestamp[sel].tolist(), strict=True):
        if kind <= 2:
            if last_recv is not None and recv - last_recv > idle_ns and pipe.sync.pending:
                take(pipe.flush_items())
            last_recv = recv
            if not admit(GLOBAL if kind == 1 else LOCAL, stamps[k][j], tpos[k][j], None, what[kind], j):
                raise BatchUnsupported(f"a sample the pipeline did not take: {dict(pipe.counts)}")
            items = poll_items()
            if items:
                take(items)
            continue
        if kind == 3 and not links.collecting:
            continue   # final links: an OMC base / rig sample changes nothing any more
        name = topic_names[k]
        t, T = stamps[k][j], mats[k][j]
        # push_omc / push_ots of a link body, minus the validation done above: the chain's own link estimation,
        # then (OTS base) the link monitor
        if kind == 3:
            pipe.observe_omc(role[name][1], t, T)
        else:
            pipe.observe_ots(role[name][1], t, T)
        if links.refusals:
            raise BatchUnsupported("a static-link calibration was refused")
    take(pipe.flush_items())
    pipe.resolve_link_checks()
    if pipe.counts["link_bumped_checks"]:
        raise BatchUnsupported("the link monitor saw a bump of the static link")
    if pipe.sync.counts.get("forced_by_overflow"):
        raise BatchUnsupported("synchronizer overflow")
    if pipe.counts:
        raise BatchUnsupported(f"pipeline events {sorted(pipe.counts)}")
    return _assemble(prep, config, pipe, counted, emitted, poses, per, jb, warnings, raw, t_start, reader)


def _assemble(prep: Prepared, config: TargetConfig, pipe: TargetPipeline, counted: Counter[str], emitted, poses,
              per, jb, warnings: list[str], raw, t_start: float, reader) -> Replay:
    """Mapping, filters, outputs, tap, counts (steps 4-6 of the module docstring)."""
    c = config.chain
    pg = poses[prep.target_omc]
    ots_t = f"/ots/{c.ots_target}/pose"
    pl = poses.get(ots_t)
    n = len(emitted)
    ig = np.array([e[0] for e in emitted], np.int64)
    il = np.array([e[1] for e in emitted], np.int64)
    has_g, has_l = ig >= 0, il >= 0
    # ---- mapping into base: one stacked product per link estimate in use
    gp, gq = np.zeros((n, 3)), np.zeros((n, 4))
    lp, lq = np.zeros((n, 3)), np.zeros((n, 4))
    for which, has, idx, src, pos in ((0, has_g, ig, pg, 2), (1, has_l, il, pl, 3)):
        if not has.any():
            continue
        rows = np.flatnonzero(has)
        links_used = [emitted[r][pos] for r in rows.tolist()]
        groups: dict[int, list[int]] = {}
        objs: dict[int, np.ndarray] = {}
        for r, L in zip(rows.tolist(), links_used, strict=True):
            groups.setdefault(id(L), []).append(r)
            objs[id(L)] = L
        for key, rs in groups.items():
            rr = np.array(rs, np.int64)
            T_dev = _matrices(src.p[idx[rr]], src.q[idx[rr]])
            A = inv_T(objs[key]) if which == 0 else objs[key]
            P, Q = _to_pq(A @ T_dev)
            if which == 0:
                gp[rr], gq[rr] = P, Q
            else:
                lp[rr], lq[rr] = P, Q
    g_t = np.where(has_g, pg.t_ns[np.maximum(ig, 0)], 0) if n else np.zeros(0, np.int64)
    l_t = np.where(has_l, pl.t_ns[np.maximum(il, 0)], 0) if (n and pl is not None) else np.zeros(n, np.int64)
    outputs = filter_outputs(config, config.filters, has_g, has_l, g_t, l_t, gp, gq, lp, lq)
    # ---- the single-source tap (sources.SourceTap.arrays): each measurement fed, one row per stamp, by stamp
    single = {}
    for role_name, has, tt, pp, qq in (("global", has_g, g_t, gp, gq), ("local", has_l, l_t, lp, lq)):
        t_sel = tt[has]
        o = np.argsort(t_sel, kind="stable")
        single[role_name] = {"t_ns": t_sel[o].astype(np.int64), "p": pp[has][o].reshape(-1, 3),
                             "q": qq[has][o].reshape(-1, 4)}
    # ---- stats as the per-sample pipeline gives them: its own, then its counters (none of its own here: any
    # event made the batched replay give up), in the order of their first increment
    stats = {**pipe.stats(), **counted}
    stats = {k: (v if isinstance(v, int | float | str | bool) else str(v)) for k, v in stats.items()}
    counts = {t: int(len(per[t][0])) for t in prep.present}
    base_t = f"/omc/{c.omc_base}/pose"
    base_poses = list(zip(poses[base_t].p, poses[base_t].q, strict=True)) if base_t in poses else []
    rep = Replay(bag=reader.path, task=_task_name(reader), start_ns=reader.start_time, outputs=outputs,
                 joint_t_ns=np.asarray(jb.t_ns, np.int64), joint_q=np.asarray(jb.position, float),
                 omc_base_poses=base_poses, counts=counts, pipeline_stats=stats, warnings=warnings,
                 messages=int(len(raw.topic)), seconds=time.perf_counter() - t_start, single_sources=single)
    rep.path = "batched"
    return rep


def filter_outputs(config: TargetConfig, filters, has_g: np.ndarray, has_l: np.ndarray, g_t: np.ndarray,
                   l_t: np.ndarray, gp: np.ndarray, gq: np.ndarray, lp: np.ndarray,
                   lq: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """The outputs (:meth:`.replay.Outputs.arrays`) of ``filters`` (the paper's five) over the items, given per
    item which samples were fused (``has_g`` / ``has_l``), their stamps and positions / quaternions in base:
    what TargetPipeline.poll makes of each filter's step (orientation and its covariance from the local
    sample when there is one, else the global one; ``omc`` only where a global sample was fused)."""
    n = len(has_g)
    t_item = np.maximum(np.where(has_g, g_t, np.iinfo(np.int64).min), np.where(has_l, l_t, np.iinfo(np.int64).min))
    # ---- filters
    kf = [f for f in filters if f in FILTER_KINDS]
    hg, hl = has_g.tolist(), has_l.tolist()
    res = run_closed_form(kf, config.params, t_item.tolist(),
                          [t if h else None for t, h in zip(g_t.tolist(), hg, strict=True)],
                          [p if h else None for p, h in zip(gp.tolist(), hg, strict=True)],
                          [t if h else None for t, h in zip(l_t.tolist(), hl, strict=True)],
                          [p if h else None for p, h in zip(lp.tolist(), hl, strict=True)])
    std_g, std_l = config.orientation_std_global, config.orientation_std_local
    outputs: dict[str, dict[str, np.ndarray]] = {}
    for f in filters:
        if f == "omc":
            sel = has_g
            m = int(sel.sum())
            cov = np.zeros((m, 6, 6))
            cov[:, 0:3, 0:3] = np.eye(3) * config.params.global_std**2
            cov[:, 3:6, 3:6] = np.eye(3) * std_g**2
            o = {"t_ns": g_t[sel].astype(np.int64), "p": gp[sel].copy(),
                 "sources": np.full(m, SOURCE_GLOBAL, np.int64), "hop": np.zeros(m, bool), "bias": np.zeros((m, 3)),
                 "q": gq[sel].copy(), "cov": cov, "orientation_source": np.full(m, SOURCE_GLOBAL, np.int64)}
        else:
            r = res[f]
            cov = np.zeros((n, 6, 6))
            cov[:, [0, 1, 2], [0, 1, 2]] = r.pos_var
            cov[:, 3:6, 3:6] = np.where(has_l[:, None, None], np.eye(3) * std_l**2, np.eye(3) * std_g**2)
            o = {"t_ns": t_item.astype(np.int64), "p": r.p, "sources": r.sources, "hop": r.hop, "bias": r.bias,
                 "q": np.where(has_l[:, None], lq, gq), "cov": cov,
                 "orientation_source": np.where(has_l, SOURCE_LOCAL, SOURCE_GLOBAL).astype(np.int64)}
        if not (np.isfinite(o["p"]).all() and np.isfinite(o["cov"]).all() and np.isfinite(o["q"]).all()):
            raise BatchUnsupported(f"a non-finite output of {f}")
        outputs[f] = o
    return outputs


class ItemTap:
    """Records each item's measurements as the filters get them (a do-nothing filter, like sources.SourceTap).

    Why: with a filter that has no batched form (``fullperc``) the per-sample pipeline has to run anyway; with this
    tap in its filter table the paper's five need not be stepped there: :meth:`outputs` runs them batched over the
    recorded items afterwards (:func:`filter_outputs`), the same result, without their per-sample cost.
    """

    kind = "item_tap"
    NAME = "_item_tap"   # its key in TargetPipeline.filters: not a registry name, never configured or output

    def __init__(self) -> None:
        self.items: list[tuple] = []

    def reset(self) -> None:
        """Nothing to forget: the record is the evaluation's, not a state."""

    def predict(self, t_ns: int) -> None:
        """No state to move."""

    def update(self, *measurements) -> None:
        mg = next((m for m in measurements if m.source == SOURCE_GLOBAL), None)
        ml = next((m for m in measurements if m.source == SOURCE_LOCAL), None)
        self.items.append((mg, ml))
        return None

    def snapshot(self) -> int:
        return len(self.items)

    def restore(self, snap: int) -> None:
        del self.items[int(snap):]

    def outputs(self, config: TargetConfig, filters) -> dict[str, dict[str, np.ndarray]]:
        """``filters``' outputs over the recorded items; BatchUnsupported where a measurement carries a covariance
        (the closed form's fixed noise would not apply)."""
        n = len(self.items)
        has_g = np.array([g is not None for g, _ in self.items], bool)
        has_l = np.array([m is not None for _, m in self.items], bool)
        g_t, l_t = np.zeros(n, np.int64), np.zeros(n, np.int64)
        gp, gq, lp, lq = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3)), np.zeros((n, 4))
        for i, (mg, ml) in enumerate(self.items):
            for m, tt, pp, qq in ((mg, g_t, gp, gq), (ml, l_t, lp, lq)):
                if m is None:
                    continue
                if m.cov is not None or m.q is None:
                    raise BatchUnsupported("a measurement with a covariance or without orientation")
                tt[i], pp[i], qq[i] = m.t_ns, m.p, m.q
        return filter_outputs(config, filters, has_g, has_l, g_t, l_t, gp, gq, lp, lq)
