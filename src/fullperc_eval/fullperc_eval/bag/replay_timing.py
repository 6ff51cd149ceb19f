"""How faithfully a replay kept a recording's timing, judged from the receiving side.

Used by the record/play system test (``test_bag_record_play.py``) and usable on any pair of bags: the
original recording and a recording of its replay (``play --rate R`` into ``record``).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import theilslopes


def envelope_timing(t_rec: np.ndarray, t_play: np.ndarray, rate: float, bins: int = 20
                     ) -> tuple[float, float, float]:
    """(slope of replay vs recorded timeline x rate, median envelope residual [s], 90th pct |jitter| [s]).

    ``t_rec``, ``t_play``: receive times [ns] of the same messages in the recording and in the
    recording of its replay at ``rate``. A faithful replay gives slope 1 and a residual of ~0.

    Receive times on the replaying side are the player's schedule plus delivery delay, and the
    delay is never negative: a process descheduled for ~0.1 s (seen in CI on the loaded 2-core
    machine: a 98 ms tail in a 0.75 s replay at rate 2, total span right, yet a Theil-Sen slope
    over all messages of 0.86) delays a run of messages, it never makes one early. So the rate
    is fitted to the lower envelope: the least-delayed message of each of ``bins`` slices of the
    timeline, then a Theil-Sen line through those points (a stall covering up to ~29 % of the
    slices cannot move it). The residual of the envelope from that line says whether the
    promptly delivered messages were on schedule; the tail (p90, printed) measures the machine.
    """
    d1 = (t_rec - t_rec[0]) / 1e9
    d2 = (t_play - t_play[0]) / 1e9
    err = d2 - d1 / rate
    edges = np.linspace(0.0, d1[-1], bins + 1)
    idx = np.clip(np.searchsorted(edges, d1, side="right") - 1, 0, bins - 1)
    slices = (np.flatnonzero(idx == b) for b in np.unique(idx))
    env = np.array([s[np.argmin(err[s])] for s in slices])
    slope = theilslopes(d2[env], d1[env])[0]
    off = d2[env] - slope * d1[env]
    resid = np.abs(off - np.median(off))
    jit = np.abs(err - np.median(err))
    return float(slope * rate), float(np.median(resid)), float(np.percentile(jit, 90))
