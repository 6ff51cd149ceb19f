"""The live benches' rule for a lost sample (bench/live_fusion.uncovered): a target sample stamped ``s`` is covered
by a fused pose stamped in ``[s, s + slop]`` -- its own output (fusion on arrival) or the output of its
approximate-time pair (stamped with the newer stamp); anything else is lost."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from live_fusion import target_params, uncovered  # noqa: E402

MS = 1_000_000


def test_own_stamp_and_pair_partner_are_covered() -> None:
    sent = np.array([0, 3 * MS, 10 * MS, 20 * MS])
    # 0 and 3 ms paired -> one output at 3 ms; 10 ms alone; 20 ms alone
    assert uncovered(sent, [3 * MS, 10 * MS, 20 * MS], 4 * MS) == 0


def test_missing_outputs_are_lost() -> None:
    sent = np.array([0, 10 * MS, 20 * MS, 30 * MS])
    assert uncovered(sent, [10 * MS, 30 * MS], 4 * MS) == 2        # 0 and 20 ms: no output within slop
    assert uncovered(sent, [5 * MS, 25 * MS], 4 * MS) == 4         # outputs more than slop after: not theirs
    assert uncovered(sent, [], 4 * MS) == 4
    assert uncovered(sent, [-1], 4 * MS) == 4                       # an output before a sample never covers it


def test_target_params_name_each_target_body_and_tool() -> None:
    args = target_params(["t0", "t1"])
    assert args[:2] == ["-p", "targets:=[t0, t1]"]
    assert "t1.omc_body:=t1" in args and "t1.ots_tool:=t1" in args
