"""fusion_publish: reused messages carry what the per-output construction carried; topics nobody subscribes to are
skipped (never the primary's pose), with the subscriber counts cached per refresh period; /tf is one TFMessage per
wake-up (``tf.rate``: newest per target, at most that rate); a refused pose publishes nothing."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from fullperc_common.ros_conv import ns_to_stamp, pose_msg
from fullperc_fusion.fusion_publish import Listeners, OutputPublisher, TfBatch, fill_pose, publish_outputs
from fullperc_fusion.pipeline.ordered import FusedOutput


class FakePub:
    def __init__(self, subs: int) -> None:
        self.subs = subs
        self.sent: list = []
        self.count_calls = 0

    def get_subscription_count(self) -> int:
        self.count_calls += 1
        return self.subs

    def publish(self, msg) -> None:
        self.sent.append(copy.deepcopy(msg))   # what rclpy serialises at this moment


def _out(filt="cbkf", t_ns=1_700_000_000_123_456_789, p=(0.1, -0.2, 0.3), q=(0.1, 0.2, 0.3, 0.9), k=0.0):
    q = np.asarray(q, float) / np.linalg.norm(q)
    return FusedOutput(target="tool", filter=filt, t_ns=t_ns, p=np.asarray(p, float) + k, q=q,
                       cov=np.arange(36.0).reshape(6, 6) * 1e-6 + k, bias=np.array([1e-3, 2e-3, k]),
                       innovation=np.array([k, 0.5, -0.5]), nis=2.5 + k, hop=bool(k), sources=3,
                       orientation_source=2, time_since_local=0.01, reset=False, t_global=None, t_local=None,
                       local_equation="", link_bumped=False)


def _sets(subs: int):
    pubs = {("tool", ""): (FakePub(subs), FakePub(subs), FakePub(subs)),
            ("tool", "kf"): (FakePub(subs), None, FakePub(subs))}
    return pubs, {k: OutputPublisher(*v, always_pose=k[1] == "") for k, v in pubs.items()}


def _refresh(sets) -> None:
    """A new wake-up: every set's (private, refresh_s 0) listener cache reads the counts again."""
    for s in sets.values():
        s.listeners.refresh(0.0)


def test_fill_pose_equals_pose_msg_and_keeps_its_refusals():
    rng = np.random.default_rng(3)
    from geometry_msgs.msg import Pose
    for _ in range(500):
        p, q = rng.normal(size=3), rng.normal(size=4)
        q *= (1 + rng.uniform(-9e-4, 9e-4)) / np.linalg.norm(q)
        a, b = pose_msg(p, q), Pose()
        fill_pose(b, p, q)
        for f in ("x", "y", "z"):
            assert getattr(a.position, f) == getattr(b.position, f)
        for f in ("x", "y", "z", "w"):
            assert abs(getattr(a.orientation, f) - getattr(b.orientation, f)) <= 1e-15
    for p, q in (([np.nan, 0, 0], [0, 0, 0, 1]), ([0, 0, 0], [0, 0, np.inf, 1]), ([0, 0, 0], [0, 0, 0, 1.0011]),
                 ([0, 0], [0, 0, 0, 1]), ([0, 0, 0], [0, 0, 1])):
        with pytest.raises(ValueError):
            pose_msg(p, q)
        with pytest.raises(ValueError):
            fill_pose(Pose(), p, q)


def test_reused_messages_carry_every_field_of_each_output():
    pubs, sets = _sets(subs=1)
    _refresh(sets)
    outs = [_out(t_ns=1_000_000_000 * i + 7, k=0.1 * i) for i in range(3)]
    for o in outs:
        sets[("tool", "")].publish("tool", o, region=4)
    pose_pub, cov_pub, st_pub = pubs[("tool", "")]
    assert len(pose_pub.sent) == len(cov_pub.sent) == len(st_pub.sent) == 3
    for o, ps, pc, st in zip(outs, pose_pub.sent, cov_pub.sent, st_pub.sent, strict=True):
        want = pose_msg(o.p, o.q)
        for m in (ps, pc, st):
            assert m.header.stamp == ns_to_stamp(o.t_ns) and m.header.frame_id == "base"
        for pose in (ps.pose, pc.pose.pose):
            assert [pose.position.x, pose.position.y, pose.position.z] == list(o.p)
            assert np.allclose([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w],
                               [want.orientation.x, want.orientation.y, want.orientation.z, want.orientation.w],
                               rtol=0, atol=1e-15)
        assert list(pc.pose.covariance) == [float(x) for x in o.cov.reshape(-1)]
        assert (st.target, st.filter, st.sources, st.orientation_source, st.region) == ("tool", "cbkf", 3, 2, 4)
        assert [st.bias.x, st.bias.y, st.bias.z] == list(o.bias)
        assert [st.innovation.x, st.innovation.y, st.innovation.z] == list(o.innovation)
        assert (st.nis, st.hop, st.time_since_local, st.link_bumped) == (o.nis, o.hop, 0.01, False)


def test_unsubscribed_topics_skipped_but_never_the_primary_pose():
    pubs, sets = _sets(subs=0)
    tf_pub = FakePub(0)
    tf = TfBatch(tf_pub, sets[("tool", "")].listeners)
    _refresh(sets)
    seen, errors = [], []
    publish_outputs(sets, "tool", [_out("cbkf"), _out("kf")], "cbkf", ["kf"], 0,
                    on_primary=seen.append, on_error=lambda o, why: errors.append(why), tf=tf)
    pose_pub, cov_pub, st_pub = pubs[("tool", "")]
    assert len(pose_pub.sent) == 1                                 # the primary's pose: always
    assert cov_pub.sent == [] and st_pub.sent == []                # pose_cov, status: nobody listens
    assert all(p is None or p.sent == [] for p in pubs[("tool", "kf")])   # side-by-side: nobody listens
    assert tf.flush(0.0) == 0 and tf_pub.sent == []                # /tf: nobody listens, nothing kept
    assert [o.filter for o in seen] == ["cbkf"] and errors == []
    pubs[("tool", "kf")][0].subs = 1   # a subscriber appears on the side-by-side pose only
    cov_pub.subs = tf_pub.subs = 1     # ... and on pose_cov and /tf
    _refresh(sets)
    publish_outputs(sets, "tool", [_out("cbkf", t_ns=4), _out("kf", t_ns=5)], "cbkf", ["kf"], 0, seen.append,
                    lambda o, w: None, tf)
    assert [m.header.stamp.nanosec for m in pubs[("tool", "kf")][0].sent] == [5]
    assert pubs[("tool", "kf")][2].sent == [] and st_pub.sent == []
    assert [m.header.stamp.nanosec for m in cov_pub.sent] == [4]
    assert tf.flush(0.0) == 1 and [t.header.stamp.nanosec for t in tf_pub.sent[0].transforms] == [4]


def test_subscriber_counts_are_read_once_per_refresh_period_not_per_output():
    """The count check is a call into rcl (~2 us): read at the first wake-up ``refresh_s`` after the last read, and
    a subscriber that appears in between gets its outputs from the next read on."""
    lis = Listeners(refresh_s=0.1)
    pose, cov, st = FakePub(1), FakePub(0), FakePub(0)
    out = OutputPublisher(pose, cov, st, always_pose=True, listeners=lis)
    assert pose.count_calls == 0, "the primary pose is never checked"
    for k in range(50):                    # 50 wake-ups within 49 ms: one read
        lis.refresh(1.0 + k * 0.001)
        out.publish("tool", _out(t_ns=1_000 + k), region=0)
    assert (cov.count_calls, st.count_calls, lis.reads) == (1, 1, 1) and cov.sent == []
    cov.subs = 1                           # matched now: not seen before the next read
    lis.refresh(1.09)
    out.publish("tool", _out(t_ns=2_000), region=0)
    assert cov.sent == []
    lis.refresh(1.1)                       # one refresh period after the last read
    out.publish("tool", _out(t_ns=3_000), region=0)
    assert [m.header.stamp.nanosec for m in cov.sent] == [3_000] and lis.reads == 2
    assert len(pose.sent) == 52


def _tf_outputs(sets, tf, target_outs):
    for target, outs in target_outs:
        publish_outputs(sets, target, outs, "cbkf", [], 0, lambda o: None, lambda o, w: None, tf)


def _two_targets():
    lis = Listeners(refresh_s=0.0)
    sets = {(t, ""): OutputPublisher(FakePub(0), FakePub(0), FakePub(0), always_pose=True, listeners=lis)
            for t in ("tool", "instrument")}
    tf_pub = FakePub(1)
    return lis, sets, tf_pub


def test_tf_is_one_message_per_wake_up_with_every_target_and_output_fused_in_it():
    lis, sets, tf_pub = _two_targets()
    tf = TfBatch(tf_pub, lis)
    lis.refresh(0.0)
    _tf_outputs(sets, tf, [("tool", [_out(t_ns=10), _out(t_ns=20, k=0.1)]), ("instrument", [_out(t_ns=15)])])
    assert tf_pub.sent == [], "nothing before the wake-up ends"
    assert tf.flush(0.0) == 3 and len(tf_pub.sent) == 1
    msg = tf_pub.sent[0]
    assert [(t.child_frame_id, t.header.stamp.nanosec) for t in msg.transforms] == [
        ("tool", 10), ("tool", 20), ("instrument", 15)]
    assert all(t.header.frame_id == "base" for t in msg.transforms)
    t20, o20 = msg.transforms[1], _out(t_ns=20, k=0.1)   # values copied from that output, not the refilled message
    assert [t20.transform.translation.x, t20.transform.translation.y, t20.transform.translation.z] == list(o20.p)
    assert np.allclose([t20.transform.rotation.x, t20.transform.rotation.y, t20.transform.rotation.z,
                        t20.transform.rotation.w], o20.q, atol=1e-15)
    assert tf.flush(0.001) == 0 and len(tf_pub.sent) == 1, "an empty wake-up sends nothing"


def test_tf_rate_sends_the_newest_transform_per_target_at_most_that_often():
    lis, sets, tf_pub = _two_targets()
    tf = TfBatch(tf_pub, lis, rate=10.0)
    lis.refresh(0.0)
    _tf_outputs(sets, tf, [("tool", [_out(t_ns=10), _out(t_ns=20)]), ("instrument", [_out(t_ns=15)])])
    assert tf.flush(5.0) == 2
    _tf_outputs(sets, tf, [("tool", [_out(t_ns=30)])])
    assert tf.flush(5.05) == 0, "within 1 / rate of the last message: kept"
    _tf_outputs(sets, tf, [("tool", [_out(t_ns=40)]), ("instrument", [_out(t_ns=35)])])
    assert tf.flush(5.1) == 2
    got = [[(t.child_frame_id, t.header.stamp.nanosec) for t in m.transforms] for m in tf_pub.sent]
    assert got == [[("tool", 20), ("instrument", 15)], [("tool", 40), ("instrument", 35)]]


def test_a_refused_pose_publishes_nothing_and_is_reported():
    pubs, sets = _sets(subs=1)
    tf_pub = FakePub(1)
    tf = TfBatch(tf_pub, sets[("tool", "")].listeners)
    _refresh(sets)
    errors = []
    bad, nonunit = _out(p=(np.nan, 0.0, 0.0)), _out("kf")
    nonunit.q = np.array([0.0, 0.0, 0.0, 1.5])
    publish_outputs(sets, "tool", [bad, nonunit], "cbkf", ["kf"], 0,
                    on_primary=lambda o: None, on_error=lambda o, why: errors.append((o.filter, why)), tf=tf)
    assert tf.flush(0.0) == 0 and [f for f, _ in errors] == ["cbkf", "kf"]
    assert all(p is None or p.sent == [] for v in pubs.values() for p in v) and tf_pub.sent == []


def test_status_rate_caps_status_by_stamp_but_never_drops_a_hop_or_a_bump_change():
    """status_rate 50 Hz over 400 Hz outputs: one status per 20 ms of fused stamps (pose and pose_cov every output);
    hops and link_bumped changes always go out; a restarted (earlier) timeline starts a new period."""
    from dataclasses import replace

    pose_pub, cov_pub, st_pub = FakePub(1), FakePub(1), FakePub(1)
    pub = OutputPublisher(pose_pub, cov_pub, st_pub, always_pose=True, status_rate=50.0)
    pub.listeners.refresh(0.0)
    t0, dt = 1_000_000_000, 2_500_000
    hops = {37, 38, 101}
    bumped_from = 150
    outs = [replace(_out(t_ns=t0 + i * dt), hop=i in hops, link_bumped=i >= bumped_from) for i in range(400)]
    outs.append(_out(t_ns=t0 - 5 * dt))   # time restarted (e.g. a replay jumped back)
    for o in outs:
        pub.publish("tool", o, region=1)
    assert len(pose_pub.sent) == len(cov_pub.sent) == len(outs)
    sent = [(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.hop, m.link_bumped) for m in st_pub.sent]
    stamps = [s[0] for s in sent]
    assert all(t0 + i * dt in stamps for i in hops), "every hop is published"
    assert t0 + bumped_from * dt in stamps, "the first output with link_bumped is published"
    assert stamps[-1] == t0 - 5 * dt, "a restarted timeline is published at once"
    regular = [t for t, hop, _ in sent[:-1] if not hop and t != t0 + bumped_from * dt]
    assert min(np.diff(regular)) >= 20_000_000 - dt   # no two periodic ones closer than a period (minus one step)
    assert 45 <= len(sent) <= 60                         # 1 s of stamps at 50 Hz plus the events
    # uncapped (the default): every output
    st2 = FakePub(1)
    pub2 = OutputPublisher(FakePub(1), FakePub(1), st2, always_pose=True)
    pub2.listeners.refresh(0.0)
    for o in outs:
        pub2.publish("tool", o, region=1)
    assert len(st2.sent) == len(outs)
