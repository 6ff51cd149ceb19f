"""fusion_endpoints.Inputs: what fusion_node subscribes for ``inputs: per_body`` and ``frames``, and what one
callback takes -- the batch's pose items and the quality records to hand to the core before them. Fake
subscriptions hold serialized messages as rclpy's would (``take_message``), so no DDS is involved."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import serialize_message

from fullperc_common.ros_conv import ns_to_stamp, pose_stamped
from fullperc_common.transforms import T_to_pq, inv_T, make_T
from fullperc_fusion.fusion_config import read_values
from fullperc_fusion.fusion_core import FusionCore
from fullperc_fusion.fusion_endpoints import Inputs
from fullperc_msgs.msg import TrackedBodies, TrackedBody, TrackingQuality

T = 1_700_000_000_000_000_000


class FakeSub:
    """A raw subscription whose queue is ``queue`` (serialized messages, oldest first)."""

    raw = True

    def __init__(self, msg_type, topic: str) -> None:
        self.msg_type, self.topic, self.queue = msg_type, topic, []
        self.handle = self

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def take_message(self, _msg_type, _raw):
        return (self.queue.pop(0), {}) if self.queue else None


class FakeEndpoints:
    def __init__(self) -> None:
        self.subs: dict[str, FakeSub] = {}

    def subscription(self, msg_type, topic: str, callback, raw: bool = False) -> FakeSub:
        assert raw
        self.subs[topic] = FakeSub(msg_type, topic)
        return self.subs[topic]


def _inputs(kind: str, **over) -> tuple[Inputs, FakeEndpoints]:
    inp, ep, _ = _inputs_core(kind, **over)
    return inp, ep


def _inputs_core(kind: str, **over) -> tuple[Inputs, FakeEndpoints, FusionCore]:
    over = {"inputs": kind, **over}
    core = FusionCore(read_values(lambda n, d: over.get(n, d)), now=0.0)
    ep = FakeEndpoints()
    return Inputs(ep, core, kind, lambda *a: None, lambda *a: None), ep, core


def _pose(t: int, frame: str, x: float) -> bytes:
    return serialize_message(pose_stamped(t, frame, [x, 0.2, 0.3], [0.0, 0.0, 0.0, 1.0]))


def _quality(t: int, body: str, number: int, fit: float) -> bytes:
    return serialize_message(TrackingQuality(header=pose_stamped(t, "omc", [0, 0, 0], [0, 0, 0, 1]).header,
                                             body=body, visible=True, fit_error=fit, frame_number=number,
                                             markers_used=4))


def test_per_body_subscribes_each_pose_and_quality_topic():
    inp, ep = _inputs("per_body")
    assert {t for t, s in ep.subs.items() if s.msg_type is PoseStamped} == {
        "/omc/base/pose", "/omc/ots_rig/pose", "/omc/tool/pose", "/ots/base/pose", "/ots/tool/pose"}
    assert {t for t, s in ep.subs.items() if s.msg_type is TrackingQuality} == {"/omc/tool/quality",
                                                                                "/ots/tool/quality"}
    assert set(inp.sub_of) == set(ep.subs)


def test_per_body_takes_the_queued_quality_records_with_the_poses():
    """A node behind its inputs finds a frame's quality record queued beside its pose: the callback takes it with
    the batch, so the core gets it before the pose is fused (not in a later quality callback)."""
    inp, ep = _inputs("per_body")
    ep.subs["/omc/tool/pose"].queue.append(_pose(T + 8, "omc", 0.2))
    ep.subs["/omc/tool/quality"].queue += [_quality(T, "tool", 41, 2e-4), _quality(T + 8, "tool", 42, 3e-4)]
    batch, topics = inp.take("omc", "tool", _pose(T, "omc", 0.1), 100)
    assert [(t, d, b) for t, d, b, *_ in batch] == [(T, "omc", "tool"), (T + 8, "omc", "tool")]
    assert topics == {"/omc/tool/pose", "/omc/tool/quality"}
    q = inp.take_qualities()
    assert [(k, n, t, v) for k, n, t, v, *_ in q] == [(("omc", "tool"), 41, T, True),
                                                       (("omc", "tool"), 42, T + 8, True)]
    assert abs(q[0][4] - 2e-4) < 1e-9 and q[0][5] == 4.0
    assert inp.take_qualities() == []   # handed over once
    assert not ep.subs["/omc/tool/quality"].queue


def test_frames_subscribes_one_topic_per_source_and_reads_each_body():
    inp, ep = _inputs("frames")
    assert {t: s.msg_type for t, s in ep.subs.items()} == {"/omc/bodies": TrackedBodies, "/ots/bodies": TrackedBodies}
    m = TrackedBodies(latency=0.002)
    m.header.stamp, m.header.frame_id = ns_to_stamp(T), "omc"
    for name, visible, x in (("base", True, 1.0), ("tool", True, 0.1), ("ots_rig", False, 0.0), ("probe", True, 5.0)):
        b = TrackedBody(name=name, visible=visible, fit_error=1e-4, frame_number=7, markers_used=5)
        b.pose = pose_stamped(T, "omc", [x, 0.2, 0.3], [0.0, 0.0, 0.0, 1.0]).pose
        m.bodies.append(b)
    ep.subs["/ots/bodies"].queue.append(serialize_message(m))   # an OTS frame, queued (the same bodies' names)
    batch, topics = inp.take("omc", "", serialize_message(m), 100)
    # visible bodies the node uses: OMC base and tool (ots_rig not visible, probe unknown); OTS base and tool
    assert [(d, b, p[0]) for _, d, b, p, _ in batch] == [("omc", "base", 1.0), ("omc", "tool", 0.1),
                                                          ("ots", "base", 1.0), ("ots", "tool", 0.1)]
    assert all(t == T for t, *_ in batch) and topics == {"/omc/bodies", "/ots/bodies"}
    q = inp.take_qualities()   # the target body's of each source
    assert [(k, n, t, v, round(f, 6), mk) for k, n, t, v, f, mk in q] == [
        (("omc", "tool"), 7, T, True, 0.0001, 5.0), (("ots", "tool"), 7, T, True, 0.0001, 5.0)]


T_OMC_BASE = make_T([1.0, 0.5, 0.8], [0.0, 0.0, 0.2588190451, 0.9659258263])
T_OMC_OTS = make_T([3.0, 1.0, 1.5], [0.0, 0.0, 0.9659258263, 0.2588190451])


def _device_frames(n: int) -> list[tuple[str, int, list[tuple[str, np.ndarray, np.ndarray, float]]]]:
    """``n`` OMC frames at 100 Hz (base, rig, tool; the tool 2 mm off with a varying fit error: the OMC model's
    covariance differs per sample) and an OTS frame (base, tool) 3 ms after every other one: (device, stamp,
    [(body, p, q, fit_error)])."""
    rng = np.random.default_rng(3)
    out = []
    for k in range(n):
        t = T + k * 10_000_000
        T_tool = T_OMC_BASE @ make_T([0.4 + 0.02 * np.sin(0.05 * k), 0.1, 0.3], [0.0, 0.0, 0.0, 1.0])
        omc = [("base", *T_to_pq(T_OMC_BASE), 1e-4), ("ots_rig", *T_to_pq(T_OMC_OTS), 1e-4),
               ("tool", T_to_pq(T_tool)[0] + [2e-3, 0, 0] + rng.normal(0, 2e-4, 3), T_to_pq(T_tool)[1],
                float(rng.uniform(1e-4, 8e-4)))]
        out.append(("omc", t, omc))
        if k % 2 == 0:
            T_ots = inv_T(T_OMC_OTS)
            ots = [("base", *T_to_pq(T_ots @ T_OMC_BASE), 5e-5),
                   ("tool", T_to_pq(T_ots @ T_tool)[0] + rng.normal(0, 1e-4, 3), T_to_pq(T_ots @ T_tool)[1], 5e-5)]
            out.append(("ots", t + 3_000_000, ots))
    return out


def _fuse(kind: str, frames: list) -> list[tuple]:
    """fusion_node's input callback (one per device frame) on ``frames``, sent as ``kind`` inputs: every output of
    the primary filter (``fullperc``, which uses the quality records) as comparable tuples."""
    inp, ep, core = _inputs_core(kind, filter="fullperc", static_links="average", init_samples=3)
    for pipe in core.pipes.values():   # a still host clock: a sample waiting for its partner (partner_wait) is
        pipe.hold.clock = lambda: 0    # released by the inputs alone, not by how long this loop took (a CI run
    outs = []                          # under load: one more output in one of the two runs)
    for number, (dev, t, bodies) in enumerate(frames):
        if kind == "frames":
            m = TrackedBodies()
            m.header.stamp, m.header.frame_id = ns_to_stamp(t), dev
            for name, p, q, fit in bodies:
                b = TrackedBody(name=name, visible=True, fit_error=fit, frame_number=number, markers_used=4)
                b.pose = pose_stamped(t, dev, p, q).pose
                m.bodies.append(b)
            first, data = (dev, ""), serialize_message(m)
        else:   # the driver's order: each body's pose, then its quality record (the target's is subscribed)
            for name, p, q, fit in bodies:
                ep.subs[f"/{dev}/{name}/pose"].queue.append(_pose_q(t, dev, p, q))
                if name == "tool":
                    ep.subs[f"/{dev}/tool/quality"].queue.append(_quality(t, "tool", number, fit))
            first, data = (dev, bodies[0][0]), ep.subs[f"/{dev}/{bodies[0][0]}/pose"].queue.pop(0)
        batch, _ = inp.take(*first, data, 100)
        batch.sort(key=core.batch_key)
        for args in inp.take_qualities():
            core.quality(*args)
        touched = {tg for t_ns, d, b, p, q in batch for tg in core.on_pose(d, b, t_ns, p, q, 0.0, None)}
        for tg in sorted(touched):
            outs += core.poll(tg, None)
    for _, o in core.flush_all():
        outs += o
    return [(o.t_ns, *o.p.tolist(), *o.q.tolist(), *o.cov.ravel().tolist(), *o.bias.tolist()) for o in outs]


def _pose_q(t: int, frame: str, p, q) -> bytes:
    return serialize_message(pose_stamped(t, frame, p, q))


def test_frames_and_per_body_inputs_fuse_to_the_same_outputs_bit_for_bit():
    """The same device frames sent per body (pose and quality messages) and as TrackedBodies give the same outputs,
    covariance and bias included: the same samples and quality records reached the filters. The quality matters
    (a sanity check: the frames without their fit errors give other outputs)."""
    frames = _device_frames(120)
    per_body, as_frames = _fuse("per_body", frames), _fuse("frames", frames)
    assert len(per_body) > 100
    assert as_frames == per_body
    other_fit = [(d, t, [(n, p, q, 1e-4) for n, p, q, _ in b]) for d, t, b in frames]
    assert _fuse("frames", other_fit) != per_body
