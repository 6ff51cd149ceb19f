"""ClockSync: the running-minimum offset estimator, checked against quantities computed from the generated input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fullperc_drivers.clock_sync import ClockSync

MS = 1_000_000


def _simulate(offset_ns, delays_ns, period_ns=10 * MS, t0=1_700_000_000 * 10**9):
    """Yield (capture_dev, send_dev, recv_host, capture_host) for a device whose clock = host - offset."""
    for k, d in enumerate(delays_ns):
        cap_host = t0 + k * period_ns
        off = offset_ns(k) if callable(offset_ns) else offset_ns
        yield cap_host - off, cap_host - off, cap_host + int(d), cap_host


@settings(max_examples=50, deadline=None)
@given(offset=st.integers(-10**12, 10**12), dmin=st.integers(0, 2 * MS), seed=st.integers(0, 2**31))
def test_constant_offset_error_equals_min_delay_in_window(offset, dmin, seed):
    rng = np.random.default_rng(seed)
    delays = dmin + rng.exponential(0.3 * MS, 400).astype(np.int64)
    cs = ClockSync(window_s=1.0)
    recvs = []
    for k, (cap_dev, send_dev, recv, cap_host) in enumerate(_simulate(offset, delays)):
        assert cs.observe(send_dev, recv)
        recvs.append(recv)
        err = cs.to_host(cap_dev) - cap_host
        in_window = np.array(recvs) >= recv - 10**9  # samples received within the last 1 s
        assert err == delays[:k + 1][in_window].min()
    assert cs.stats.resets == 0


def test_drift_is_followed_with_bounded_lag():
    drift = 50e-6  # 50 ppm
    delays = np.full(3000, 100_000)  # 0.1 ms constant transport delay
    cs = ClockSync(window_s=2.0)
    worst = 0
    for k, (cap_dev, send_dev, recv, cap_host) in enumerate(
            _simulate(lambda k: int(-3 * 10**9 + drift * k * 10 * MS), delays)):
        cs.observe(send_dev, recv)
        if k > 300:
            worst = max(worst, abs(cs.to_host(cap_dev) - cap_host))
    assert worst <= 100_000 + drift * 2.0 * 1e9 + 10


def test_offset_step_down_is_followed_at_once_and_step_up_after_reset():
    cs = ClockSync(window_s=5.0, reset_threshold_s=0.5, reset_after=5)
    t = 10**18
    for k in range(50):
        cs.observe(t + k * MS - 1000 * MS, t + k * MS + 100_000)
    assert cs.offset_ns == 1000 * MS + 100_000
    # device clock jumps forward by 2 s (offset drops): the very next sample wins the minimum
    cs.observe(t + 50 * MS + 1000 * MS, t + 50 * MS + 100_000)
    assert cs.offset_ns == -1000 * MS + 100_000
    # device clock jumps back by 3 s relative to the host: larger samples, reset after 5 of them
    for k in range(51, 56):
        cs.observe(t + k * MS + 1000 * MS - 3000 * MS, t + k * MS + 100_000)
    assert cs.stats.resets >= 1
    assert cs.offset_ns == 2000 * MS + 100_000


def test_device_time_backwards_small_rejected_large_resets():
    cs = ClockSync(reset_threshold_s=0.5)
    assert cs.observe(10 * MS, 20 * MS)
    assert not cs.observe(9 * MS, 21 * MS)  # 1 ms backwards: jitter, rejected
    assert cs.stats.backwards == 1 and cs.stats.resets == 0 and cs.offset_ns == 10 * MS
    assert cs.observe(10 * MS - 10**9, 22 * MS)  # 1 s backwards: device clock reset, window restarts
    assert cs.stats.backwards == 2 and cs.stats.resets == 1 and cs.offset_ns == 12 * MS + 10**9


def test_transport_delay_is_subtracted_and_not_ready_before_samples():
    cs = ClockSync(transport_delay_ns=40_000)
    assert not cs.ready and cs.to_host(5) is None and cs.offset_ns is None
    cs.observe(0, 1_000_000)
    assert cs.to_host(0) == 1_000_000 - 40_000


@pytest.mark.parametrize("kw", [dict(window_s=0), dict(reset_threshold_s=-1), dict(reset_after=0)])
def test_bad_settings_rejected(kw):
    with pytest.raises(ValueError):
        ClockSync(**kw)
