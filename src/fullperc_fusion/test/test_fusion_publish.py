"""fusion_publish: reused messages carry what the per-output construction carried; topics nobody subscribes to are
skipped only where allowed (never the primary's pose / pose_cov / tf); a refused pose publishes nothing."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from fullperc_common.ros_conv import ns_to_stamp, pose_msg
from fullperc_fusion.fusion_publish import OutputPublisher, fill_pose, publish_outputs
from fullperc_fusion.pipeline.ordered import FusedOutput


class FakePub:
    def __init__(self, subs: int) -> None:
        self.subs = subs
        self.sent: list = []

    def get_subscription_count(self) -> int:
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
    return pubs, {k: OutputPublisher(*v) for k, v in pubs.items()}


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


def test_unsubscribed_topics_are_skipped_each_on_its_own():
    """Nothing is built for a topic without a matched reader (volatile: it would reach nobody) -- the primary's pose
    and pose_cov included; the primary hook still sees every output and /tf is the caller's (``tf_of``) to skip."""
    pubs, sets = _sets(subs=0)
    seen, errors = [], []
    tfs = publish_outputs(sets, "tool", [_out("cbkf"), _out("kf")], "cbkf", ["kf"], 0,
                          on_primary=seen.append, on_error=lambda o, why: errors.append(why),
                          tf_of=lambda o: ("tf", o.t_ns))
    assert all(p is None or p.sent == [] for v in pubs.values() for p in v)   # nobody listens: nothing sent
    assert tfs == [("tf", _out().t_ns)] and [o.filter for o in seen] == ["cbkf"] and errors == []
    pose_pub, cov_pub, st_pub = pubs[("tool", "")]
    pose_pub.subs = 1   # a consumer of the fused pose only
    publish_outputs(sets, "tool", [_out("cbkf", t_ns=4)], "cbkf", ["kf"], 0, seen.append, lambda o, w: None, None)
    assert [m.header.stamp.nanosec for m in pose_pub.sent] == [4] and cov_pub.sent == [] and st_pub.sent == []
    cov_pub.subs = 1
    publish_outputs(sets, "tool", [_out("cbkf", t_ns=6)], "cbkf", ["kf"], 0, seen.append, lambda o, w: None, None)
    assert [m.header.stamp.nanosec for m in cov_pub.sent] == [6] and len(pose_pub.sent) == 2 and st_pub.sent == []
    pubs[("tool", "kf")][0].subs = 1   # a subscriber appears on the side-by-side pose only
    publish_outputs(sets, "tool", [_out("kf", t_ns=5)], "cbkf", ["kf"], 0, seen.append, lambda o, w: None, None)
    assert [m.header.stamp.nanosec for m in pubs[("tool", "kf")][0].sent] == [5]
    assert pubs[("tool", "kf")][2].sent == []


def test_a_refused_pose_publishes_nothing_and_is_reported():
    pubs, sets = _sets(subs=1)
    errors = []
    bad, nonunit = _out(p=(np.nan, 0.0, 0.0)), _out("kf")
    nonunit.q = np.array([0.0, 0.0, 0.0, 1.5])
    tfs = publish_outputs(sets, "tool", [bad, nonunit], "cbkf", ["kf"], 0,
                          on_primary=lambda o: None, on_error=lambda o, why: errors.append((o.filter, why)),
                          tf_of=lambda o: o)
    assert tfs == [] and [f for f, _ in errors] == ["cbkf", "kf"]
    assert all(p is None or p.sent == [] for v in pubs.values() for p in v)


@pytest.mark.parametrize("cov", [np.full((6, 6), np.nan), np.eye(6) * np.inf, np.eye(3)])
def test_a_non_finite_covariance_publishes_nothing_and_is_reported(cov):
    """pose_cov never carries NaN: an output whose covariance is not a finite 6x6 is refused whole, as a NaN pose."""
    pubs, sets = _sets(subs=1)
    errors = []
    bad = _out()
    bad.cov = cov
    tfs = publish_outputs(sets, "tool", [bad, _out(t_ns=5)], "cbkf", ["kf"], 0, on_primary=lambda o: None,
                          on_error=lambda o, why: errors.append(why), tf_of=lambda o: o)
    assert len(errors) == 1 and "covariance" in errors[0] and len(tfs) == 1
    assert [m.header.stamp.nanosec for m in pubs[("tool", "")][1].sent] == [5]


def test_status_rate_caps_status_by_stamp_but_never_drops_a_hop_or_a_bump_change():
    """status_rate 50 Hz over 400 Hz outputs: one status per 20 ms of fused stamps (pose and pose_cov every output);
    hops and link_bumped changes always go out; a restarted (earlier) timeline starts a new period."""
    from dataclasses import replace

    pose_pub, cov_pub, st_pub = FakePub(1), FakePub(1), FakePub(1)
    pub = OutputPublisher(pose_pub, cov_pub, st_pub, status_rate=50.0)
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
    pub2 = OutputPublisher(FakePub(1), FakePub(1), st2)
    for o in outs:
        pub2.publish("tool", o, region=1)
    assert len(st2.sent) == len(outs)


def test_final_only_while_read_and_never_a_nan():
    from fullperc_fusion.fusion_publish import publish_final

    unread, read = FakePub(0), FakePub(1)
    outs = [_out(t_ns=7), _out(p=(np.nan, 0.0, 0.0), t_ns=8), _out(t_ns=9)]
    publish_final(unread, outs, "or1_base")
    publish_final(None, outs, "or1_base")
    publish_final(read, outs, "or1_base")
    assert unread.sent == []
    assert [(m.header.frame_id, m.header.stamp.nanosec) for m in read.sent] == [("or1_base", 7), ("or1_base", 9)]
