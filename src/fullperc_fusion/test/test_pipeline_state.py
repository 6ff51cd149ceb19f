"""The pipelines' state is declared: what a rewind restores (the lanes, pipeline/lane.py) and what it keeps.

A rewind on arrival restores a :class:`FilterLane` whole. These tests fail when state is added outside it without
being declared (an attribute of the pipeline not in CONSTANT / LANES / KEPT), when a CONSTANT changes in a run, or
when a lane's snapshot misses part of the lane.
"""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from fullperc_common.testing import load_by_path
from fullperc_fusion.filters.fullperc_params import FullpercParams
from fullperc_fusion.pipeline.arrival import ArrivalPipeline
from fullperc_fusion.pipeline.frame_chain import ChainConfig
from fullperc_fusion.pipeline.lane import FilterLane, LaneState
from fullperc_fusion.pipeline.ordered import TargetConfig, TargetPipeline

MS = 1_000_000
# the synthetic streams of test_pipeline.py and test_sources.py (tests run with --import-mode=importlib: by path)
_HERE = Path(__file__).parent


def _load(name: str):
    return load_by_path(_HERE / f"{name}.py", f"_state_{name}")


_tp = _load("test_pipeline")


def undeclared(pipe: TargetPipeline) -> set[str]:
    """Attributes of ``pipe`` its class does not declare (CONSTANT, LANES, KEPT)."""
    cls = type(pipe)
    return set(vars(pipe)) - {*cls.CONSTANT, *cls.LANES, *cls.KEPT}


def _events(seed: int = 0, reorder_ms: int = 30):
    events = _tp.stream(duration=2.0, local=(0.4, 1.6), omc_hz=240, ots_hz=400)
    rng = np.random.default_rng(seed)
    recv = [ev[2] + int(rng.uniform(0, reorder_ms * MS)) for ev in events]
    return [ev for _, ev in sorted(zip(recv, events, strict=True), key=lambda x: x[0])]


def _run(pipe, events):
    outs = []
    for dev, body, ns, T in events:
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, T)
        outs += pipe.poll()
        if isinstance(pipe, ArrivalPipeline):
            pipe.take_final()
    return outs + pipe.flush()


CONFIG = TargetConfig(filters=("fullperc", "cbkf", "omc"), params=FullpercParams(),
                      chain=ChainConfig(static_links="average"))


@pytest.mark.parametrize("cls", [TargetPipeline, ArrivalPipeline])
def test_every_attribute_of_a_pipeline_is_declared_once(cls):
    pipe = cls(CONFIG)
    declared = [*cls.CONSTANT, *cls.LANES, *cls.KEPT]
    assert len(declared) == len(set(declared)), "an attribute declared twice"
    assert undeclared(pipe) == set()
    _run(pipe, _events())
    assert undeclared(pipe) == set(), "state added while running, outside the declared attributes"
    assert set(vars(pipe)) == set(declared), "a declared attribute that does not exist"
    assert all(isinstance(getattr(pipe, n), FilterLane) for n in cls.LANES)


def test_the_checker_finds_a_planted_attribute():
    class Planted(ArrivalPipeline):
        def __init__(self, config):
            super().__init__(config)
            self._fused_so_far = 0   # mutable state that a rewind would not restore

    assert undeclared(Planted(CONFIG)) == {"_fused_so_far"}


@pytest.mark.parametrize("cls", [TargetPipeline, ArrivalPipeline])
def test_constants_do_not_change_in_a_run(cls):
    pipe = cls(CONFIG)
    before = {n: (id(getattr(pipe, n)), pickle.dumps(getattr(pipe, n))) for n in cls.CONSTANT}
    _run(pipe, _events())
    assert {n: (id(getattr(pipe, n)), pickle.dumps(getattr(pipe, n))) for n in cls.CONSTANT} == before


def _lane_bytes(lane: FilterLane) -> bytes:
    return pickle.dumps(lane.snapshot())


def test_a_lane_restore_takes_back_everything_fusing_changed():
    """Snapshot the lane mid-stream, fuse on, restore: the lane equals the snapshot, and fusing the same items again
    gives the same outputs as the first time, bit for bit -- twice from the same snapshot."""
    events = _events(reorder_ms=0)
    pipe = TargetPipeline(CONFIG)
    half = len(events) // 2
    _run(pipe, events[:half])
    items = []   # the next items, as the pipeline's synchronizer makes them (its stamp rules, its links)
    for dev, body, ns, T in events[half:]:
        (pipe.push_omc if dev == "omc" else pipe.push_ots)(body, ns, T)
        items += pipe.poll_items()
    items += pipe.flush_items()
    assert len(items) > 100
    snap, at_snap = pipe.lane.snapshot(), _lane_bytes(pipe.lane)
    runs = []
    for k in range(3):
        if k:
            pipe.lane.restore(snap)
            assert _lane_bytes(pipe.lane) == at_snap
        outs = [o for it in items for o in pipe._process_item(it, pipe.lane, pipe.diag)]
        runs.append([(o.filter, o.t_ns, o.p.tobytes(), o.cov.tobytes(), o.q.tobytes(), o.time_since_local)
                     for o in outs])
        assert _lane_bytes(pipe.lane) != at_snap
    assert runs[0] == runs[1] == runs[2] and len(runs[0]) > 100


def test_lane_state_copies_every_attribute_it_has():
    """By construction: LaneState.copy copies the whole instance, an attribute nobody listed included, and the copy
    shares no container with the original."""
    st = LaneState(last_local_ns=5)
    st.last_output["cbkf"] = "out"
    st.added_later = [1, 2]          # the point: a new attribute is copied without code for it
    c = st.copy()
    assert vars(c) == vars(st)
    st.added_later.append(3)
    st.last_output["kf"] = "out"
    assert c.added_later == [1, 2] and c.last_output == {"cbkf": "out"}


def test_lane_state_holds_values_or_containers_of_values():
    """What LaneState.copy relies on (a shallow copy is a snapshot): after a run every attribute is a value or a
    container of values (outputs are never changed after they are made)."""
    pipe = ArrivalPipeline(CONFIG)
    _run(pipe, _events())
    for lane in pipe.lanes():
        for name, v in vars(lane.state).items():
            assert v is None or isinstance(v, int | float | str | dict), name
            assert not isinstance(v, dict) or all(dataclasses.is_dataclass(x) for x in v.values()), name
