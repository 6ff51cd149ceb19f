"""The offline evaluation's further hot paths give the plain form's results exactly (issue 38 item 5).

* the synchronizer's two-stream drain and poll (``ApproxSync._drain_two``) against the general drain
  (``_drain_any``) and the general poll: the same items, counters (in the same order), stamp rules and pending
  samples, on random streams with equal stamps, ties within the slop, late and duplicate samples, overflow and
  given clocks;
* ``Box.blocks``' pairwise min / max over the axes against numpy's reduction along the last axis, on random
  segments including points on a face, inside a box, at the origin and axis-parallel segments;
* ``StaticLinks.add`` calls the calibrate-mode finish only once a collection is complete: the links, estimates,
  sources and generation after every sighting are those of calling the finish after every sighting.
"""

from __future__ import annotations

import copy
import random

import numpy as np
import pytest

from fullperc_fusion.calibration.static_links import ChainConfig, StaticLinks
from fullperc_fusion.margin.geometry import SEGMENT_END, Box
from fullperc_fusion.pipeline.synchronizer import ApproxSync


# ------------------------------------------------------------------------------------------ synchronizer
class _Plain(ApproxSync):
    """The general poll and drain for two streams (the reference of the two-stream shortcut)."""

    def poll(self, now_ns=None):
        now = self.watermark_ns if now_ns is None else int(now_ns)
        if now is None:
            return []
        final_by = now - 2 * self.slop - self.delay
        head = None
        for s, ts in enumerate(self._t):
            if ts and (head is None or (ts[0], s) < head):
                head = (ts[0], s)
        if head is None or (head[0] > final_by and len(self._t[head[1]]) <= self.max_pending):
            return []
        return self._drain_any(lambda t: t <= final_by)

    def _drain_two(self, final):
        return self._drain_any(final)


def _items(items):
    return [(i.t_ns, i.glob and (i.glob.t_ns, i.glob.payload), i.local and (i.local.t_ns, i.local.payload), i.source)
            for i in items]


def _state(s: ApproxSync):
    r = s.rules
    return (list(s.counts.items()), r.horizon_ns, r.newest_ns, list(r.released), [sorted(p) for p in r.pending],
            [list(t) for t in s._t], [list(p) for p in s._p])


@pytest.mark.parametrize("seed", range(4))
def test_two_stream_drain_and_poll_equal_the_general_ones(seed):
    rng = random.Random(seed)
    for _ in range(150):
        slop, delay, maxp = rng.choice([0, 2, 5, 9]), rng.choice([0, 7, 30]), rng.choice([1, 3, 4096])
        a, b = ApproxSync(slop, delay, max_pending=maxp), _Plain(slop, delay, max_pending=maxp)
        t = [0, 0]
        for k in range(80):
            st = rng.randint(0, 1)
            t[st] = max(1, t[st] + rng.randint(-6, 12)) if rng.random() < 0.9 else t[1 - st]   # equal stamps too
            assert a.push(st, t[st], k) == b.push(st, t[st], k)
            r = rng.random()
            if r < 0.6:
                got, want = a.poll(), b.poll()
            elif r < 0.9:
                now = rng.randint(0, 500)
                got, want = a.poll(now), b.poll(now)
            else:
                got, want = a.flush(), b.flush()
            assert _items(got) == _items(want)
            assert _state(a) == _state(b)
        assert _items(a.flush()) == _items(b.flush()) and _state(a) == _state(b)


def test_three_streams_take_the_general_drain():
    a = ApproxSync(3, 0, names=("global", "local", "local1"))
    for st, t in ((0, 10), (1, 11), (2, 10), (2, 30), (0, 40)):
        a.push(st, t, t)
    got = a.flush()
    assert [(i.t_ns, i.source) for i in got] == [(11, 0), (10, 1), (30, 1), (40, 0)]


# ------------------------------------------------------------------------------------------ occluders
def _blocks_reduced(box: Box, origin, points) -> np.ndarray:
    """Box.blocks with numpy's reductions along the last axis (its form before the pairwise min / max)."""
    c = np.asarray(origin, dtype=float)
    d = np.asarray(points, dtype=float) - c
    inv = 1.0 / (d + 1e-300)
    t1 = (box.lo - c) * inv
    t2 = (box.hi - c) * inv
    tmin = np.max(np.minimum(t1, t2), axis=-1)
    tmax = np.min(np.maximum(t1, t2), axis=-1)
    return np.maximum(tmin, 0.0) <= np.minimum(tmax, SEGMENT_END)


def test_box_blocks_equals_the_reduction():
    rng = np.random.default_rng(7)
    for _ in range(300):
        lo = rng.uniform(-1.0, 0.5, 3)
        box = Box("b", lo, lo + rng.uniform(0.05, 1.0, 3))
        cams = rng.uniform(-3.0, 3.0, (1, 6, 3))
        pts = rng.uniform(-2.0, 2.0, (40, 1, 3))
        pts[0, 0] = box.lo                                     # a corner
        pts[1, 0] = (box.lo + box.hi) / 2                      # inside
        pts[2, 0] = np.array([box.hi[0], *(box.lo[1:] + box.hi[1:]) / 2])   # on a face
        pts[3, 0] = cams[0, 0]                                 # at a camera (d = 0)
        pts[4, 0] = cams[0, 1] + np.array([0.0, 0.0, 1.5])     # axis-parallel segment
        pts[5, 0, 0] = cams[0, 2, 0]
        assert np.array_equal(box.blocks(cams, pts), _blocks_reduced(box, cams, pts))
        assert np.array_equal(box.blocks(cams[0, 0], pts[:, 0]), _blocks_reduced(box, cams[0, 0], pts[:, 0]))
    nan = np.array([[np.nan, 0.0, 0.0]])
    assert np.array_equal(box.blocks(np.zeros(3), nan), _blocks_reduced(box, np.zeros(3), nan))


# ------------------------------------------------------------------------------------------ static links
def _T(rng: np.random.Generator, p0: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    a = rng.normal(0.0, 1e-4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = p0 + rng.normal(0.0, 5e-5, 3)
    return T


def _links_state(s: StaticLinks):
    return (s.generation, s.collecting, dict(s.sources), sorted(s.estimates), s.refusals,
            None if s.T_omc_base is None else s.T_omc_base.tobytes(),
            None if s.T_base_ots is None else s.T_base_ots.tobytes())


def test_static_links_finish_as_when_tried_after_every_sighting():
    cfg = ChainConfig(static_links="calibrate", calibration_duration_s=1.0)
    fast = StaticLinks(cfg)
    every = copy.deepcopy(fast)
    rng = np.random.default_rng(3)
    p_omc, p_ots = np.array([1.0, 0.2, 0.5]), np.array([-0.3, 0.1, 1.2])
    t = 1_000_000_000
    for k in range(300):
        t += 10_000_000
        which, p0 = ("omc_base", p_omc) if k % 2 == 0 else ("ots_base", p_ots)
        T = _T(rng, p0)
        a = fast.add(which, T, t)
        b = every.add(which, T, t)
        b = every._try_finish_calibrate() or b   # the former add: the finish tried after every sighting
        assert a == b, k
        assert _links_state(fast) == _links_state(every), k
    assert not fast.collecting and fast.T_omc_base is not None and fast.T_base_ots is not None
