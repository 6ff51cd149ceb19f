"""Dataset bags hold exactly what the live drivers publish (topics, types, frames, SI units, acquisition stamps)
plus the calibration for the ground truth; the simulator's truth survives the trip through the bag."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from fullperc_drivers.diana_kinematics import JOINT_NAMES, DianaKinematics
from fullperc_eval.bag.calibration import load_calibration
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.metadata import load_metadata
from fullperc_eval.bag.reader import BagReader
from fullperc_eval.evaluation.ground_truth import GroundTruth
from fullperc_eval.sim.dataset import content_from_sim, generate, synthetic_content, write_bag


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    content, truth = synthetic_content(2.0, ots_window_s=(0.5, 1.5))
    # one frame claims "visible" with a NaN pose: a driver would never publish that pose
    content.omc.bodies["tool"].position[7] = np.nan
    bag = write_bag(tmp_path_factory.mktemp("ds") / "bag", content)
    r = BagReader(bag).open()
    msgs: dict[str, list] = {}
    for m in r.messages():
        msgs.setdefault(m.topic, []).append((m.timestamp, r.deserialize(m.data, m.msgtype)))
    r.close()
    return bag, content, msgs, BagReader(bag)


def ns(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def test_topics_and_types_are_the_drivers(written):
    _, _, _, reader = written
    want = {f"/omc/{b}/pose": "geometry_msgs/msg/PoseStamped" for b in ("base", "ots_rig", "tool")}
    want |= {f"/omc/{b}/quality": "fullperc_msgs/msg/TrackingQuality" for b in ("base", "ots_rig", "tool")}
    want |= {f"/ots/{b}/pose": "geometry_msgs/msg/PoseStamped" for b in ("tool", "base")}
    want |= {f"/ots/{b}/quality": "fullperc_msgs/msg/TrackingQuality" for b in ("tool", "base")}
    want |= {"/diana/joint_states": "sensor_msgs/msg/JointState", "/diana/flange_pose": "geometry_msgs/msg/PoseStamped"}
    assert {t: i.msgtype for t, i in reader.topics.items()} == want
    assert reader.storage == "mcap"
    assert reader.info["custom_data"]["task"] == "synthetic"


def test_omc_poses_frames_stamps_and_units(written):
    _, c, msgs, _ = written
    b = c.omc.bodies["tool"]
    ok = b.visible & np.all(np.isfinite(b.position), axis=1)
    poses = msgs["/omc/tool/pose"]
    assert len(poses) == int(ok.sum()) == len(c.omc.t_ns) - 1
    stamps = np.array([ns(m.header) for _, m in poses])
    assert np.array_equal(stamps, c.omc.t_ns[ok])                                   # acquisition time
    assert np.array_equal(np.array([t for t, _ in poses]), stamps + c.omc.latency_ns)  # bag time = receipt
    assert {m.header.frame_id for _, m in poses} == {"omc"}
    P = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for _, m in poses])
    Q = np.array([[m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w]
                  for _, m in poses])
    np.testing.assert_array_equal(P, b.position[ok])                              # metres, unchanged
    np.testing.assert_array_equal(Q, b.quat_xyzw[ok])                             # x y z w


def test_quality_for_every_frame_with_visibility(written):
    _, c, msgs, _ = written
    q = msgs["/omc/tool/quality"]
    assert len(q) == len(c.omc.t_ns)
    vis = [m.visible for _, m in q]
    assert vis[7] is False and sum(vis) == len(q) - 1                              # the NaN frame
    assert [m.frame_number for _, m in q] == list(range(1, len(q) + 1))
    assert {m.body for _, m in q} == {"tool"} and {m.header.frame_id for _, m in q} == {"omc"}
    assert q[0][1].latency == pytest.approx(c.omc.latency_ns * 1e-9, rel=1e-6)
    oq = msgs["/ots/tool/quality"]
    assert len(oq) == len(c.ots.t_ns)
    assert sum(m.visible for _, m in oq) == len(msgs["/ots/tool/pose"]) == int(c.ots.bodies["tool"].visible.sum())
    assert {m.header.frame_id for _, m in msgs["/ots/tool/pose"]} == {"ots"}
    assert {m.port_status for _, m in oq} == {0x31}


def test_joint_states_and_flange_pose(written):
    _, c, msgs, _ = written
    js = msgs["/diana/joint_states"]
    assert len(js) == len(c.diana.t_ns)
    assert all(list(m.name) == list(JOINT_NAMES) and m.header.frame_id == "diana_base" for _, m in js)
    np.testing.assert_array_equal(np.array([m.position for _, m in js]), c.diana.q)
    assert np.array_equal(np.array([ns(m.header) for _, m in js]), c.diana.t_ns)
    fl = msgs["/diana/flange_pose"]
    T = DianaKinematics().fk(c.diana.q[5])
    m = fl[5][1]
    np.testing.assert_allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z], T[:3, 3], atol=1e-12)
    assert m.header.frame_id == "diana_base"


def test_bag_time_never_goes_backwards_and_metadata_counts(written):
    bag, _, msgs, _ = written
    info = load_metadata(bag)
    assert info["message_count"] == sum(len(v) for v in msgs.values())
    r = BagReader(bag).open()
    ts = [m.timestamp for m in r.messages()]
    r.close()
    assert ts == sorted(ts)


def test_calibration_travels_with_the_bag(written):
    bag, c, _, _ = written
    cal = load_calibration(bag)
    for k in ("T_base_diana_base", "T_flange_tool", "T_omc_base"):
        np.testing.assert_allclose(getattr(cal, k), getattr(c.calibration, k), atol=1e-12)


def test_simulator_truth_survives_the_bag(tmp_path):
    """Ground truth rebuilt from the bag (joint states + calibration.yaml) equals the simulator's own truth."""
    from fullperc_eval.sim.run import simulate
    from fullperc_eval.sim.scene import build_scene
    from fullperc_eval.sim.trajectories import JointArc

    scene = build_scene(0)
    # 0.2 rad in 4 s, minimum jerk: peak 5.77 * 0.2 / 4^2 = 0.072 rad/s^2 (the tasks: ~0.03), so linear
    # interpolation between 10 ms joint samples is off by at most a dt^2 / 8 = 0.9 µrad, ~1 µm at 1 m reach
    arc = JointArc((0.3, 0.5, 0.0, 1.6, 0.0, 0.6, 0.0), 0, 0.3, 0.5, 4.0, 0.2, 0.2)
    run = simulate(scene, arc, task="unit")
    bag = write_bag(tmp_path / "sim", content_from_sim(run))
    r = BagReader(bag).open()
    t, q = [], []
    for m in r.messages(["/diana/joint_states"]):
        js = r.deserialize(m.data, m.msgtype)
        t.append(ns(js.header))
        q.append(js.position)
    r.close()
    gt = GroundTruth(t, np.array(q), load_calibration(bag))
    epoch = t[0] - int(run.diana.t_ns[0])
    P, ok = gt.position_base(run.omc.t_ns + epoch)
    assert ok.all()
    np.testing.assert_allclose(P, run.truth.T_base_tool[:, :3, 3], atol=2e-6)
    info = load_metadata(bag)
    assert info["custom_data"] == {"generator": "fullperc_eval.dataset", "task": "unit", "seed": "0", "profile": "base"}


def test_generate_refuses_to_overwrite_foreign_directories(tmp_path):
    (tmp_path / "G-B-P").mkdir()
    (tmp_path / "G-B-P" / "precious.txt").write_text("keep me")
    with pytest.raises(BagError, match="not written by"):
        generate(tmp_path, ["G-B-P"])
    assert (tmp_path / "G-B-P" / "precious.txt").read_text() == "keep me"


def test_cli_rejects_unknown_task(tmp_path):
    p = subprocess.run([sys.executable, "-m", "fullperc_eval.sim.dataset", "--out", str(tmp_path), "--tasks", "B-X"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "unknown task 'B-X'" in p.stderr and "Traceback" not in p.stderr
