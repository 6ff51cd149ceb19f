"""``evaluate``: offline evaluation of one bag -- the paper's Table 1 (MAE) and Table 2 (B->P segment).

    python -m fullperc_eval.evaluate BAG [--out DIR] [--json FILE] [--calibration FILE] [--layout FILE]
                                         [--fusion-config FILE] [--target tool] [--quiet]

What it does, without DDS:

1. reads the raw driver topics of the bag (``/omc/<body>/pose``, ``/ots/<tool>/pose``, ``/diana/joint_states``)
   with :class:`fullperc_eval.bag_io.BagReader`, in bag (receive) order;
2. feeds them into one :class:`fullperc_fusion.pipeline.TargetPipeline` running all five methods side by side
   (``omc`` pass-through, ``kf``, ``bkf``, ``ckf``, ``cbkf``) with the configuration of ``fusion_node``
   (``fullperc_fusion/config/fusion.yaml``, mapped exactly as the node maps its parameters, see
   :func:`load_fusion_config`), pushing and polling like the node does in its default ``clock: stamps`` mode
   (including its idle flush, emulated on bag time), so offline and live give the same poses;
3. computes the ground truth at every output stamp from the joint states and the calibration
   (:mod:`fullperc_eval.ground_truth`) and the error |p_method - p_true| in ``base``;
4. labels the true path with the view-margin model (:func:`fullperc_fusion.margin.label_points`, layout in the
   ``omc`` frame) on the joint-state time grid.

Definitions (documented in the README, pinned by tests):

* **MAE** of a method = mean Euclidean position error [mm] over *every pose the method outputs* (what
  ``/fullperc/<target>/<filter>/pose`` would carry). The pass-through only outputs when the OMC sees the
  target; the filters also output on OTS-only items. ``mae_common_mm`` is the same mean over the stamps at
  which *all* methods output, for a like-for-like comparison.
* **Segments**: the label sequence on the joint-state grid is split into runs of equal labels. The segment
  X->Y of two consecutive runs starts at the *last* sample of the X run and ends at the last sample of the
  following Y run (both inclusive): it covers the moment of leaving X and the whole stay in Y. The paper's
  Table 2 segment is the first **B->P** segment (a BVV run directly followed by a PVV run); a path that goes
  B->G->P has no B->P segment (``b_to_p`` is null). Its ``max_mm`` / ``median_mm`` are over the errors of the
  poses each method output inside the segment.

Bad input (missing/corrupt bag, missing metadata.yaml, a topic with an unexpected type, no joint states, no
calibration) ends with ``error: ...`` on stderr and exit code 1, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fullperc_common.transforms import make_T, mean_T
from fullperc_fusion.filters import FilterParams
from fullperc_fusion.frame_chain import ChainConfig
from fullperc_fusion.pipeline import TargetConfig, TargetPipeline

from .bag_io import BagError, BagReader
from .ground_truth import Calibration, CalibrationError, GroundTruth, load_calibration

METHODS = ("omc", "kf", "bkf", "ckf", "cbkf")   # the paper's column order
LETTER = {1: "B", 2: "G", 3: "P"}
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
JOINT_TYPE = "sensor_msgs/msg/JointState"
JOINT_TOPIC = "/diana/joint_states"
PROGRESS_EVERY_S = 2.0


class EvaluationError(Exception):
    """The bag or its companions cannot be evaluated; the message says why."""


# ------------------------------------------------------------------------------------------ configuration
def default_fusion_config_path() -> Path:
    """The installed share/fullperc_fusion/config/fusion.yaml (the node's params file), else the source copy."""
    from .bag_io import package_share

    share = package_share("fullperc_fusion")
    if share is not None and (share / "config" / "fusion.yaml").is_file():
        return share / "config" / "fusion.yaml"
    here = Path(__file__).resolve().parents[2] / "fullperc_fusion" / "config" / "fusion.yaml"
    if here.is_file():
        return here
    raise EvaluationError("fusion.yaml not found (neither installed nor in the source tree); pass --fusion-config")


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def load_fusion_config(path: str | Path | None = None, target: str = "tool",
                       filters: tuple[str, ...] = METHODS) -> tuple[TargetConfig, dict[str, Any]]:
    """TargetConfig of ``target`` from a fusion_node params file, mapped like ``FusionNode.__init__`` does.

    Missing keys take the node's built-in defaults (those of the dataclasses), so an empty file gives the
    node's default behaviour. Returns the config and the flat parameter dict that was used.
    """
    p = Path(path) if path is not None else default_fusion_config_path()
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise EvaluationError(f"fusion config {p}: cannot read ({type(e).__name__}: {e})") from None
    node = data.get("fusion_node", data) if isinstance(data, dict) else None
    params = (node or {}).get("ros__parameters", node) if isinstance(node, dict) else None
    if not isinstance(params, dict):
        raise EvaluationError(f"fusion config {p}: expected 'fusion_node: ros__parameters: {{...}}'")
    flat = _flatten(params)
    d = FilterParams()
    c = ChainConfig()

    def get(key: str, default):
        v = flat.get(key, default)
        return default if v is None else v

    def pose7(key: str):
        v = flat.get(key)
        if v is None or len(v) == 0:
            return None
        if len(v) != 7:
            raise EvaluationError(f"fusion config {p}: '{key}' must be [x y z qx qy qz qw], got {v!r}")
        return (np.asarray(v[:3], float), np.asarray(v[3:], float))

    if get("clock", "stamps") != "stamps":
        print(f"note: fusion config clock '{flat['clock']}' is a live setting; offline evaluation always runs on "
              "the stamps (the default)", file=sys.stderr)
    try:
        fp = FilterParams(
            accel_noise=float(get("noise.accel", d.accel_noise)), bias_walk=float(get("noise.bias_walk", d.bias_walk)),
            global_std=float(get("noise.global_std", d.global_std)),
            local_std=float(get("noise.local_std", d.local_std)),
            init_pos_std=float(get("init.pos_std", d.init_pos_std)),
            init_vel_std=float(get("init.vel_std", d.init_vel_std)),
            init_bias_std=float(get("init.bias_std", d.init_bias_std)),
            hop_gate=float(get("hop_gate", d.hop_gate)), hop_to_bias=bool(get("hop_to_bias", d.hop_to_bias)),
            max_gap_s=float(get("max_gap", d.max_gap_s))).validate()
        chain = ChainConfig(omc_target=str(get(f"{target}.omc_body", target)),
                            ots_target=str(get(f"{target}.ots_tool", target)),
                            omc_base=str(get("omc_base_body", c.omc_base)), omc_rig=str(get("omc_rig_body", c.omc_rig)),
                            ots_base=str(get("ots_base_tool", c.ots_base)),
                            local_chain=str(get("local_chain", c.local_chain)),
                            init_samples=int(get("init_samples", c.init_samples)),
                            T_rig_ots=pose7("T_rig_ots"), T_base_ots=pose7("T_base_ots"))
        cfg = TargetConfig(name=target, chain=chain, filters=tuple(filters), params=fp,
                           slop_ns=int(float(get("slop", 0.004)) * 1e9),
                           delay_ns=int(float(get("reorder_delay", 0.05)) * 1e9))
    except (TypeError, ValueError) as e:
        raise EvaluationError(f"fusion config {p}: {e}") from None
    flat.setdefault("idle_flush", 0.5)
    flat["_source"] = str(p)
    return cfg, flat


# ------------------------------------------------------------------------------------------------ reading
@dataclass
class Outputs:
    """What one method output over the bag (base frame, SI)."""

    t_ns: list[int] = field(default_factory=list)
    p: list[np.ndarray] = field(default_factory=list)
    sources: list[int] = field(default_factory=list)
    hop: list[bool] = field(default_factory=list)
    bias: list[np.ndarray] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self.t_ns)
        return {"t_ns": np.asarray(self.t_ns, dtype=np.int64),
                "p": np.asarray(self.p, dtype=float).reshape(n, 3),
                "sources": np.asarray(self.sources, dtype=np.int64),
                "hop": np.asarray(self.hop, dtype=bool),
                "bias": np.asarray(self.bias, dtype=float).reshape(n, 3)}


@dataclass
class Replay:
    """Everything the replay of one bag produced (input to the metrics and the report)."""

    bag: Path
    task: str
    start_ns: int
    outputs: dict[str, dict[str, np.ndarray]]
    joint_t_ns: np.ndarray
    joint_q: np.ndarray
    omc_base_poses: list[tuple[np.ndarray, np.ndarray]]   # raw (p, q) of the OMC base marker
    counts: dict[str, int]
    pipeline_stats: dict[str, Any]
    warnings: list[str]
    messages: int
    seconds: float


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _task_name(reader: BagReader) -> str:
    cd = reader.info.get("custom_data") or {}
    if isinstance(cd, dict) and cd.get("task"):
        return str(cd["task"])
    return reader.path.name


def replay(bag: str | Path, config: TargetConfig, idle_flush_s: float = 0.5, progress: bool = True) -> Replay:
    """Run the pipeline over the raw measurements of ``bag`` the way fusion_node would have."""
    t_start = time.perf_counter()
    try:
        reader = BagReader(bag)
    except BagError as e:
        raise EvaluationError(str(e)) from None
    c = config.chain
    omc_topics = {f"/omc/{b}/pose": b for b in dict.fromkeys((c.omc_target, c.omc_base, c.omc_rig))}
    ots_topics = {f"/ots/{b}/pose": b for b in dict.fromkeys((c.ots_target, c.ots_base))}
    wanted = {**{t: POSE_TYPE for t in (*omc_topics, *ots_topics)}, JOINT_TOPIC: JOINT_TYPE}
    warnings: list[str] = []
    for topic, typ in wanted.items():
        info = reader.topics.get(topic)
        if info is not None and info.msgtype != typ:
            raise EvaluationError(f"bag {str(reader.path)!r}: topic {topic} has type {info.msgtype}, expected {typ}")
    if JOINT_TOPIC not in reader.topics or reader.topics[JOINT_TOPIC].count == 0:
        raise EvaluationError(f"bag {str(reader.path)!r} has no {JOINT_TOPIC} messages: no ground truth to compare "
                              "with (record the diana_state node too)")
    target_omc = f"/omc/{c.omc_target}/pose"
    if target_omc not in reader.topics or reader.topics[target_omc].count == 0:
        raise EvaluationError(f"bag {str(reader.path)!r} has no {target_omc} messages: nothing to evaluate")
    for t in ots_topics:
        if t not in reader.topics or reader.topics[t].count == 0:
            warnings.append(f"no {t} messages in the bag")
    present = [t for t in wanted if t in reader.topics]
    total = sum(reader.topics[t].count for t in present)

    pipe = TargetPipeline(config)
    outs = {f: Outputs() for f in config.filters}
    joint_t: list[int] = []
    joint_q: list[np.ndarray] = []
    base_poses: list[np.ndarray] = []
    counts = {t: 0 for t in present}
    frames = {"omc": None, "ots": None}
    idle_ns = int(idle_flush_s * 1e9)
    last_target_recv: int | None = None
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

    try:
        reader.open()
        for m in reader.messages(present):
            n += 1
            counts[m.topic] += 1
            try:
                msg = reader.deserialize(m.data, m.msgtype)
            except Exception as e:  # noqa: BLE001 - rosbags raises many types for bad CDR
                raise EvaluationError(f"bag {str(reader.path)!r}: message {counts[m.topic]} of {m.topic} cannot be "
                                      f"decoded as {m.msgtype} ({type(e).__name__}: {e})") from None
            if m.topic == JOINT_TOPIC:
                names = list(msg.name)
                if joint_names is None:
                    joint_names = names
                q = np.asarray(msg.position, dtype=float)
                if names and names != joint_names:
                    raise EvaluationError(f"{JOINT_TOPIC}: joint names changed from {joint_names} to {names}")
                if q.shape != (7,):
                    raise EvaluationError(f"{JOINT_TOPIC}: expected 7 joint positions, got {q.shape[0]}")
                joint_t.append(_stamp_ns(msg.header))
                joint_q.append(q)
                continue
            t_ns = _stamp_ns(msg.header)
            pp = msg.pose.position
            qq = msg.pose.orientation
            pose = (np.array([pp.x, pp.y, pp.z]), np.array([qq.x, qq.y, qq.z, qq.w]))
            dev = "omc" if m.topic in omc_topics else "ots"
            if frames[dev] is None:
                frames[dev] = msg.header.frame_id
                if msg.header.frame_id != dev:
                    warnings.append(f"{m.topic}: frame_id '{msg.header.frame_id}', expected '{dev}'")
            is_target = m.topic == target_omc or m.topic == f"/ots/{c.ots_target}/pose"
            if is_target:
                # fusion_node's idle flush: no target sample for idle_flush seconds -> process everything pending
                if last_target_recv is not None and pipe.sync.pending and m.timestamp - last_target_recv > idle_ns:
                    take(pipe.flush())
                last_target_recv = m.timestamp
            if dev == "omc":
                body = omc_topics[m.topic]
                pipe.push_omc(body, t_ns, pose)
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
                  pipeline_stats=stats, warnings=warnings, messages=n, seconds=time.perf_counter() - t_start)


def live_replay(bag: str | Path, target: str = "tool", primary: str = "cbkf", base_body: str = "base") -> Replay:
    """The fused poses that ``fusion_node`` published live and ``record`` stored, as a :class:`Replay`.

    ``--live`` evaluates these instead of re-running the filters, so a recording of the live graph can be
    compared with the offline replay of its own raw measurements (the demo and the system test do).
    Method ``f`` is read from ``/fullperc/<target>/<f>/pose``; the primary filter also from
    ``/fullperc/<target>/pose``. Sources, hop flags and biases are not in the pose topics (zeros here).
    """
    t_start = time.perf_counter()
    try:
        reader = BagReader(bag)
    except BagError as e:
        raise EvaluationError(str(e)) from None
    topics = {f"/fullperc/{target}/{f}/pose": f for f in METHODS}
    if f"/fullperc/{target}/{primary}/pose" not in reader.topics:
        topics[f"/fullperc/{target}/pose"] = primary
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


# ------------------------------------------------------------------------------------------------ metrics
def runs(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """(label, first index, last index inclusive) of each run of equal labels."""
    lab = np.asarray(labels)
    if lab.size == 0:
        return []
    starts = np.flatnonzero(np.concatenate([[True], lab[1:] != lab[:-1]]))
    ends = np.concatenate([starts[1:] - 1, [lab.size - 1]])
    return [(int(lab[s]), int(s), int(e)) for s, e in zip(starts, ends, strict=True)]


def transition_segments(t_ns: np.ndarray, labels: np.ndarray) -> list[dict[str, Any]]:
    """Every X->Y segment of consecutive label runs: [last sample of X, last sample of Y] (see module doc)."""
    r = runs(labels)
    out = []
    for (la, _, ea), (lb, _, eb) in zip(r, r[1:], strict=False):
        out.append({"from": LETTER.get(la, str(la)), "to": LETTER.get(lb, str(lb)),
                    "t0_ns": int(t_ns[ea]), "t1_ns": int(t_ns[eb])})
    return out


def _finite_pose(pq) -> bool:
    p, q = pq
    return bool(np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 0.5)


def _stats(e_mm: np.ndarray) -> dict[str, float | int | None]:
    if e_mm.size == 0:
        return {"n": 0, "mae": None, "rmse": None, "max": None, "median": None, "min": None, "q1": None, "q3": None,
                "p95": None}
    q1, med, q3, p95 = np.percentile(e_mm, [25, 50, 75, 95])
    return {"n": int(e_mm.size), "mae": float(e_mm.mean()), "rmse": float(np.sqrt(np.mean(e_mm**2))),
            "max": float(e_mm.max()), "median": float(med), "min": float(e_mm.min()), "q1": float(q1),
            "q3": float(q3), "p95": float(p95)}


@dataclass
class Evaluation:
    result: dict[str, Any]                 # everything that goes into the JSON
    series: dict[str, Any]                 # arrays for the plots


def evaluate_replay(rep: Replay, calibration: Calibration, layout, kinematics=None) -> Evaluation:
    """Errors against the ground truth, region labels, Table 1 / Table 2 figures of one replay."""
    from fullperc_fusion.margin import label_points

    try:
        gt = GroundTruth(rep.joint_t_ns, rep.joint_q, calibration, kinematics)
    except ValueError as e:
        raise EvaluationError(f"{rep.bag}: {e}") from None
    # region labels of the true path on the joint-state grid, in the layout (omc) frame
    grid_t = gt.t_ns
    P_grid, ok_grid = gt.position_base(grid_t)
    warnings = list(rep.warnings)
    if calibration.T_omc_base is not None:
        T_omc_base, omc_base_source = calibration.T_omc_base, "calibration"
    elif any(_finite_pose(p) for p in rep.omc_base_poses):
        T_omc_base = mean_T([make_T(p, q / np.linalg.norm(q)) for p, q in rep.omc_base_poses if _finite_pose((p, q))])
        omc_base_source = "mean of the recorded OMC base poses"
    else:
        raise EvaluationError(f"{rep.bag}: no T_omc_base in the calibration and no OMC base-marker poses in the "
                              "bag: cannot place the path in the layout frame for the region labels")
    P_omc = P_grid @ T_omc_base[:3, :3].T + T_omc_base[:3, 3]
    labels, margin = label_points(layout, P_omc)
    labels = np.asarray(labels, dtype=np.int64)
    order = "-".join(LETTER.get(r[0], "?") for r in runs(labels))
    if rep.task and set(rep.task.split("-")) <= set("BGP") and order != rep.task:
        warnings.append(f"the margin model labels the recorded path {order}, the bag says task {rep.task}")

    # errors per method at each output stamp
    all_t = np.unique(np.concatenate([o["t_ns"] for o in rep.outputs.values()] + [np.zeros(0, np.int64)]))
    P_true_all, ok_all = gt.position_base(all_t)
    errors: dict[str, np.ndarray] = {}
    valid: dict[str, np.ndarray] = {}
    out_labels: dict[str, np.ndarray] = {}
    for f, o in rep.outputs.items():
        idx = np.searchsorted(all_t, o["t_ns"])
        ok = ok_all[idx] if idx.size else np.zeros(0, bool)
        e = np.full(len(idx), np.nan)
        if idx.size:
            e[ok] = np.linalg.norm(o["p"][ok] - P_true_all[idx[ok]], axis=1) * 1e3
        errors[f], valid[f] = e, ok
        gi = np.clip(np.searchsorted(grid_t, o["t_ns"], side="right") - 1, 0, len(grid_t) - 1)
        out_labels[f] = labels[gi] if idx.size else np.zeros(0, np.int64)

    methods = [m for m in METHODS if m in rep.outputs] + [m for m in rep.outputs if m not in METHODS]
    per = {f: _stats(errors[f][valid[f]]) for f in methods}
    common = None
    for f in methods:
        s = set(rep.outputs[f]["t_ns"][valid[f]].tolist())
        common = s if common is None else common & s
    common_t = np.array(sorted(common or ()), dtype=np.int64)
    mae_common = {}
    for f in methods:
        sel = np.isin(rep.outputs[f]["t_ns"], common_t) & valid[f]
        mae_common[f] = float(errors[f][sel].mean()) if sel.any() else None
    by_region = {}
    for lab, name in ((1, "BVV"), (2, "GVV"), (3, "PVV")):
        by_region[name] = {f: (float(errors[f][valid[f] & (out_labels[f] == lab)].mean())
                               if np.any(valid[f] & (out_labels[f] == lab)) else None) for f in methods}
    segs = transition_segments(grid_t, labels)
    seg_errors: list[dict[str, np.ndarray]] = []
    for s in segs:
        se = {}
        for f in methods:
            t = rep.outputs[f]["t_ns"]
            sel = valid[f] & (t >= s["t0_ns"]) & (t <= s["t1_ns"])
            se[f] = errors[f][sel]
        seg_errors.append(se)
        s["t0_s"] = (s["t0_ns"] - int(grid_t[0])) * 1e-9
        s["t1_s"] = (s["t1_ns"] - int(grid_t[0])) * 1e-9
        s["stats_mm"] = {f: _stats(se[f]) for f in methods}
    b_to_p = None
    bp_index = next((i for i, s in enumerate(segs) if s["from"] == "B" and s["to"] == "P"), None)
    if bp_index is not None:
        s = segs[bp_index]
        b_to_p = {"t0_s": s["t0_s"], "t1_s": s["t1_s"],
                  "n": {f: s["stats_mm"][f]["n"] for f in methods},
                  "max_mm": {f: s["stats_mm"][f]["max"] for f in methods},
                  "median_mm": {f: s["stats_mm"][f]["median"] for f in methods},
                  "box_mm": {f: {k: s["stats_mm"][f][k] for k in ("min", "q1", "median", "q3", "max")}
                             for f in methods}}
    invalid = {f: int((~valid[f]).sum()) for f in methods}
    if any(invalid.values()):
        warnings.append(f"outputs without ground truth (outside the joint-state span or in a gap): {invalid}")
    result = {
        "task": rep.task,
        "bag": str(rep.bag),
        "mae_mm": {f: per[f]["mae"] for f in methods},
        "b_to_p": b_to_p,
        "mae_common_mm": mae_common,
        "common_stamps": int(common_t.size),
        "rmse_mm": {f: per[f]["rmse"] for f in methods},
        "max_mm": {f: per[f]["max"] for f in methods},
        "median_mm": {f: per[f]["median"] for f in methods},
        "p95_mm": {f: per[f]["p95"] for f in methods},
        "outputs": {f: per[f]["n"] for f in methods},
        "mae_by_region_mm": by_region,
        "regions": {"order": order,
                    "fraction": {n: float(np.mean(labels == k)) for k, n in ((1, "BVV"), (2, "GVV"), (3, "PVV"))},
                    "grid": "joint-state stamps", "T_omc_base": omc_base_source},
        "segments": [{k: v for k, v in s.items() if k not in ("t0_ns", "t1_ns")} for s in segs],
        "duration_s": float((grid_t[-1] - grid_t[0]) * 1e-9),
        "messages": rep.messages,
        "topic_counts": rep.counts,
        "pipeline": rep.pipeline_stats,
        "calibration_source": calibration.source,
        "warnings": warnings,
    }
    series = {"grid_t_ns": grid_t, "grid_p": P_grid, "grid_ok": ok_grid, "labels": labels,
              "margin_deg": np.asarray(margin.margin_deg), "outputs": rep.outputs, "errors": errors, "valid": valid,
              "segments": segs, "seg_errors": seg_errors, "b_to_p_index": bp_index, "methods": methods}
    return Evaluation(result, series)


def evaluate_bag(bag: str | Path, *, calibration: str | Path | None = None, layout: str | Path | None = None,
                 fusion_config: str | Path | None = None, target: str = "tool", progress: bool = True,
                 config: TargetConfig | None = None, live: bool = False) -> Evaluation:
    """Replay + metrics for one bag; ``config`` overrides the fusion config file (tests, benchmarks).

    ``live``: evaluate the fused poses recorded from ``fusion_node`` (:func:`live_replay`) instead.
    """
    from fullperc_fusion.layout import LayoutError, default_layout_path, load_layout

    from .bag_io import load_metadata

    try:
        load_metadata(Path(bag))          # the bag itself first: its problems are the likeliest
    except BagError as e:
        raise EvaluationError(str(e)) from None
    flat: dict[str, Any] = {"idle_flush": 0.5}
    if config is None:
        config, flat = load_fusion_config(fusion_config, target)
    try:
        cal = load_calibration(calibration if calibration is not None else bag)
    except CalibrationError as e:
        raise EvaluationError(str(e)) from None
    try:
        lay = load_layout(layout if layout is not None else default_layout_path())
    except (LayoutError, FileNotFoundError) as e:
        raise EvaluationError(f"layout: {e}") from None
    if live:
        rep = live_replay(bag, target=target, primary=str(flat.get("filter", "cbkf")))
    else:
        rep = replay(bag, config, idle_flush_s=float(flat.get("idle_flush", 0.5)), progress=progress)
    ev = evaluate_replay(rep, cal, lay)
    ev.result["config"] = {"fusion_config": flat.get("_source", "<given>"), "layout": str(lay.source),
                           "filter_params": {k: v for k, v in vars(config.params).items()},
                           "slop_s": config.slop_ns * 1e-9, "reorder_delay_s": config.delay_ns * 1e-9,
                           "local_chain": config.chain.local_chain, "init_samples": config.chain.init_samples}
    ev.result["config"]["filter_params"]["shrink_blocks"] = list(config.params.shrink_blocks)
    return ev


# ------------------------------------------------------------------------------------------------ output
def _fmt(v) -> str:
    return "   -  " if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:6.2f}"


def format_table1(rows: list[dict[str, Any]], methods=METHODS) -> str:
    head = f"{'task':<10}" + "".join(f"{m.upper():>7}" for m in methods) + "   CBKF/OMC"
    lines = ["Table 1: MAE [mm] (every pose each method outputs, vs Diana ground truth)", head]
    for r in rows:
        mae = r["mae_mm"]
        ratio = (mae["cbkf"] / mae["omc"]) if mae.get("cbkf") and mae.get("omc") else None
        lines.append(f"{r['task']:<10}" + "".join(f" {_fmt(mae.get(m))}" for m in methods)
                     + (f"   {ratio:9.2f}" if ratio is not None else ""))
    return "\n".join(lines)


def format_table2(r: dict[str, Any], methods=METHODS) -> str:
    bp = r.get("b_to_p")
    if not bp:
        return f"Table 2 ({r['task']}): no B->P segment on this path (regions {r['regions']['order']})"
    lines = [f"Table 2 ({r['task']}): B->P segment {bp['t0_s']:.2f}-{bp['t1_s']:.2f} s, error [mm]",
             f"{'value':<10}" + "".join(f"{m.upper():>7}" for m in methods)]
    for key in ("max_mm", "median_mm"):
        lines.append(f"{key[:-3]:<10}" + "".join(f" {_fmt(bp[key].get(m))}" for m in methods))
    return "\n".join(lines)


def to_json(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars -> Python, NaN/inf -> null."""
    if isinstance(obj, dict):
        return {str(k): to_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path: str | Path, data: Any) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(to_json(data), indent=1) + "\n")
    return p


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="evaluate", description=__doc__.split("\n")[0])
    ap.add_argument("bag", help="rosbag2 bag directory (with metadata.yaml)")
    ap.add_argument("--out", help="write the report (PNG plots, index.html, eval.json) into this directory")
    ap.add_argument("--json", help="write all figures as JSON to this file")
    ap.add_argument("--calibration", help="calibration YAML (default: <bag>/calibration.yaml)")
    ap.add_argument("--layout", help="camera layout YAML (default: fullperc_fusion's or_layout.yaml)")
    ap.add_argument("--fusion-config", help="fusion_node params file (default: fullperc_fusion's fusion.yaml)")
    ap.add_argument("--target", default="tool", help="fused target name (default: tool)")
    ap.add_argument("--quiet", action="store_true", help="no progress output")
    ap.add_argument("--live", action="store_true",
                    help="evaluate the fused poses recorded live (/fullperc/<target>/...) instead of re-running")
    args = ap.parse_args(argv)
    try:
        ev = evaluate_bag(args.bag, calibration=args.calibration, layout=args.layout,
                          fusion_config=args.fusion_config, target=args.target, progress=not args.quiet,
                          live=args.live)
        r = ev.result
        print(format_table1([r]))
        print()
        print(format_table2(r))
        for w in r["warnings"]:
            print(f"warning: {w}", file=sys.stderr)
        if args.json:
            write_json(args.json, r)
        if args.out:
            from .report import write_report

            index = write_report(ev, args.out)
            write_json(Path(args.out) / "eval.json", r)
            print(f"report: {index}")
    except (EvaluationError, BagError, CalibrationError) as e:
        print("error: " + " ".join(str(e).split()), file=sys.stderr)   # one line, also for YAML parser messages
        return 1
    except OSError as e:
        print(f"error: {e.filename or ''}: {e.strerror or e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
