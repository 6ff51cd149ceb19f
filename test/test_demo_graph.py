"""System test: the whole demo graph (`supervisor demo`) on the simulated OR, with the Vega killed mid-run.

One run of the real graph -- simulator with its Vega emulator and UDP streams, omc_driver, ndi_driver,
diana_state, fusion_node (five filters), margin_node, record -- as separate processes on a private domain.
Halfway through, the simulator switches its Vega emulator off (as if the process were killed) and later
starts a fresh one on the same port. The assertions read what the run left behind: the supervisor's
output, the simulator's event log and the recorded bag.
"""

from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.diagnostics import as_level
from fullperc_common.testing import claim_domain, installed_exe

TASK = "B-G-P"
OUTAGE = (6.0, 12.0)   # task seconds during which the Vega is off
LETTER = {1: "B", 2: "G", 3: "P"}
SOURCE_GLOBAL, SOURCE_LOCAL = 1, 2
# share of a target's samples the live node may lose itself: of the offline replay's outputs (every recorded input
# sample), those the node never published. Its input queues hold seconds (qos_depth) and it drains them at shutdown,
# so on a busy machine it falls behind and catches up instead of dropping; what it loses it must count and WARN on
# /diagnostics (_node_losses, an upper bound: frame-number gaps count as lost even when the body was occluded then)
MAX_LOSS = 0.02

pytestmark = pytest.mark.system


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    with claim_domain() as lease:
        env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        p = subprocess.run([installed_exe("fullperc_eval", "supervisor"), "demo", "--task", TASK, "--out", str(out),
                            "--set", f"vega_outage={OUTAGE[0]}:{OUTAGE[1]}"],
                           env=env, capture_output=True, text=True, timeout=900)
    run_dir = next(out.iterdir())
    return p, run_dir


def _events(run_dir: Path) -> list[dict]:
    evs = []
    for line in (run_dir / "logs" / "sim.log").read_text().splitlines():
        try:
            evs.append(json.loads(line))
        except ValueError:
            pass
    return evs


def _node_losses(run_dir: Path, target: str = "tool") -> int:
    """Samples of ``target`` fusion_node lost itself, from the recorded /diagnostics; fails the test when a loss was
    never WARNed. The graph's eight processes can be more than a 2-core machine keeps up with: then the node falls
    behind and loses samples from its input queues (seen: 455 of 3,361 OMC samples, the node ten seconds behind at
    the end of the task) -- counted and WARNed, which is what it must do; its estimates are then of other samples
    than the recording's. The node counts every frame-number gap of the OTS as lost; the Vega frames ndi_driver
    never read (its ``skipped_frames``: a late poll gets the newest frame) are in neither the recording nor the node,
    so they are not counted here (one run: 47 skipped, and the node's 47 lost OTS samples per target were those)."""
    last: dict[str, str] = {}
    skipped = 0
    warned = []
    for m in _read(run_dir / "bag", ["/diagnostics"])["/diagnostics"]:
        for st in m.status:
            if st.name == f"fusion_node: target {target}":
                last = {kv.key: kv.value for kv in st.values}
                if as_level(st.level) >= 1 and "lost samples" in st.message:
                    warned.append(st.message)
            elif st.name.startswith("ndi_driver"):
                skipped = max(skipped, int(next((kv.value for kv in st.values if kv.key == "skipped_frames"), 0)))
    omc, ots = (int(last.get(k) or 0) for k in ("omc_samples_lost", "ots_samples_lost"))
    assert not (omc or ots) or warned, f"fusion_node lost {omc + ots} samples without a WARN naming them"
    return omc + max(0, ots - skipped)


def _truth(run_dir: Path, target: str, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The target's true position in ``base`` at ``stamps_ns`` and the validity mask: the Diana forward kinematics
    for the arm-held tool, the simulator's truth track for the instrument."""
    return _truth_track(run_dir, target).position_base(stamps_ns)


@functools.cache
def _truth_track(run_dir: Path, target: str):
    """The target's truth track (read once per run: every bag open costs seconds)."""
    from fullperc_eval.bag.calibration import load_calibration
    from fullperc_eval.evaluation.ground_truth import GroundTruth, target_truth

    track = target_truth(run_dir / "bag", target)
    if track is None:
        js = _read(run_dir / "bag", ["/diana/joint_states"])["/diana/joint_states"]
        track = GroundTruth([_ns(m.header) for m in js], [list(m.position) for m in js],
                            load_calibration(run_dir / "calibration.yaml"))
    return track


def _live_vs_offline(run_dir: Path, target: str) -> dict[str, dict[str, float]]:
    """Per paper method, live (the node's recorded outputs) against offline (the evaluator's replay of the
    recording): ``n_live`` outputs, ``n_common`` at a stamp both have, ``median_mm`` distance between the two
    estimates there, and the MAE against the truth over those common stamps, ``mae_live_mm`` and ``mae_offline_mm``.
    At a common stamp both ran the same core on the same samples; what the node lost changes the estimates after
    it (the static links it averaged, a bias learned from fewer pairs)."""
    from fullperc_eval.evaluation.config import PAPER_METHODS, replay_config
    from fullperc_eval.evaluation.replay import live_replay, replay

    config, _ = replay_config(run_dir / "fusion.yaml", target)   # the demo's: reorder_delay = the node's
    # on_time: a sample the recorder got more than `history` late (a DDS repair under load) is replayed where the node,
    # which got it in time, fused it (evaluation/on_time.py: a CI run at load had three OMC samples 2.66 s late)
    off = replay(run_dir / "bag", config, progress=False, on_time=True).outputs
    live = live_replay(run_dir / "bag", target=target).outputs
    out = {}
    for m in PAPER_METHODS:
        common, i, j = np.intersect1d(off[m]["t_ns"], live[m]["t_ns"], assume_unique=True, return_indices=True)
        d = np.linalg.norm(off[m]["p"][i] - live[m]["p"][j], axis=1) * 1e3
        truth, ok = _truth(run_dir, target, common)
        e_off = np.linalg.norm(off[m]["p"][i][ok] - truth[ok], axis=1) * 1e3
        e_live = np.linalg.norm(live[m]["p"][j][ok] - truth[ok], axis=1) * 1e3
        out[m] = {"n_live": len(live[m]["t_ns"]), "n_offline": len(off[m]["t_ns"]), "n_common": int(i.size),
                  "n_truth": int(ok.sum()),
                  "median_mm": float(np.median(d)) if i.size else float("nan"),
                  "mae_live_mm": float(e_live.mean()) if ok.any() else float("nan"),
                  "mae_offline_mm": float(e_off.mean()) if ok.any() else float("nan")}
    return out


def _input_samples(run_dir: Path, target: str) -> int:
    """The target's input samples in the recording: its OMC and Vega poses."""
    got = _read(run_dir / "bag", [f"/omc/{target}/pose", f"/ots/{target}/pose"])
    return sum(len(v) for v in got.values())


def _check_live_against_offline(run_dir: Path, target: str, diff_mm: float, record_property) -> None:
    """The node lost at most MAX_LOSS of the target's OMC samples -- offline OMC pass-through outputs (one per recorded
    OMC sample) it never published; the figures of every method go to the test report --, and on the stamps both
    hold its estimates are the offline
    replay's: median distance <= ``diff_mm``, and the same MAE against the truth to 0.05 mm (or 2 %).

    Why outputs and not the node's own count: that is an upper bound (a frame-number gap is counted as a lost pose
    even when the body was occluded then; a CI run counted 173 of the walking instrument's while the node had
    published an output of each of its OMC samples), so it is reported, not limited."""
    counted, n_in = _node_losses(run_dir, target), _input_samples(run_dir, target)
    cmp = _live_vs_offline(run_dir, target)
    missing = {m: c["n_offline"] - c["n_common"] for m, c in cmp.items()}
    record_property("demo", f"{target}: the node counted {counted} of {n_in} input samples lost; live vs offline on "
                    "common stamps: " + ", ".join(
                        f"{m} {c['n_common']}/{c['n_live']} live, {missing[m]} of {c['n_offline']} offline outputs "
                        f"missing live, MAE {c['mae_live_mm']:.3f}/{c['mae_offline_mm']:.3f} mm median diff "
                        f"{c['median_mm']:.3f} mm" for m, c in cmp.items()))
    # the OMC pass-through has one output per OMC sample fused: its offline outputs the node never published are OMC
    # samples it lost (the side-by-side filters' topics are not: a run with 0 lost lacked 61-388 of theirs)
    c = cmp["omc"]
    assert missing["omc"] <= MAX_LOSS * c["n_offline"], \
        f"the live node lacks {missing['omc']} of the {c['n_offline']} omc outputs of {target} ({counted} " \
        "input samples counted lost)"
    for method, c in cmp.items():
        assert c["n_common"] >= 0.5 * c["n_live"] and c["n_truth"] >= 0.9 * c["n_common"], (method, c)
        assert c["median_mm"] <= diff_mm, (method, c)
        assert abs(c["mae_live_mm"] - c["mae_offline_mm"]) <= max(0.05, 0.02 * c["mae_offline_mm"]), (method, c)


_DECODED: dict[tuple[Path, str], list] = {}   # (bag, topic) -> its messages: the module's tests read one bag


def _read(bag: Path, topics: list[str]) -> dict[str, list]:
    """The messages of ``topics`` in ``bag``, decoded; the topics not read before in one pass (an open of the demo's
    bag costs 1-2 s: rosbags parses every channel's QoS YAML). Callers must not modify the lists."""
    from fullperc_eval.bag.reader import BagReader

    missing = [t for t in topics if (bag, t) not in _DECODED]
    if missing:
        got: dict[str, list] = {t: [] for t in missing}
        r = BagReader(bag)
        r.open()
        try:
            for m in r.messages([t for t in missing if t in r.topics]):
                got[m.topic].append(r.deserialize(m.data, m.msgtype))
        finally:
            r.close()
        _DECODED.update(((bag, t), v) for t, v in got.items())
    return {t: _DECODED[(bag, t)] for t in topics}


def _ns(h) -> int:
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def test_demo_runs_and_prints_the_table(demo):
    p, run_dir = demo
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert "Table 1: MAE" in p.stdout and "report:" in p.stdout
    assert (run_dir / "report" / "index.html").exists()
    assert re.search(r"region tool: \w+ -> \w+", p.stdout), "live region changes were not shown"


def test_no_process_left_behind(demo):
    p, _ = demo
    pids = [int(x) for x in re.findall(r"started \w+ \(pid (\d+)\)", p.stdout)]
    assert len(pids) == 7   # one graph for both targets: no process per target
    for pid in pids:
        assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]


def test_fused_poses_in_base_with_monotonic_stamps(demo):
    _, run_dir = demo
    got = _read(run_dir / "bag", ["/fullperc/tool/pose", "/fullperc/tool/ckf/pose"])
    for topic, msgs in got.items():
        assert len(msgs) > 500, topic
        assert {m.header.frame_id for m in msgs} == {"base"}
        stamps = np.array([_ns(m.header) for m in msgs])
        assert np.all(np.diff(stamps) > 0), f"{topic}: stamps not strictly increasing"
        P = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in msgs])
        assert np.all(np.isfinite(P))


NEAR_M = 0.005  # a label may differ from the truth's only within this distance of the truth (CBKF max error 2.95 mm)


def _true_labels(run_dir: Path, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, object, np.ndarray]:
    """Region labels of the true target position (Diana FK, the bag's calibration) at ``stamps_ns``.

    Returns (labels, valid mask, layout, true positions in the layout frame).
    """
    from fullperc_eval.bag.calibration import load_calibration
    from fullperc_eval.evaluation.ground_truth import GroundTruth
    from fullperc_fusion.margin.layout import default_layout_path, load_layout
    from fullperc_fusion.margin.view_margin import label_points

    js = _read(run_dir / "bag", ["/diana/joint_states"])["/diana/joint_states"]
    cal = load_calibration(run_dir / "calibration.yaml")
    gt = GroundTruth([_ns(m.header) for m in js], [list(m.position) for m in js], cal)
    layout = load_layout(default_layout_path())
    p_base, valid = gt.position_base(stamps_ns)
    P = p_base @ cal.T_omc_base[:3, :3].T + cal.T_omc_base[:3, 3]
    labels = np.zeros(len(P), dtype=int)
    labels[valid] = label_points(layout, P[valid])[0]
    return labels, valid, layout, P


def test_region_labels_follow_the_task_order(demo):
    from fullperc_common.runs import runs
    from fullperc_fusion.margin.view_margin import label_points

    _, run_dir = demo
    msgs = _read(run_dir / "bag", ["/fullperc/tool/region"])["/fullperc/tool/region"]
    msgs = sorted((m for m in msgs if m.label in LETTER), key=lambda m: _ns(m.header))
    labels = np.array([m.label for m in msgs])
    truth, valid, layout, P = _true_labels(run_dir, np.array([_ns(m.header) for m in msgs]))
    if valid.mean() <= 0.99:   # the joint states (the truth) must cover the labels: say what is missing
        js = np.array([_ns(m.header) for m in _read(run_dir / "bag", ["/diana/joint_states"])["/diana/joint_states"]])
        stamps = np.array([_ns(m.header) for m in msgs])
        raise AssertionError(
            f"{(~valid).sum()} of {len(msgs)} labels without a joint state near them: labels from {stamps[0]} to "
            f"{stamps[-1]}, {len(js)} joint states from {js[0]} to {js[-1]}, largest gap "
            f"{np.diff(js).max() / 1e6:.1f} ms, {(np.diff(js) > 50e6).sum()} gaps > 50 ms")
    # every label is right, or the truth is within NEAR_M of the labelled region: the labels are of the fused
    # estimate, and near a boundary its error may put it on the other side
    dirs = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if i or j or k], float)
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    for i in np.flatnonzero(valid & (labels != truth)):
        near = np.concatenate([P[i] + r * dirs for r in (NEAR_M / 4, NEAR_M / 2, NEAR_M)])
        assert labels[i] in label_points(layout, near)[0], (i, labels[i], truth[i], P[i])
    # the order: runs of >= 10 labels (shorter ones are boundary flicker, < 0.1 s), leaving out a run the truth
    # is not in for most of it -- the estimate crossing a boundary the true path runs along (B-G-P ends within
    # 1 mm of the GVV for its last 7 s), which the check above bounds to NEAR_M
    order = []
    for lab, i0, i1 in runs(labels):
        if i1 - i0 + 1 >= 10 and np.mean(truth[i0:i1 + 1] == lab) >= 0.5 and (not order or order[-1] != LETTER[lab]):
            order.append(LETTER[lab])
    assert "-".join(order) == TASK


def test_recorded_bag_evaluates_like_the_live_outputs(demo, record_property):
    _, run_dir = demo
    off = json.loads((run_dir / "report" / "eval.json").read_text())["mae_mm"]
    live = json.loads((run_dir / "report" / "eval_live.json").read_text())["mae_mm"]
    from fullperc_eval.evaluation.config import METHODS, PAPER_METHODS

    # the demo's fusion_node runs the paper's five live (demo_graph.yaml); the offline table has every method
    assert all(off[m] is not None for m in METHODS), off
    for method in PAPER_METHODS:
        assert live[method] is not None, method
    # on the stamps both hold, the live estimates are the offline replay's (seen: medians 0.03-0.05 mm; a node
    # fusing with a wrong link or chain is millimetres off)
    _check_live_against_offline(run_dir, "tool", 0.5, record_property)
    for method in PAPER_METHODS:
        # the whole outputs too: the same core, config and first samples (test below), nearly the same samples
        assert abs(off[method] - live[method]) <= max(0.15, 0.05 * off[method]), (method, off, live)


def test_bag_holds_the_task_from_its_first_sample(demo):
    """The static links are averaged over the first samples, so a bag that misses them evaluates differently
    from the live run (CI saw 0.5 mm on the OMC column when the recorder subscribed late)."""
    _, run_dir = demo
    t0 = next(e for e in _events(run_dir) if e.get("event") == "start")["t0_host_ns"]
    got = _read(run_dir / "bag", ["/omc/base/quality", "/omc/base/pose", "/ots/base/pose"])
    assert min(m.frame_number for m in got["/omc/base/quality"]) == 1
    # the first OMC frame's pose (its stamp is the frame's quality message's: both are stamped with the frame's
    # acquisition time, which the driver's clock sync places -- on a busy machine a few milliseconds later than t0)
    first = next(_ns(m.header) for m in got["/omc/base/quality"] if m.frame_number == 1)
    poses = sorted(_ns(m.header) for m in got["/omc/base/pose"])
    assert first in poses, f"frame 1 at t0 + {(first - t0) / 1e6:.1f} ms; first poses at t0 + " \
        f"{[round((p - t0) / 1e6, 1) for p in poses[:3]]} ms"
    assert first - t0 < 100_000_000    # the task's first frame, not a later one
    assert min(_ns(m.header) for m in got["/ots/base/pose"]) - t0 < 100_000_000      # first Vega frames (60 Hz)


def test_fusion_continues_on_omc_alone_and_recovers(demo):
    _, run_dir = demo
    ev = {e["event"]: e for e in _events(run_dir) if "event" in e}
    off_ns, on_ns = ev["vega_off"]["t_host_ns"], ev["vega_on"]["t_host_ns"]
    got = _read(run_dir / "bag", ["/ots/base/pose", "/fullperc/tool/status", "/fullperc/tool/pose"])
    ots = np.array([_ns(m.header) for m in got["/ots/base/pose"]])
    assert np.sum(ots < off_ns) > 30, "the Vega was not tracking before the outage"
    assert not np.any((ots > off_ns + 200_000_000) & (ots < on_ns)), "OTS poses during the outage"
    after = ots[ots > on_ns]
    assert after.size > 30 and after[0] - on_ns < 5_000_000_000, "the ndi_driver did not recover"
    # after the Vega comes back the driver has re-loaded both tools: quality of the target tool flows again
    # (the target itself has left the Vega's volume by then in this task, so visible may be false)
    q = _read(run_dir / "bag", ["/ots/tool/quality"])["/ots/tool/quality"]
    assert sum(1 for m in q if _ns(m.header) > on_ns) > 30, "the target tool was not re-loaded after the outage"
    # fused output kept coming during the outage, from the global source only
    st = [m for m in got["/fullperc/tool/status"] if off_ns + 500_000_000 < _ns(m.header) < on_ns]
    lost = _node_losses(run_dir)
    # Every OMC sample of the outage is fused (its status published) or counted lost: a node behind its inputs on a
    # busy machine catches up from its input queues (qos_depth), and what it still loses it counts and WARNs
    # (_node_losses; at most MAX_LOSS of the task, test_recorded_bag_evaluates_like_the_live_outputs)
    assert len(st) + lost > 0.9 * 120 * (on_ns - off_ns - 500_000_000) / 1e9, \
        f"{len(st)} outputs in the outage and {lost} samples counted lost: the rest went missing uncounted"
    assert len(st) >= 30, f"{len(st)} outputs in the outage ({lost} samples counted lost): nothing to check"
    assert all(m.sources == SOURCE_GLOBAL for m in st)
    assert all(m.filter == "cbkf" for m in st)
    # CBKF keeps compensating with the bias it learned while the OTS saw the target
    before = [m for m in got["/fullperc/tool/status"] if _ns(m.header) < off_ns and m.sources & SOURCE_LOCAL]
    assert before, "the OTS never saw the target before the outage"
    b0 = np.array([before[-1].bias.x, before[-1].bias.y, before[-1].bias.z])
    bias = np.array([[m.bias.x, m.bias.y, m.bias.z] for m in st])
    assert np.linalg.norm(b0) > 2e-4
    # Without the OTS the bias is unobservable and stays as learned -- except where the OMC hops: a hop's jump goes
    # into the bias (hop_to_bias), by design. With the `paper` twin (OMC jumps of several mm where few cameras see
    # the tool) a hop during the outage is normal, so: no drift between hops, and the bias never falls to zero.
    hop = np.array([m.hop for m in st])
    step = np.linalg.norm(np.diff(np.vstack([b0, bias]), axis=0), axis=1)
    assert np.all(step[~hop] < 2e-4), f"bias drifted without a hop: {step[~hop].max() * 1e3:.3f} mm in one update"
    first_hop = int(np.argmax(hop)) if hop.any() else len(st)
    assert np.all(np.linalg.norm(bias[:first_hop], axis=1) > 0.5 * np.linalg.norm(b0))
    assert np.all(np.linalg.norm(bias, axis=1) > 2e-4)


# ------------------------------------------------------------------------------- the second target (instrument)
INSTRUMENT = "instrument"


def test_the_bag_holds_both_targets(demo):
    _, run_dir = demo
    topics = [f"/omc/{INSTRUMENT}/pose", f"/ots/{INSTRUMENT}/pose", f"/fullperc/{INSTRUMENT}/pose",
              f"/fullperc/{INSTRUMENT}/ckf/pose", f"/fullperc/{INSTRUMENT}/omc/pose", f"/sim/truth/{INSTRUMENT}",
              "/fullperc/tool/pose"]
    got = _read(run_dir / "bag", topics)
    for t in topics:
        assert len(got[t]) > 100, t
    for t in (f"/fullperc/{INSTRUMENT}/pose", f"/sim/truth/{INSTRUMENT}"):
        assert {m.header.frame_id for m in got[t]} == {"base"}, t
        stamps = np.array([_ns(m.header) for m in got[t]])
        assert np.all(np.diff(stamps) > 0), f"{t}: stamps not strictly increasing"
    # the fused instrument follows its truth as closely as the node's OMC pass-through does. With the arm's motion
    # model and hop rule (before <target>.accel_noise / hop_to_bias) the walk's accelerations were taken for OMC hops
    # and went into the bias: medians 8-15 mm against the OMC's 2.3-4.8 on the same samples, and 0.25 m for seconds
    # (CI saw 65 mm) when the node, on a busy machine, lost samples. Compared on the samples both topics hold: when
    # the node loses samples, each topic keeps other parts of the walk, whose errors differ by millimetres (CI:
    # medians 4.9 mm for CKF's 1,600-odd outputs against 2.3 mm for the OMC's; on common samples the two agreed)
    from fullperc_eval.evaluation.ground_truth import load_truth_track

    track = load_truth_track(run_dir / "bag", INSTRUMENT)

    def errors(topic: str) -> dict[int, float]:
        P = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in got[topic]])
        stamps = np.array([_ns(m.header) for m in got[topic]])
        truth, ok = track.position_base(stamps)
        assert ok.mean() > 0.95, topic
        return dict(zip(stamps[ok].tolist(), np.linalg.norm(P[ok] - truth[ok], axis=1).tolist(), strict=True))

    omc = errors(f"/fullperc/{INSTRUMENT}/omc/pose")
    lost = _node_losses(run_dir, INSTRUMENT)
    # cbkf is the demo's primary filter: its poses are /fullperc/<target>/pose
    for method, topic in (("ckf", f"/fullperc/{INSTRUMENT}/ckf/pose"), ("cbkf", f"/fullperc/{INSTRUMENT}/pose")):
        err = errors(topic)
        common = sorted(set(err) & set(omc))
        assert len(common) > 100, (method, len(err), len(omc), lost)
        e_f, e_o = np.median([err[s] for s in common]), np.median([omc[s] for s in common])
        assert e_f <= 1.5 * e_o + 1e-3, (method, e_f, e_o, f"{len(common)} common samples, node lost {lost}")


def test_the_bag_tf_has_base_to_each_target_in_rosbags_jazzy_types(demo):
    """Issue 17's acceptance: the demo's /tf and /tf_static decode with rosbags' own Jazzy type store (not the
    definitions stored in the bag) and hold base -> each target, and the static links from the calibration."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    _, run_dir = demo
    ts = get_typestore(Stores.ROS2_JAZZY)
    edges: dict[str, set[tuple[str, str]]] = {"/tf": set(), "/tf_static": set()}
    with Reader(run_dir / "bag") as r:
        conns = [c for c in r.connections if c.topic in edges]
        assert {c.msgtype for c in conns} == {"tf2_msgs/msg/TFMessage"}
        for conn, _t, raw in r.messages(connections=conns):
            for tf in ts.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage").transforms:
                edges[conn.topic].add((tf.header.frame_id, tf.child_frame_id))
    assert {("base", "tool"), ("base", INSTRUMENT)} <= edges["/tf"], edges["/tf"]
    assert {("omc", "base"), ("base", "ots"), ("base", "diana_base")} <= edges["/tf_static"], edges["/tf_static"]
    assert ("diana_base", "diana_link1") in edges["/tf"], "diana_state's arm tree hangs under diana_base"


def test_the_arm_hangs_under_base_with_the_simulators_transform(demo):
    """fusion_node's base -> diana_base (from the demo's sim_diana_base, computed before the graph starts) is the
    transform the simulator itself wrote to calibration.yaml after the run: in RViz the arm's link tree and the fused
    targets share one tree."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    from fullperc_eval.bag.calibration import load_calibration

    _, run_dir = demo
    ts = get_typestore(Stores.ROS2_JAZZY)
    got = []
    with Reader(run_dir / "bag") as r:
        conns = [c for c in r.connections if c.topic == "/tf_static"]
        for _conn, _t, raw in r.messages(connections=conns):
            got += [tf.transform for tf in ts.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage").transforms
                    if (tf.header.frame_id, tf.child_frame_id) == ("base", "diana_base")]
    assert got
    T = load_calibration(run_dir / "calibration.yaml").T_base_diana_base
    for tr in got:
        p = np.array([tr.translation.x, tr.translation.y, tr.translation.z])
        q = np.array([tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w])
        assert np.allclose(p, T[:3, 3], atol=1e-9)
        R = Rotation.from_quat(q).as_matrix()
        assert np.allclose(R, T[:3, :3], atol=1e-9)


def test_the_instrument_is_labelled_and_evaluated(demo, record_property):
    p, run_dir = demo
    from fullperc_eval.evaluation.ground_truth import load_truth_track
    from fullperc_fusion.margin.layout import default_layout_path, load_layout
    from fullperc_fusion.margin.view_margin import label_points

    assert f"region {INSTRUMENT}:" in p.stdout, "margin_node did not label the instrument live"
    msgs = _read(run_dir / "bag", [f"/fullperc/{INSTRUMENT}/region"])[f"/fullperc/{INSTRUMENT}/region"]
    msgs = [m for m in msgs if m.label in LETTER]
    assert {LETTER[m.label] for m in msgs} == {"B", "G", "P"}
    # the labels are of the fused estimate: mostly those of the true position (they differ near boundaries)
    from fullperc_eval.bag.calibration import load_calibration

    cal = load_calibration(run_dir / "calibration.yaml")
    truth, ok = load_truth_track(run_dir / "bag", INSTRUMENT).position_base(np.array([_ns(m.header) for m in msgs]))
    P = truth[ok] @ cal.T_omc_base[:3, :3].T + cal.T_omc_base[:3, 3]
    true_labels = label_points(load_layout(default_layout_path()), P)[0]
    assert np.mean(np.array([m.label for m in msgs])[ok] == true_labels) > 0.8
    off = json.loads((run_dir / "report" / INSTRUMENT / "eval.json").read_text())
    live = json.loads((run_dir / "report" / INSTRUMENT / "eval_live.json").read_text())
    assert off["target"] == INSTRUMENT and f"B-G-P {INSTRUMENT}" in p.stdout
    # the raw OMC and the plain KF, offline and live: millimetres, as the OMC's error; no tight agreement asked for:
    # with two targets fusion_node needs ~0.9 of a core here, and on a loaded machine DDS drops samples the recorder
    # kept (seen: 0.21 mm on the OMC column at load 7). The compensated filters' MAE is not compared: on a walking
    # target their bias after a hop is not stable against a few dropped samples (docs/targets.md);
    # their estimates are, at the stamps both hold (_live_vs_offline, below).
    for method in ("omc", "kf"):
        assert off["mae_mm"][method] < 5.0 and live["mae_mm"][method] < 5.0, (method, off["mae_mm"], live["mae_mm"])
    # the recorded Vega poses of the walking instrument are of their stamps' times: the raw Vega chain is off its
    # truth by the twin's Vega error (0.17-0.21 mm in three runs). When the emulator answered each frame with the
    # latest simulated sample before it, the poses were up to a period (16.7 ms) older than their stamps, by a phase
    # that changed from run to run: 0.30-1.46 mm, and the compensated filters learned that as the OMC's bias (CI:
    # CKF 4.9 mm vs OMC 2.4)
    assert off["single_sources"]["local"]["mae_mm"] < 0.6, off["single_sources"]["local"]
    # as for the tool (test_recorded_bag_evaluates_like_the_live_outputs): the node lost at most MAX_LOSS, and at the
    # stamps both hold its estimates are the offline replay's (the walking target's bias moves more with a lost pair
    # than the arm-held tool's; offline with the arm's motion model instead, CKF and CBKF are 9.6-11.5 mm off)
    _check_live_against_offline(run_dir, INSTRUMENT, 2.0, record_property)
    for method in ("omc", "kf"):
        assert abs(off["mae_mm"][method] - live["mae_mm"][method]) <= max(0.5, 0.25 * off["mae_mm"][method]), method

if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-v"]))
