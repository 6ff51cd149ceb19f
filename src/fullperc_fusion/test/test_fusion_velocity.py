"""The optional velocity output (issue 39 item 4): ``FusedOutput.velocity()`` is the filter's constant-velocity
state, against a synthetic constant-velocity target; reading it changes no other number of the output; the
TwistWithCovarianceStamped fusion_publish builds from it (frame, linear block, angular "unknown")."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as Rot

from fullperc_common.transforms import inv_T, make_T
from fullperc_fusion.fusion_publish import ANGULAR_VAR_UNKNOWN, OutputPublisher
from fullperc_fusion.pipeline.arrival import make_pipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.ordered import TargetConfig

S = 1_000_000_000
T0 = 1_700_000_000 * S
V = np.array([0.08, -0.05, 0.02])   # [m/s] the target's constant velocity in base
T_OMC_BASE = make_T([1.0, 0.5, 0.8], Rot.from_euler("z", 30, degrees=True).as_quat())
T_OMC_OTS = make_T([3.0, 1.0, 1.5], Rot.from_euler("zyx", [150, 20, 0], degrees=True).as_quat())
FILTERS = ("cbkf", "ckf", "bkf", "kf", "fullperc", "omc")


def truth(t: float) -> np.ndarray:
    """T_base_tool: a straight line at V, turning slowly about z."""
    return make_T(np.array([0.4, 0.1, 0.3]) + V * t, Rot.from_euler("z", 3 * t, degrees=True).as_quat())


def _run(processing: str, duration: float = 6.0, seed: int = 1):
    """OMC 120 Hz (0.3 mm noise, a constant 3 mm offset), OTS 60 Hz (0.1 mm) seeing the target throughout; the
    static links given, so every sample is fused from the first."""
    rng = np.random.default_rng(seed)
    T_base_ots = inv_T(T_OMC_BASE) @ T_OMC_OTS
    chain = ChainConfig(T_base_ots=(T_base_ots[:3, 3], Rot.from_matrix(T_base_ots[:3, :3]).as_quat()))
    pipe = make_pipeline(TargetConfig(filters=FILTERS, chain=chain, processing=processing))
    ev = []
    for k in range(int(duration * 120)):
        t = k / 120
        Tm = T_OMC_BASE @ truth(t)
        Tm[:3, 3] += np.array([3e-3, -2e-3, 1e-3]) + rng.normal(0, 3e-4, 3)
        ev += [(t, "omc", "base", T_OMC_BASE), (t, "omc", "tool", Tm)]
    for k in range(int(duration * 60)):
        t = 0.003 + k / 60
        Tl = inv_T(T_OMC_OTS) @ T_OMC_BASE @ truth(t)
        Tl[:3, 3] += rng.normal(0, 1e-4, 3)
        ev += [(t, "ots", "base", inv_T(T_OMC_OTS) @ T_OMC_BASE), (t, "ots", "tool", Tl)]
    outs = []
    for t, dev, body, T in sorted(ev, key=lambda e: (e[0], e[2] != "base")):
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, T0 + round(t * S), T)
        outs += pipe.poll()
    return outs + pipe.flush()


@pytest.fixture(scope="module", params=["arrival", "ordered"])
def outputs(request):
    return _run(request.param)


@pytest.mark.parametrize("name", FILTERS[:-1])
def test_velocity_is_the_constant_velocity_of_the_target(outputs, name):
    """After 2 s every filter that compensates the OMC's offset reports V within 5 mm/s per axis on average (the
    white-acceleration model settles on a straight line), and its covariance is consistent: the error within 4 sigma
    on average. KF and BKF do not compensate it: each OMC / OTS alternation moves them by the 3.7 mm between the two,
    so their velocity is noisier (within 2 cm/s on average) -- what they are, not what the output does."""
    late = [o for o in outputs if o.filter == name and (o.t_ns - T0) / S > 2.0]
    assert len(late) > 200
    vs = np.array([o.velocity()[0] for o in late])
    covs = np.array([o.velocity()[1] for o in late])
    tol = 2e-2 if name in ("kf", "bkf") else 5e-3
    assert np.all(np.abs(vs.mean(axis=0) - V) < tol), (name, vs.mean(axis=0))
    if name in ("kf", "bkf"):
        return
    assert np.allclose(covs, np.transpose(covs, (0, 2, 1))) and np.all(np.linalg.eigvalsh(covs) > 0)
    z = (vs - V) / np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    assert np.mean(np.abs(z)) < 4.0, (name, np.mean(np.abs(z)))


def test_the_raw_omc_has_no_velocity(outputs):
    assert all(o.velocity() is None for o in outputs if o.filter == "omc")


def test_reading_the_velocity_changes_no_output():
    """The same run, once reading every velocity as it comes: every other field of every output is bit-identical
    (the velocity is taken from the filter's step, nothing is recomputed)."""
    plain = _run("arrival", duration=2.0)
    read = _run("arrival", duration=2.0)
    for o in read:
        o.velocity()
    assert len(plain) == len(read)
    for a, b in zip(plain, read, strict=True):
        assert (a.filter, a.t_ns, a.sources, a.hop) == (b.filter, b.t_ns, b.sources, b.hop)
        for f in ("p", "q", "cov", "bias", "innovation"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f


class FakePub:
    def __init__(self) -> None:
        self.sent: list = []

    def get_subscription_count(self) -> int:
        return 1

    def publish(self, msg) -> None:
        self.sent.append(copy.deepcopy(msg))


def test_twist_message_carries_the_velocity_in_the_outputs_frame():
    outs = [o for o in _run("arrival", duration=1.0) if o.filter in ("cbkf", "omc")]
    vel = FakePub()
    pub = OutputPublisher(FakePub(), FakePub(), FakePub(), frame="or1_base", vel_pub=vel)
    for o in outs:
        pub.publish("tool", o, 0)
    cbkf = [o for o in outs if o.filter == "cbkf"]
    assert len(vel.sent) == len(cbkf)   # nothing for the raw omc
    for o, m in zip(cbkf, vel.sent, strict=True):
        v, P = o.velocity()
        assert m.header.frame_id == "or1_base" and m.header.stamp.sec * S + m.header.stamp.nanosec == o.t_ns
        lin, ang = m.twist.twist.linear, m.twist.twist.angular
        assert [lin.x, lin.y, lin.z] == list(v) and [ang.x, ang.y, ang.z] == [0.0, 0.0, 0.0]
        C = np.array(m.twist.covariance).reshape(6, 6)
        assert np.array_equal(C[:3, :3], P) and np.array_equal(C[3:, 3:], np.eye(3) * ANGULAR_VAR_UNKNOWN)
        assert not C[:3, 3:].any() and not C[3:, :3].any()


def test_no_twist_is_built_without_a_reader():
    """velocity is lazy like every output topic (fusion_publish): no matched reader, nothing published."""
    class Unread(FakePub):
        def get_subscription_count(self) -> int:
            return 0

    outs = [o for o in _run("arrival", duration=0.3) if o.filter == "cbkf"]
    vel, pose = Unread(), FakePub()
    pub = OutputPublisher(pose, FakePub(), FakePub(), vel_pub=vel)
    for o in outs:
        pub.publish("tool", o, 0)
    assert outs and vel.sent == [] and len(pose.sent) == len(outs)
