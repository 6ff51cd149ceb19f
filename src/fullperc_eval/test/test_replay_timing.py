"""envelope_timing (bag/replay_timing.py) on modelled replays: a receiver that stalls or falls behind
does not move its rate estimate; a player at the wrong rate is caught either way."""

from __future__ import annotations

import numpy as np
import pytest

from fullperc_eval.bag.replay_timing import envelope_timing

N = 1500  # messages per topic in the record/play system test: 1.5 s at 1 kHz


def _replay_timeline(rate: float, slow: tuple[float, float, float] | None, rng) -> tuple[np.ndarray, np.ndarray]:
    """Recorded 1 kHz stamps and their replay's receive times [ns], a receiver modelled as a queue.

    ``slow = (a, b, f)``: from a to b seconds into the replay the receiver (or the player) gets
    only the fraction f of the CPU it needs, so a backlog builds and drains afterwards (f = 0: a
    stall). Delivery is schedule + delay, the delay never negative.
    """
    t_rec = 1_000_000_000 + np.arange(N, dtype=np.int64) * 1_000_000 + rng.integers(0, 200_000, N)
    due = (t_rec - t_rec[0]) / rate
    recv = due + rng.exponential(200_000, N)  # ~0.2 ms delivery
    if slow is not None:
        a, b, f = slow[0] * 1e9, slow[1] * 1e9, slow[2]
        need = 1e6 / rate / 3  # service time a message needs at full speed: a third of its period
        t = 0.0
        for i in range(N):
            t = max(t, recv[i])
            if f == 0.0 and a <= t < b:  # stalled: nothing until b
                t = b
            t += need / f if a <= t < b else need
            recv[i] = t
    return t_rec, (5_000_000_000 + recv).astype(np.int64)


@pytest.mark.parametrize("rate", [1.0, 2.0])
def test_envelope_timing_tolerates_a_slow_receiver_and_catches_a_wrong_rate(rate):
    rng = np.random.default_rng(3)
    span = (N - 1) * 1e-3 / rate
    # a 0.1 s stall mid-replay, and a receiver at 25 % speed over a fifth of the replay (a
    # backlog of ~0.2 s at rate 2: the CI failure had a 98 ms tail and a whole-run slope of 0.86)
    for slow in ((0.4 * span, 0.4 * span + 0.1, 0.0), (0.3 * span, 0.5 * span, 0.25)):
        slope, resid, p90 = envelope_timing(*_replay_timeline(rate, slow, rng), rate)
        assert abs(slope - 1.0) < 0.01 and resid < 0.001, (slow, slope, resid)
    # a player that played at another rate than asked is caught, with or without a slow receiver
    for played in (rate * 2, rate / 2, rate * 1.25, rate / 1.25):
        pspan = (N - 1) * 1e-3 / played
        for slow in (None, (0.4 * pspan, 0.4 * pspan + 0.1, 0.0), (0.3 * pspan, 0.5 * pspan, 0.25)):
            slope, _, _ = envelope_timing(*_replay_timeline(played, slow, rng), rate)
            assert abs(slope - 1.0) > 0.1, (played, slow, slope)
