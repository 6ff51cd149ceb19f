"""``make dataset``: the six evaluation tasks simulated offline and written as rosbag2 (MCAP) bags.

    python -m fullperc_eval.sim.dataset --out bags [--tasks G-B-P P-G-B ...] [--seed 0] [--profile paper]

Each task becomes ``<out>/<task>/`` holding what a ``record`` of the live system would hold -- the driver
topics with the drivers' types, frames, units and stamps -- plus the calibration the evaluator needs:

* ``/omc/<body>/pose`` (PoseStamped, frame ``omc``; only when tracked) and ``/omc/<body>/quality``
  (TrackingQuality, every frame) for the bodies ``base``, ``ots_rig``, ``tool`` (and the extra targets');
* ``/ots/<tool>/pose`` (frame ``ots``; only when visible) and ``/ots/<tool>/quality`` for ``tool``, ``base``
  (and the extra targets');
* ``/diana/joint_states`` (JointState, ``joint1..joint7``, frame ``diana_base``) and ``/diana/flange_pose``
  (PoseStamped, FK of the nominal DH table, frame ``diana_base``);
* the extra targets (:mod:`.targets`: ``instrument``, ``reference``): ``/omc/<target>/{pose,quality}``,
  ``/ots/<target>/{pose,quality}`` like the tool's, and each one's ground truth ``/sim/truth/<target>``
  (PoseStamped in ``base`` at the OMC frame stamps, received at its stamp). **Simulator only**: no real recording
  has it; the evaluator uses it for every target but the arm-held ``tool`` (whose truth is the Diana's forward
  kinematics);
* ``calibration.yaml``: T_base_diana_base, T_flange_tool, T_omc_base -- the simulator's true values
  (see :mod:`fullperc_eval.evaluation.ground_truth` for why the evaluator does not estimate them);
* ``metadata.yaml`` ``custom_data``: generator, task, seed, profile (the evaluator takes the task name from here).

Stamps: ``header.stamp`` is the acquisition time on the host clock (simulator time + a fixed epoch, so the
bags are reproducible bit for bit); the bag (receive) time is the stamp plus the device's latency (OMC and
Vega latencies from the simulator's scene, 1 ms for the arm's state push), so messages appear in the bag in
the order a recorder would have received them. MCAP chunks are zstd-compressed.

:func:`write_bag` is independent of the simulator (arrays in, bag out); the tests use it to write synthetic
bags with known errors.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fullperc_common.transforms import T_to_pq, inv_T, make_T
from fullperc_drivers.diana_kinematics import JOINT_NAMES, DianaKinematics
from fullperc_eval.bag.calibration import Calibration, save_calibration
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.metadata import load_metadata, write_metadata
from fullperc_eval.bag.qos import make_qos
from fullperc_eval.bag.writer import BagWriter
from fullperc_fusion.margin.layout import default_layout_path, load_layout

from . import cdr_records
from .runner import run_task
from .scene import DEFAULT_PROFILE, PROFILES
from .tasks import TASKS

EPOCH_NS = 1_700_000_000_000_000_000   # 2023-11-14T22:13:20Z: fixed "host clock" start of every bag
DIANA_LATENCY_NS = 1_000_000           # joint state push -> host (UDP on the robot LAN); an assumption
# The generator's name as recorded in every bag it writes (metadata custom_data, calibration source): the
# committed sample bags carry it, and generate() replaces only bags with this name; not a module path.
GENERATOR = "fullperc_eval.dataset"
TRUTH_PREFIX = "/sim/truth"            # /sim/truth/<target>: simulator-only ground truth of a target without a robot
PORT_STATUS_OK = 0x31                  # NDI PSTAT: occupied | initialized | enabled (what the Vega reports)


@dataclass
class BodyArrays:
    """One rigid body (OMC) or tool (OTS) over all device frames; NaN pose where not visible."""

    visible: np.ndarray            # (F,) bool
    position: np.ndarray           # (F, 3) [m] in the device frame
    quat_xyzw: np.ndarray          # (F, 4)
    fit_error: np.ndarray | None = None   # (F,) [m]; NaN/None -> -1 (unknown)
    markers: np.ndarray | None = None     # (F,)


@dataclass
class DeviceStream:
    """Frames of one tracking device: capture stamps on the host clock [ns] and the bodies in them."""

    frame_id: str
    t_ns: np.ndarray               # (F,) int64 acquisition stamps
    bodies: dict[str, BodyArrays]
    latency_ns: int = 0
    frame_number: np.ndarray | None = None
    port_status: int = 0           # NDI port status of a tracked port (0 for the OMC)
    qos_depth: int = 10


@dataclass
class JointStream:
    t_ns: np.ndarray               # (N,) int64 acquisition stamps
    q: np.ndarray                  # (N, 7) [rad]
    dq: np.ndarray | None = None   # (N, 7) [rad/s]
    latency_ns: int = DIANA_LATENCY_NS
    frame_id: str = "diana_base"


@dataclass
class BagContent:
    omc: DeviceStream
    ots: DeviceStream
    diana: JointStream
    calibration: Calibration
    custom_data: dict[str, str] = field(default_factory=dict)
    truth: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)   # target -> (t_ns, T_base (F,4,4))


def _types(ts):
    T = ts.types
    return (T["geometry_msgs/msg/PoseStamped"], T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"],
            T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"],
            T["fullperc_msgs/msg/TrackingQuality"], T["sensor_msgs/msg/JointState"])


def write_bag(path: str | Path, content: BagContent, *, compression: str = "zstd", per_message: bool = False) -> Path:
    """Write ``content`` as a rosbag2 MCAP bag directory at ``path`` (must not exist) + calibration.yaml.

    Each topic's records are serialised at once (:func:`_bulk_events`, :mod:`.cdr_records`): the bytes rosbags'
    serialiser gives message by message (``per_message``: that path, the reference; test_twin_profiles.py pins the
    two bags equal record for record). Content the bulk path does not take (values outside a field's wire range,
    a joint count other than the names') is written message by message."""
    path = Path(path)
    w = BagWriter(path, storage="mcap", compression=compression, custom_data=content.custom_data,
                  flush_interval=3600.0)
    with w:
        for prefix, dev in (("/omc", content.omc), ("/ots", content.ots)):
            for name in dev.bodies:
                w.add_topic(f"{prefix}/{name}/pose", "geometry_msgs/msg/PoseStamped", [make_qos(depth=dev.qos_depth)])
                w.add_topic(f"{prefix}/{name}/quality", "fullperc_msgs/msg/TrackingQuality",
                            [make_qos(depth=dev.qos_depth)])
        w.add_topic("/diana/joint_states", "sensor_msgs/msg/JointState", [make_qos(depth=10)])
        w.add_topic("/diana/flange_pose", "geometry_msgs/msg/PoseStamped", [make_qos(depth=10)])
        for name in content.truth:
            w.add_topic(f"{TRUTH_PREFIX}/{name}", "geometry_msgs/msg/PoseStamped", [make_qos(depth=10)])
        bulk = None if per_message else _bulk_events(content)
        if bulk is not None:
            for recv, topic, data in bulk:
                w.write(topic, recv, data)
        else:
            for recv, topic, msg in _message_events(w.typestore, content):
                w.write_msg(topic, recv, msg)
    save_calibration(path, content.calibration)
    return path


def _message_events(ts, content: BagContent) -> list[tuple[int, str, object]]:
    """Every message of ``content`` as a rosbags message object, (receive ns, topic, message) in the bag's order:
    by receive time, ties in the order they are made here (per device frame: each body's pose, if published, then
    its quality; per arm sample: joint state, flange pose; then each truth track)."""
    PoseStamped, Header, Time, Pose, Point, Quaternion, Quality, JointState = _types(ts)

    def header(t_ns: int, frame: str):
        return Header(stamp=Time(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)), frame_id=frame)

    events: list[tuple[int, int, str, object]] = []   # (receive ns, sequence, topic, message)
    seq = 0
    for prefix, dev in (("/omc", content.omc), ("/ots", content.ots)):
        t = np.asarray(dev.t_ns, dtype=np.int64)
        fn = dev.frame_number if dev.frame_number is not None else np.arange(1, len(t) + 1)
        for k in range(len(t)):
            tk = int(t[k])
            recv = tk + int(dev.latency_ns)
            for name, b in dev.bodies.items():
                vis = bool(b.visible[k])
                if vis:
                    p, q = b.position[k], b.quat_xyzw[k]
                    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
                        vis = False   # a driver never publishes NaN: reported as not visible
                    else:
                        msg = PoseStamped(header=header(tk, dev.frame_id), pose=Pose(
                            position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                            orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))
                        events.append((recv, seq, f"{prefix}/{name}/pose", msg))
                        seq += 1
                fe = np.nan if b.fit_error is None else float(b.fit_error[k])
                qm = Quality(header=header(tk, dev.frame_id), body=name, visible=vis,
                             fit_error=np.float32(fe if np.isfinite(fe) else -1.0),
                             frame_number=int(fn[k]) & 0xFFFFFFFF,
                             markers_used=int(0 if b.markers is None else max(0, min(int(b.markers[k]), 65535))),
                             latency=np.float32(dev.latency_ns * 1e-9),
                             port_status=int(dev.port_status))
                events.append((recv, seq, f"{prefix}/{name}/quality", qm))
                seq += 1
    d = content.diana
    Q = np.asarray(d.q, dtype=float)
    F = DianaKinematics().fk_many(Q)
    for k, tk in enumerate(np.asarray(d.t_ns, dtype=np.int64).tolist()):
        recv = tk + int(d.latency_ns)
        js = JointState(header=header(tk, d.frame_id), name=list(JOINT_NAMES),
                        position=Q[k].astype(np.float64),
                        velocity=(np.asarray(d.dq[k], dtype=np.float64) if d.dq is not None
                                  else np.zeros(0, np.float64)),
                        effort=np.zeros(0, np.float64))
        events.append((recv, seq, "/diana/joint_states", js))
        seq += 1
        p, q = T_to_pq(F[k])
        events.append((recv, seq, "/diana/flange_pose", PoseStamped(header=header(tk, d.frame_id), pose=Pose(
            position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))))
        seq += 1
    for name, (t_tr, T_tr) in content.truth.items():
        topic = f"{TRUTH_PREFIX}/{name}"
        for tk, T in zip(np.asarray(t_tr, dtype=np.int64).tolist(), T_tr, strict=True):
            p, q = T_to_pq(T)
            events.append((tk, seq, topic, PoseStamped(header=header(tk, "base"), pose=Pose(
                position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))))
            seq += 1
    events.sort(key=lambda e: (e[0], e[1]))
    return [(recv, topic, msg) for recv, _, topic, msg in events]


def _whole(a: np.ndarray, lo: int, hi: int) -> bool:
    """Every value of ``a`` finite and within [lo, hi] (what a wire field of that range takes as is)."""
    a = np.asarray(a)
    return bool(a.size == 0 or (np.isfinite(a).all() and a.min() >= lo and a.max() <= hi))


def _bulk_events(content: BagContent) -> list[tuple[int, str, bytes]] | None:
    """:func:`_message_events` as serialised records, (receive ns, topic, CDR bytes) in the same order, each topic
    serialised at once (:mod:`.cdr_records`); None for content it does not take (see :func:`write_bag`)."""
    recv_parts, seq_parts, topics, records = [], [], [], []

    def add(topic: str, recv: np.ndarray, seq: np.ndarray, recs: list[bytes]) -> None:
        recv_parts.append(np.asarray(recv, np.int64))
        seq_parts.append(np.asarray(seq, np.int64))
        topics.append(topic)
        records.append(recs)

    seq0 = 0
    for prefix, dev in (("/omc", content.omc), ("/ots", content.ots)):
        t = np.asarray(dev.t_ns, dtype=np.int64)
        fn = dev.frame_number if dev.frame_number is not None else np.arange(1, len(t) + 1)
        if not (_whole(t // 1_000_000_000, 0, 2**31 - 1) and _whole(fn, -2**62, 2**62)
                and 0 <= int(dev.port_status) < 2**32):
            return None
        names = list(dev.bodies)
        vis = np.zeros((len(t), len(names)), bool)
        for j, b in enumerate(dev.bodies.values()):
            with np.errstate(invalid="ignore"):
                vis[:, j] = np.asarray(b.visible, bool) & np.isfinite(np.asarray(b.position, float)).all(1) \
                    & np.isfinite(np.asarray(b.quat_xyzw, float)).all(1)   # a driver never publishes NaN
        count = vis.astype(np.int64) + 1                    # per frame and body: its pose (if any), its quality
        first = seq0 + (np.cumsum(count.ravel()) - count.ravel()).reshape(count.shape)
        seq0 += int(count.sum())
        recv = t + int(dev.latency_ns)
        frame_number = np.asarray(fn).astype(np.int64) & 0xFFFFFFFF
        for j, (name, b) in enumerate(dev.bodies.items()):
            v = vis[:, j]
            add(f"{prefix}/{name}/pose", recv[v], first[v, j],
                cdr_records.pose_stamped(t[v], dev.frame_id, np.asarray(b.position, float)[v],
                                         np.asarray(b.quat_xyzw, float)[v]))
            fe = np.full(len(t), np.nan) if b.fit_error is None else np.asarray(b.fit_error, float)
            if b.markers is not None and not _whole(b.markers, -2**62, 2**62):
                return None
            markers = np.zeros(len(t), np.int64) if b.markers is None else \
                np.clip(np.asarray(b.markers).astype(np.int64), 0, 65535)
            with np.errstate(invalid="ignore"):
                fit = np.where(np.isfinite(fe), fe, -1.0).astype(np.float32)
            add(f"{prefix}/{name}/quality", recv, first[:, j] + v,
                cdr_records.tracking_quality(t, dev.frame_id, name, v, fit, frame_number, markers,
                                             np.float32(dev.latency_ns * 1e-9), int(dev.port_status)))
    d = content.diana
    t = np.asarray(d.t_ns, dtype=np.int64)
    Q = np.asarray(d.q, dtype=float)
    dq = None if d.dq is None else np.asarray(d.dq, dtype=np.float64)
    if Q.shape != (len(t), len(JOINT_NAMES)) or (dq is not None and dq.shape != Q.shape) \
            or not _whole(t // 1_000_000_000, 0, 2**31 - 1):
        return None
    F = DianaKinematics().fk_many(Q)
    recv = t + int(d.latency_ns)
    seq = seq0 + 2 * np.arange(len(t))
    add("/diana/joint_states", recv, seq, cdr_records.joint_state(t, d.frame_id, JOINT_NAMES, Q, dq))
    pq = [T_to_pq(T) for T in F]
    add("/diana/flange_pose", recv, seq + 1, cdr_records.pose_stamped(t, d.frame_id, np.array([p for p, _ in pq]),
                                                                      np.array([q for _, q in pq])))
    seq0 += 2 * len(t)
    for name, (t_tr, T_tr) in content.truth.items():
        tt = np.asarray(t_tr, dtype=np.int64)
        if not _whole(tt // 1_000_000_000, 0, 2**31 - 1):
            return None
        pq = [T_to_pq(T) for T in T_tr]
        add(f"{TRUTH_PREFIX}/{name}", tt, seq0 + np.arange(len(tt)),
            cdr_records.pose_stamped(tt, "base", np.array([p for p, _ in pq]).reshape(-1, 3),
                                     np.array([q for _, q in pq]).reshape(-1, 4)))
        seq0 += len(tt)
    recv_all, seq_all = np.concatenate(recv_parts), np.concatenate(seq_parts)
    which = np.concatenate([np.full(len(r), k) for k, r in enumerate(recv_parts)])
    within = np.concatenate([np.arange(len(r)) for r in recv_parts])
    order = np.lexsort((seq_all, recv_all))
    return [(int(recv_all[i]), topics[which[i]], records[which[i]][within[i]]) for i in order.tolist()]


def write_truth_bag(path: str | Path, truth: dict[str, tuple[np.ndarray, np.ndarray]],
                    custom_data: dict[str, str] | None = None) -> Path:
    """A bag holding only ``/sim/truth/<target>`` (PoseStamped in ``base``, received at the stamp) per target.

    The live simulator writes its second target's truth like this (host-clock stamps), and the demo merges it into
    the recording with :func:`merge_bag`: the target has no robot, so nothing on the wire carries its truth.
    """
    path = Path(path)
    w = BagWriter(path, storage="mcap", compression="zstd", custom_data=custom_data or {}, flush_interval=3600.0)
    PoseStamped, Header, Time, Pose, Point, Quaternion, _, _ = _types(w.typestore)
    with w:
        for name in truth:
            w.add_topic(f"{TRUTH_PREFIX}/{name}", "geometry_msgs/msg/PoseStamped", [make_qos(depth=10)])
        events = []
        for name, (t_tr, T_tr) in truth.items():
            for tk, T in zip(np.asarray(t_tr, dtype=np.int64).tolist(), T_tr, strict=True):
                p, q = T_to_pq(T)
                events.append((tk, f"{TRUTH_PREFIX}/{name}", PoseStamped(
                    header=Header(stamp=Time(sec=tk // 1_000_000_000, nanosec=tk % 1_000_000_000), frame_id="base"),
                    pose=Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                              orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))))
        for tk, topic, msg in sorted(events, key=lambda e: e[0]):
            w.write_msg(topic, tk, msg)
    return path


def merge_bag(dst: str | Path, src: str | Path) -> Path:
    """Move the storage files of bag ``src`` into bag ``dst`` (same storage) and list them in its metadata.yaml.

    rosbag2 bags may span several files (``relative_file_paths``); readers (rosbags, ``ros2 bag``) read them as one
    bag. The topics of ``src`` must not already be in ``dst``. ``src`` is removed.
    """
    dst, src = Path(dst), Path(src)
    di, si = load_metadata(dst), load_metadata(src)
    if di["storage_identifier"] != si["storage_identifier"]:
        raise BagError(f"cannot merge a {si['storage_identifier']} bag into a {di['storage_identifier']} bag")
    have = {e["topic_metadata"]["name"] for e in di["topics_with_message_count"]}
    clash = have & {e["topic_metadata"]["name"] for e in si["topics_with_message_count"]}
    if clash:
        raise BagError(f"cannot merge {src} into {dst}: both hold {sorted(clash)}")
    files = list(di.get("files") or [])
    for rel in si["relative_file_paths"]:
        new = f"{src.name}_{rel}"
        if (dst / new).exists():
            raise BagError(f"cannot merge {src} into {dst}: {dst / new} exists")
        shutil.move(str(src / rel), str(dst / new))
        di["relative_file_paths"].append(new)
        entry = next((dict(f) for f in si.get("files") or [] if f.get("path") == rel), None)
        if entry is not None:
            entry["path"] = new
            files.append(entry)
    di["files"] = files
    di["topics_with_message_count"] += si["topics_with_message_count"]
    di["message_count"] = int(di.get("message_count", 0)) + int(si.get("message_count", 0))
    ends = [int(i["starting_time"]["nanoseconds_since_epoch"]) + int(i["duration"]["nanoseconds"]) for i in (di, si)
            if int(i.get("message_count", 0))]
    starts = [int(i["starting_time"]["nanoseconds_since_epoch"]) for i in (di, si) if int(i.get("message_count", 0))]
    if starts:
        di["starting_time"] = {"nanoseconds_since_epoch": min(starts)}
        di["duration"] = {"nanoseconds": max(ends) - min(starts)}
    write_metadata(dst, {"rosbag2_bagfile_information": di})
    shutil.rmtree(src)
    return dst


# ------------------------------------------------------------------------------------------- synthetic
def _grid(duration_s: float, rate_hz: float, phase_s: float = 0.0) -> np.ndarray:
    n = int(np.floor((duration_s - phase_s) * rate_hz + 1e-9)) + 1
    return np.round((phase_s + np.arange(n) / rate_hz) * 1e9).astype(np.int64)


def synthetic_content(duration_s: float = 10.0, *, omc_offset=(0.003, 0.0, 0.0), omc_offset_after=None,
                      t_offset_change_s: float | None = None, ots_window_s=(0.0, 5.0), omc_noise_m: float = 0.0,
                      ots_noise_m: float = 0.0, joint: int = 0, joint_speed: float = 0.05, seed: int = 0,
                      epoch_ns: int = EPOCH_NS) -> tuple[BagContent, dict[str, np.ndarray]]:
    """A recording with *known* errors, for tests and benchmarks (no simulator, no cameras).

    The Diana turns ``joint`` at a constant ``joint_speed`` [rad/s] (so linear joint interpolation is exact);
    the OMC sees the tool with a constant position error ``omc_offset`` [m, omc axes] (``omc_offset_after``
    from ``t_offset_change_s`` on: a hop), the base marker and the rig exactly (+ noise); the Vega sees the
    base marker always and the tool only inside ``ots_window_s`` (+ noise). Rates: OMC 120 Hz, Vega 60 Hz,
    arm 100 Hz. Returns the content and the truth: ``t_omc_ns`` and ``p_base_true`` (F, 3) at the OMC frames,
    ``offset_base`` (F, 3) -- the injected error expressed in ``base``.
    """
    rng = np.random.default_rng(seed)
    lay = load_layout(default_layout_path())
    T_omc_ots = np.asarray(lay.ots.T_omc_ots, float)
    q_base = np.array([0.0, -0.7071067811865476, 0.0, 0.7071067811865476])
    T_omc_base = make_T([-0.6, 0.35, 1.10], q_base)
    T_omc_diana_base = make_T([0.2, -0.65, 0.8], [0, 0, 0, 1])
    T_flange_tool = make_T([0, 0, -0.06], [1, 0, 0, 0])
    T_ots_rig = make_T([-0.05, 0.12, 0.05], [-0.7071067811865476, 0, 0, 0.7071067811865476])
    q0 = np.array([0.3, 0.5, 0.0, 1.6, 0.0, 0.6, 0.0])
    kin = DianaKinematics()

    def q_at(t_ns):
        Q = np.tile(q0, (len(t_ns), 1))
        Q[:, joint] += joint_speed * (np.asarray(t_ns) * 1e-9)
        return Q

    def tool_omc(t_ns):
        return T_omc_diana_base @ kin.fk_many(q_at(t_ns)) @ T_flange_tool

    t_omc, t_ots, t_dia = _grid(duration_s, 120.0), _grid(duration_s, 60.0, 0.0031), _grid(duration_s, 100.0)
    F, V = len(t_omc), len(t_ots)
    off = np.tile(np.asarray(omc_offset, float), (F, 1))
    if omc_offset_after is not None and t_offset_change_s is not None:
        off[t_omc * 1e-9 >= t_offset_change_s] = np.asarray(omc_offset_after, float)
    T_tool = tool_omc(t_omc)
    quat = lambda Ts: np.array([T_to_pq(T)[1] for T in Ts])  # noqa: E731

    def body(Ts, noise, extra=None, visible=None):
        p = Ts[:, :3, 3] + (0 if extra is None else extra) + noise * rng.standard_normal((len(Ts), 3))
        vis = np.ones(len(Ts), bool) if visible is None else visible
        p = np.where(vis[:, None], p, np.nan)
        return BodyArrays(vis, p, np.where(vis[:, None], quat(Ts), np.nan), np.full(len(Ts), 1e-4),
                          np.full(len(Ts), 4))

    omc = DeviceStream("omc", t_omc + epoch_ns, {
        "base": body(np.broadcast_to(T_omc_base, (F, 4, 4)), omc_noise_m),
        "ots_rig": body(np.broadcast_to(T_omc_ots @ inv_T(T_ots_rig), (F, 4, 4)), omc_noise_m),
        "tool": body(T_tool, omc_noise_m, off)}, latency_ns=8_000_000, frame_number=np.arange(1, F + 1))
    in_win = (t_ots * 1e-9 >= ots_window_s[0]) & (t_ots * 1e-9 < ots_window_s[1])
    T_ots_omc = inv_T(T_omc_ots)
    ots = DeviceStream("ots", t_ots + epoch_ns, {
        "tool": body(T_ots_omc @ tool_omc(t_ots), ots_noise_m, visible=in_win),
        "base": body(np.broadcast_to(T_ots_omc @ T_omc_base, (V, 4, 4)), ots_noise_m)},
        latency_ns=14_000_000, frame_number=np.arange(1, V + 1), port_status=PORT_STATUS_OK, qos_depth=50)
    dq = np.zeros((len(t_dia), 7))
    dq[:, joint] = joint_speed
    diana = JointStream(t_dia + epoch_ns, q_at(t_dia), dq)
    cal = Calibration(inv_T(T_omc_base) @ T_omc_diana_base, T_flange_tool, T_omc_base, source="synthetic truth")
    R_base_omc = inv_T(T_omc_base)[:3, :3]
    truth = {"t_omc_ns": t_omc + epoch_ns, "p_base_true": (inv_T(T_omc_base) @ T_tool)[:, :3, 3],
             "offset_base": off @ R_base_omc.T}
    return BagContent(omc, ots, diana, cal, {"generator": "synthetic", "task": "synthetic"}), truth


# ------------------------------------------------------------------------------------------- simulator
def device_precision(b: BodyArrays, device: str) -> BodyArrays:
    """What the driver publishes for a pose the device sent with its own wire precision.

    Both devices send float32: the NOKOV SDK's ``sRigidBodyData`` (x y z [mm], qx qy qz qw, MeanError [mm];
    reference/nokov_mocap.md) and the NDI BX reply (``<8f``: q0 qx qy qz, tx ty tz [mm], error [mm]). The
    drivers convert exactly like this: position float64(float32 mm) * 1e-3 (omc_driver) or / 1000 (ndi_driver),
    quaternion renormalised (nokov/frames.py, ndi/driver.py). (The simulator's own UDP stream carries float64;
    the dataset mirrors the real devices.)
    """
    with np.errstate(invalid="ignore"):
        mm = (np.asarray(b.position, float) * 1000.0).astype(np.float32).astype(float)
        p = mm * 1e-3 if device == "omc" else mm / 1000.0
        q = np.asarray(b.quat_xyzw, float).astype(np.float32).astype(float)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        err = None if b.fit_error is None else \
            (np.asarray(b.fit_error, float) * 1000.0).astype(np.float32).astype(float) / 1000.0
    return BodyArrays(b.visible, p, q, err, b.markers)


def content_from_sim(run, epoch_ns: int = EPOCH_NS, wire_precision: bool = True) -> BagContent:
    """The bag content of one :class:`.run.SimRun` (simulator time + ``epoch_ns``).

    ``wire_precision``: poses as the drivers publish them from the devices' float32 replies
    (:func:`device_precision`); False keeps the simulator's float64 values. The Vega's stamps (and receive times)
    are late by the run's ``ots.stamp_offset_s`` (0 unless a test set it: an unsubtracted latency).
    """
    o, v = run.omc, run.ots
    wp = device_precision if wire_precision else (lambda b, _d: b)
    omc = DeviceStream("omc", np.asarray(o.t_ns, np.int64) + epoch_ns,
                       {n: wp(BodyArrays(b.tracked, b.position, b.quat_xyzw, b.mean_error, b.markers_used), "omc")
                        for n, b in o.bodies.items()},
                       latency_ns=int(round(o.latency_s * 1e9)), frame_number=o.frame_number, qos_depth=10)
    ots = DeviceStream("ots", np.asarray(v.t_ns, np.int64) + epoch_ns + int(round(v.stamp_offset_s * 1e9)),
                       {n: wp(BodyArrays(t.visible, t.position, t.quat_xyzw, t.rms, t.markers_used), "ots")
                        for n, t in v.tools.items()},
                       latency_ns=int(round(v.latency_s * 1e9)), frame_number=v.frame_number,
                       port_status=PORT_STATUS_OK, qos_depth=50)
    diana = JointStream(np.asarray(run.diana.t_ns, np.int64) + epoch_ns, run.diana.q, run.diana.dq)
    truth = {n: (np.asarray(tr.t_ns, np.int64) + epoch_ns, tr.T_base_tool) for n, tr in run.extra_truth.items()}
    return BagContent(omc, ots, diana, sim_calibration(run),
                      {"generator": GENERATOR, "task": str(run.task), "seed": str(run.seed),
                       "profile": str(run.info.get("profile", "base"))}, truth)


def sim_calibration(run) -> Calibration:
    """The calibration of a simulated run: the simulator's true static transforms (for ground truth)."""
    s = run.static
    return Calibration(T_base_diana_base=inv_T(s["T_omc_base"]) @ s["T_omc_diana_base"],
                       T_flange_tool=np.asarray(s["T_flange_tool"], float),
                       T_omc_base=np.asarray(s["T_omc_base"], float),
                       source=f"simulator truth ({GENERATOR}, task {run.task}, seed {run.seed}, "
                              f"profile {run.info.get('profile', 'base')})")


def _is_ours(bagdir: Path) -> bool:
    try:
        info = load_metadata(bagdir)
    except BagError:
        return False
    return (info.get("custom_data") or {}).get("generator") == GENERATOR


def generate(out: str | Path, tasks, seed: int = 0, log=print, profile: str | None = DEFAULT_PROFILE) -> list[Path]:
    """Simulate ``tasks`` and write one bag per task into ``out``; replaces bags this generator wrote before."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for task in tasks:
        dest = out / task
        if dest.exists() and not _is_ours(dest):
            raise BagError(f"{dest} exists and was not written by {GENERATOR}; refusing to overwrite it")
        t0 = time.monotonic()
        run = run_task(task, seed=seed, profile=profile)
        t1 = time.monotonic()
        tmp_parent = out / f".{task}.partial"
        if tmp_parent.exists():
            shutil.rmtree(tmp_parent)
        tmp = write_bag(tmp_parent / task, content_from_sim(run))   # storage file is named <task>_0.mcap
        if dest.exists():
            shutil.rmtree(dest)
        tmp.rename(dest)
        tmp_parent.rmdir()
        size = sum(f.stat().st_size for f in dest.iterdir())
        log(f"{task}: simulated {run.duration_s:.1f} s in {t1 - t0:.1f} s, wrote {dest} "
            f"({size / 1e6:.2f} MB) in {time.monotonic() - t1:.1f} s")
        written.append(dest)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fullperc_eval.sim.dataset", description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="bags", help="directory for the bags (default: bags)")
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), help=f"tasks to generate (default: {' '.join(TASKS)})")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    ap.add_argument("--profile", default=DEFAULT_PROFILE, choices=(*PROFILES, "base"),
                    help=f"twin profile (default {DEFAULT_PROFILE}; base = scene.yaml alone)")
    args = ap.parse_args(argv)
    for t in args.tasks:
        if t not in TASKS:
            print(f"error: unknown task {t!r} (one of {', '.join(TASKS)})", file=sys.stderr)
            return 2
    t0 = time.monotonic()
    try:
        paths = generate(args.out, args.tasks, args.seed, profile=args.profile)
    except (BagError, OSError, ValueError, RuntimeError) as e:
        print(f"error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    total = sum(f.stat().st_size for p in paths for f in p.iterdir())
    print(f"dataset: {len(paths)} bags (profile {args.profile}, seed {args.seed}), {total / 1e6:.2f} MB in total, "
          f"{time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
