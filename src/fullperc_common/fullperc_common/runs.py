"""Run-length encoding of a label sequence (regions along a path, per-frame states).

One definition for the evaluator's region segments, the task planner's region order and the demo checks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def runs(labels: Sequence | np.ndarray) -> list[tuple[int, int, int]]:
    """``(label, first index, last index inclusive)`` of each maximal run of equal labels, in order."""
    lab = np.asarray(labels)
    if lab.size == 0:
        return []
    starts = np.flatnonzero(np.concatenate([[True], lab[1:] != lab[:-1]]))
    ends = np.concatenate([starts[1:] - 1, [lab.size - 1]])
    return [(int(lab[s]), int(s), int(e)) for s, e in zip(starts, ends, strict=True)]
