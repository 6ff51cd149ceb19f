"""Fusion on arrival's input path at 1 kHz + 1 kHz: CPU per sample, and the re-pairing it does per sample.

Why: a node falling seconds behind at 1 kHz + 1 kHz (test_fusion_realtime) spends its time in ArrivalPipeline's
``enqueue``, which pairs the history's window again for every sample it takes in. ``ApproxSync.pair`` of two streams
walks the window with a read position per stream (``_pair_two``); the baseline is what it did before: push the
window into a fresh ApproxSync and flush it (the live synchronizer's rules, list pops and stamp-rule bookkeeping).
Both give the same items (test_synchronizer.py); this prints their cost on the windows the 1 kHz input makes, and
the whole input path per sample (one TargetPipeline on arrival, cbkf, the stream of test_fusion_realtime's 1 kHz
case: tool at 1 kHz on each device, base every 10th frame, the OTS up to 3 ms late). One JSON line per figure.
"""

from __future__ import annotations

import numpy as np
from benchlib import emit, median_time

from fullperc_fusion.fusion_config import read_values, target_config
from fullperc_fusion.pipeline.arrival import make_pipeline
from fullperc_fusion.pipeline.synchronizer import GLOBAL, LOCAL, ApproxSync, Sample

MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def stream(seconds: float = 3.0, seed: int = 0) -> list[tuple[int, str, str, np.ndarray]]:
    """(stamp, device, body, position) in arrival order: frames at 1 kHz, the OTS's up to 3 ms late."""
    rng = np.random.default_rng(seed)
    out, late = [], []
    for k in range(int(seconds * 1000)):
        t = T0 + k * MS
        tool = np.array([0.1 * np.sin(k / 500), 0.05, 0.2])
        for dev, off in (("omc", np.array([1.0, 0.5, 0.8])), ("ots", np.array([0.1, -0.2, -1.5]))):
            bodies = (("base", off), ("tool", off + tool)) if k % 10 == 0 else (("tool", off + tool),)
            for body, p in bodies:
                out.append((t, dev, body, p + rng.normal(0, 1e-4, 3)))
                late.append(int(rng.integers(0, 3 * MS)) if dev == "ots" else 0)
    order = sorted(range(len(out)), key=lambda i: out[i][0] + late[i])
    return [out[i] for i in order]


def flush_pair(glob: list[Sample], local: list[Sample], slop: int):
    """The baseline: the window pushed into a fresh synchronizer and flushed."""
    s = ApproxSync(slop, 0, max_pending=max(1, len(glob), len(local)))
    for x in glob:
        s.push(GLOBAL, x.t_ns, x.payload)
    for x in local:
        s.push(LOCAL, x.t_ns, x.payload)
    return s.flush()


def main() -> None:
    over = {"init_samples": 20, "static_links": "average"}
    cfg = target_config(read_values(lambda n, d: over.get(n, d)), "tool")
    msgs = stream()
    q = np.array([0.0, 0.0, 0.0, 1.0])

    def run() -> None:
        pipe = make_pipeline(cfg)
        for t, dev, body, p in msgs:
            (pipe.push_omc(body, t, (p, q)) if dev == "omc" else pipe.push_local(0, body, t, (p, q)))
            pipe.poll()

    per = median_time(run, repeats=3) / len(msgs)
    emit("arrival_input_per_sample", per * 1e6, "us", samples=len(msgs), processing=cfg.processing)
    # the windows enqueue re-pairs: 2 slop of each stream around a sample (8 ms at 1 kHz: ~8 samples each)
    slop = cfg.slop_ns
    g = [Sample(T0 + k * MS, k) for k in range(2 * slop // MS)]
    loc = [Sample(T0 + k * MS + 300_000, k) for k in range(2 * slop // MS)]
    assert ApproxSync.pair(g, loc, slop) == flush_pair(g, loc, slop)
    new = median_time(lambda: ApproxSync.pair(g, loc, slop), repeats=7, number=2000)
    old = median_time(lambda: flush_pair(g, loc, slop), repeats=7, number=2000)
    emit("arrival_repair_window", new * 1e6, "us", baseline=old * 1e6, window=len(g) + len(loc))


if __name__ == "__main__":
    main()
