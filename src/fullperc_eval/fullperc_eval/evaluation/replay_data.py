"""What a replay of one bag produces and how a bag is opened for it, shared by the per-sample replay
(:mod:`.replay`) and the batched one (:mod:`.batch`): :class:`Replay`, :class:`Outputs`, :func:`prepare`.

Its own module so that :mod:`.replay` (which dispatches to the batched replay) and :mod:`.batch` (which builds the
same :class:`Replay`) do not import each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.reader import BagReader
from fullperc_fusion.pipeline.ordered import TargetConfig

from .config import EvaluationError

POSE_TYPE = "geometry_msgs/msg/PoseStamped"
JOINT_TYPE = "sensor_msgs/msg/JointState"
JOINT_TOPIC = "/diana/joint_states"


@dataclass
class Outputs:
    """What one method output over the bag (base frame, SI)."""

    t_ns: list[int] = field(default_factory=list)
    p: list[np.ndarray] = field(default_factory=list)
    sources: list[int] = field(default_factory=list)
    hop: list[bool] = field(default_factory=list)
    bias: list[np.ndarray] = field(default_factory=list)
    # orientation and covariance hook (orientation error and NEES, evaluation/orientation.py, consistency.py)
    q: list[np.ndarray] = field(default_factory=list)
    cov: list[np.ndarray] = field(default_factory=list)
    orientation_source: list[int] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self.t_ns)
        return {"t_ns": np.asarray(self.t_ns, dtype=np.int64),
                "p": np.asarray(self.p, dtype=float).reshape(n, 3),
                "sources": np.asarray(self.sources, dtype=np.int64),
                "hop": np.asarray(self.hop, dtype=bool),
                "bias": np.asarray(self.bias, dtype=float).reshape(n, 3),
                "q": np.asarray(self.q, dtype=float).reshape(n, 4),
                "cov": np.asarray(self.cov, dtype=float).reshape(n, 6, 6),
                "orientation_source": np.asarray(self.orientation_source, dtype=np.int64)}


@dataclass
class Replay:
    """Everything the replay of one bag produced (input to the metrics and the report)."""

    bag: Path
    task: str
    start_ns: int
    outputs: dict[str, dict[str, np.ndarray]]
    joint_t_ns: np.ndarray
    joint_q: np.ndarray
    omc_base_poses: list[tuple[np.ndarray, np.ndarray]]   # raw (p, q) of the OMC base marker
    counts: dict[str, int]
    pipeline_stats: dict[str, Any]
    warnings: list[str]
    messages: int
    seconds: float
    single_sources: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # SourceTap.arrays() (sources.py)
    path: str = "per-sample"       # how the filters were run: "batched" (batch.py) or "per-sample"
    fallback: str = ""             # why the per-sample path ran ("" for the batched path and live replays)


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _task_name(reader: BagReader) -> str:
    cd = reader.info.get("custom_data") or {}
    if isinstance(cd, dict) and cd.get("task"):
        return str(cd["task"])
    return reader.path.name


@dataclass
class Prepared:
    """A bag opened and checked for :func:`replay` (both paths): the topics it reads and the warnings so far."""

    reader: BagReader
    omc_topics: dict[str, str]     # topic -> OMC body
    ots_topics: dict[str, str]     # topic -> OTS tool
    target_omc: str
    present: list[str]             # the wanted topics the bag has, in the order counts are reported
    total: int
    warnings: list[str]


def prepare(bag: str | Path, config: TargetConfig, reader: BagReader | None = None) -> Prepared:
    """Open ``bag`` and check what the replay needs (topic types, joint states, the target's OMC topic);
    :class:`EvaluationError` naming the problem. Shared by the per-sample and the batched replay (batch.py), so
    both refuse the same bags with the same words."""
    if reader is None:
        try:
            reader = BagReader(bag)
        except BagError as e:
            raise EvaluationError(str(e)) from None
    c = config.chain
    omc_topics = {f"/omc/{b}/pose": b for b in dict.fromkeys((c.omc_target, c.omc_base, c.omc_rig))}
    ots_topics = {f"/ots/{b}/pose": b for b in dict.fromkeys((c.ots_target, c.ots_base))}
    wanted = {**{t: POSE_TYPE for t in (*omc_topics, *ots_topics)}, JOINT_TOPIC: JOINT_TYPE}
    warnings: list[str] = []
    for topic, typ in wanted.items():
        info = reader.topics.get(topic)
        if info is not None and info.msgtype != typ:
            raise EvaluationError(f"bag {str(reader.path)!r}: topic {topic} has type {info.msgtype}, expected {typ}")
    if JOINT_TOPIC not in reader.topics or reader.topics[JOINT_TOPIC].count == 0:
        raise EvaluationError(f"bag {str(reader.path)!r} has no {JOINT_TOPIC} messages: no ground truth to compare "
                              "with (record the diana_state node too)")
    target_omc = f"/omc/{c.omc_target}/pose"
    if target_omc not in reader.topics or reader.topics[target_omc].count == 0:
        raise EvaluationError(f"bag {str(reader.path)!r} has no {target_omc} messages: nothing to evaluate")
    for t in ots_topics:
        if t not in reader.topics or reader.topics[t].count == 0:
            warnings.append(f"no {t} messages in the bag")
    present = [t for t in wanted if t in reader.topics]
    total = sum(reader.topics[t].count for t in present)
    return Prepared(reader, omc_topics, ots_topics, target_omc, present, total, warnings)
