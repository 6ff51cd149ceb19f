"""The evaluator's faster reading and figures give what the plain ones give, exactly (issue 38 item 5).

* the OMC qualities for fullperc's model covariance, bulk-decoded, against rosbags message by message;
* the bag metadata through libyaml against PyYAML's pure-Python loader, on every committed bag;
* the MCAP walk's one-unpack message branch against rosbags' reader on a bag with several chunks;
* the orientation and NEES figures, computed once per distinct (truth rows, quaternions), against computing them for
  every method (the paper's filters output the same quaternions on the same items);
* the orientation figures' rotations and products (``orientation._from_matrix`` / ``_compose``) against scipy's
  ``Rotation.from_matrix`` and ``*``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from fullperc_eval.bag import metadata
from fullperc_eval.bag.reader import BagReader, _raw_messages
from fullperc_eval.evaluation import metrics
from fullperc_eval.evaluation.consistency import FUSED_ORIENTATION, nees
from fullperc_eval.evaluation.ground_truth import GroundTruth
from fullperc_eval.evaluation.orientation import _compose, _from_matrix, orientation_error_deg, pose_error
from fullperc_eval.evaluation.replay import omc_quality_by_stamp, replay
from fullperc_fusion.fusion_config import load_fusion_config

ROOT = Path(__file__).resolve().parents[3]
BAGS = sorted(p.parent for p in (ROOT / "bags").glob("*/*/metadata.yaml"))
SAMPLE = ROOT / "bags" / "paper" / "G-B-P"


@pytest.fixture(scope="module")
def every_method():
    cfg, _ = load_fusion_config()
    assert "fullperc" in cfg.filters
    return cfg


def test_omc_qualities_equal_rosbags_message_by_message(every_method):
    reader = BagReader(SAMPLE)
    got = omc_quality_by_stamp(reader, every_method)
    ref = BagReader(SAMPLE).open()
    want: dict[int, dict[str, float]] = {}
    for m in ref.messages(["/omc/tool/quality"]):
        q = ref.deserialize(m.data, m.msgtype)
        want[int(q.header.stamp.sec) * 1_000_000_000 + int(q.header.stamp.nanosec)] = {
            "fit_error": float(q.fit_error), "markers_used": float(q.markers_used)}
    ref.close()
    assert len(got) > 1000 and list(got.items()) == list(want.items())


@pytest.mark.skipif(not hasattr(yaml, "CSafeLoader"), reason="PyYAML built without libyaml")
def test_bag_metadata_reads_the_same_through_libyaml():
    assert metadata._LOADER is yaml.CSafeLoader and len(BAGS) >= 12
    for bag in BAGS:
        want = yaml.safe_load((bag / metadata.METADATA_FILE).read_text())["rosbag2_bagfile_information"]
        assert repr(metadata.load_metadata(bag)) == repr(want), bag


def test_mcap_walk_equals_rosbags_records():
    reader = BagReader(SAMPLE)
    topics = sorted(reader.topics)
    fast = _raw_messages(reader, topics)
    ref = BagReader(SAMPLE).open()
    want = list(ref.messages(topics))
    ref.close()
    assert len(want) == len(fast.data) > 40_000
    assert [topics[k] for k in fast.topic.tolist()] == [m.topic for m in want]
    assert fast.timestamp.tolist() == [m.timestamp for m in want]
    assert fast.data == [m.data for m in want]


def _figures_per_method(outputs, idx, ok, T_true):
    """_pose_figures without the shared rotation figures: every method's own computation."""
    orient, nees_v = {}, {}
    for f, o in outputs.items():
        n = len(o["t_ns"])
        oe, npos, npose = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        k = ok[f]
        if "q" in o and k.any():
            Tt = T_true[idx[f][k]]
            oe[k] = orientation_error_deg(Tt[:, :3, :3], o["q"][k])
            d = pose_error(Tt[:, :3, 3], Tt[:, :3, :3], o["p"][k], o["q"][k])
            C = o["cov"][k]
            npos[k] = nees(d[:, :3], C[:, :3, :3])
            fused = o["orientation_source"][k] == FUSED_ORIENTATION
            if fused.any():
                tmp = np.full(len(d), np.nan)
                tmp[fused] = nees(d[fused], C[fused])
                npose[k] = tmp
        orient[f] = oe
        nees_v[f] = {"position": npos, "pose": npose}
    return orient, nees_v


def test_shared_rotation_figures_equal_each_methods_own():
    cfg, _ = load_fusion_config(filters=("omc", "kf", "bkf", "ckf", "cbkf"))
    rep = replay(SAMPLE, cfg, progress=False)
    cal = metrics.load_calibration(SAMPLE)
    gt = GroundTruth(rep.joint_t_ns, rep.joint_q, cal)
    all_t = np.unique(np.concatenate([o["t_ns"] for o in rep.outputs.values()]))
    T_true, ok_all = gt.T_base_tool(all_t)
    idx = {f: np.searchsorted(all_t, o["t_ns"]) for f, o in rep.outputs.items()}
    ok = {f: ok_all[i] for f, i in idx.items()}
    kf_q = rep.outputs["kf"]["q"]
    assert all(np.array_equal(rep.outputs[f]["q"], kf_q) for f in ("bkf", "ckf", "cbkf"))   # what is shared
    got = metrics._pose_figures(rep.outputs, idx, ok, T_true)
    want = _figures_per_method(rep.outputs, idx, ok, T_true)
    for f in rep.outputs:
        assert got[0][f].tobytes() == want[0][f].tobytes(), f
        for kind in ("position", "pose"):
            assert got[1][f][kind].tobytes() == want[1][f][kind].tobytes(), (f, kind)


def _same_rotations(a: Rotation, b: Rotation) -> bool:
    qa, qb = a.as_quat(), b.as_quat()
    return qa.shape == qb.shape and qa.tobytes() == qb.tobytes() and len(a) == len(b)


def test_rotations_and_products_equal_scipys():
    """Bit for bit: random rotations, the near-identity products of the figures (an estimate against its truth),
    the truth's matrices from forward kinematics, and matrices from_matrix has to check and project itself."""
    rng = np.random.default_rng(21)
    cal = metrics.load_calibration(SAMPLE)
    rep = replay(SAMPLE, load_fusion_config(filters=("omc", "kf", "bkf", "ckf", "cbkf"))[0], progress=False)
    gt = GroundTruth(rep.joint_t_ns, rep.joint_q, cal)
    T_fk, ok = gt.T_base_tool(gt.t_ns[:800])
    stacks = [Rotation.random(3000, rng=rng).as_matrix(), T_fk[ok, :3, :3]]
    rough = Rotation.random(50, rng=rng).as_matrix()
    rough[::7] *= 1.0 + 1e-9                           # past the fast path's vouching: from_matrix itself
    stacks.append(rough)
    for R in stacks:
        assert _same_rotations(_from_matrix(R), Rotation.from_matrix(R))
        a = Rotation.from_matrix(R)
        for b in (Rotation.random(len(R), rng=rng), Rotation.from_rotvec(rng.normal(0, 0.01, (len(R), 3))) * a):
            assert _same_rotations(_compose(a.inv(), b), a.inv() * b)
            assert _same_rotations(_compose(a, b.inv()), a * b.inv())
            assert _compose(a.inv(), b).magnitude().tobytes() == (a.inv() * b).magnitude().tobytes()
