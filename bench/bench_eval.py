"""Offline evaluation throughput: measurements/s through ``evaluate`` (bag reading + all five methods + truth).

Figures (medians over repeats; a "measurement" is one message the evaluator reads: an OMC/OTS pose of the
target, base or rig, or a joint state):
  eval_throughput_all5     evaluate_bag, bag decode included, the paper's five methods side by side
                           (omc, kf, bkf, ckf, cbkf), through the batched replay (evaluation/batch.py, the
                           default)                                                        baseline: bulk decode
                           (+ with_rosbags_decode: the per-sample evaluation reading through rosbags per message,
                           as before the bulk path, same run)
  eval_throughput_all5_per_sample  the same through the per-sample replay (``evaluate --per-sample``, the
                           reference; ``speedup`` = batched / per-sample in this run)     baseline: bulk decode
  eval_throughput_cbkf     the same with the cbkf filter alone (batched; ``per_sample`` field: the per-sample
                           replay's rate in this run)                                      baseline: bulk decode
  eval_throughput_every    the same with every method `evaluate` runs by default, when that is more than the five
                           (a filter registered since, e.g. fullperc: run per sample beside the batched five;
                           ``per_sample`` field: everything per sample)                    baseline: bulk decode
  eval_decode_bulk         bag.reader.decoded_messages of the same topics (what evaluate reads through, one pass
                           over the MCAP file + numpy CDR decode: the floor)              baseline: rosbags
  eval_read_only           rosbags' reader + deserializer per message (the evaluator's reading before issue 16)
ratio = value / baseline (for the throughputs: the share of the decoding rate that the evaluation reaches).

Bag: bags/paper/G-B-P (the committed sample) when present, else a 20 s synthetic recording (same rates).
Run: python bench/bench_eval.py [--profile]   (--profile: cProfile of one evaluate_bag, top functions on stderr)
The per-sample figures are measured in the same run, so the batched/per-sample ratio is visible in one run.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchlib import emit, median_time  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
REPEATS = 3
PAPER_FIVE = ("omc", "kf", "bkf", "ckf", "cbkf")   # "all5": the paper's Table 1 columns


def main() -> None:
    from fullperc_eval.bag.reader import BagReader, decoded_messages
    from fullperc_eval.evaluation.metrics import evaluate_bag
    from fullperc_eval.evaluation.replay import JOINT_TOPIC
    from fullperc_eval.sim.dataset import synthetic_content, write_bag
    from fullperc_fusion.fusion_config import load_fusion_config

    tmp = None
    bag = ROOT / "bags" / "paper" / "G-B-P"
    if not (bag / "metadata.yaml").is_file():
        tmp = Path(tempfile.mkdtemp(prefix="bench_eval_"))
        bag = write_bag(tmp / "synthetic", synthetic_content(20.0)[0])
    try:
        cfg_all, _ = load_fusion_config(filters=PAPER_FIVE)
        cfg_every, _ = load_fusion_config()          # what `evaluate` runs: the five + any filter registered since
        cfg_one, _ = load_fusion_config(filters=("cbkf",))
        topics = [f"/omc/{b}/pose" for b in ("tool", "base", "ots_rig")] + \
                 [f"/ots/{b}/pose" for b in ("tool", "base")] + [JOINT_TOPIC]
        n = evaluate_bag(bag, progress=False, config=cfg_all).result["messages"]
        from fullperc_eval.evaluation.replay import replay as replay_fn
        path_all = replay_fn(bag, cfg_all, progress=False).path   # "batched" unless it fell back (then: why not)

        def read_only():
            r = BagReader(bag).open()
            for m in r.messages(topics):
                r.deserialize(m.data, m.msgtype)
            r.close()

        def bulk():
            r = BagReader(bag)
            decoded_messages(r, [t for t in topics if t in r.topics])
            r.close()

        if "--profile" in sys.argv:
            import cProfile
            import pstats

            prof = cProfile.Profile()
            prof.runcall(evaluate_bag, bag, progress=False, config=cfg_all)
            pstats.Stats(prof, stream=sys.stderr).sort_stats("tottime").print_stats(25)
        t_read = median_time(read_only, repeats=REPEATS)
        t_bulk = median_time(bulk, repeats=REPEATS)
        t_all = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_all), repeats=REPEATS)
        t_one = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_one), repeats=REPEATS)
        from fullperc_eval.bag import reader as bag_reader
        from fullperc_eval.evaluation import replay as replay_mod

        def with_rosbags_decode():   # the evaluator before the bulk path: rosbags per message (same outputs)
            replay_mod.decoded_messages = bag_reader.decoded_messages_reference
            try:
                evaluate_bag(bag, progress=False, config=cfg_all, per_sample=True)
            finally:
                replay_mod.decoded_messages = bag_reader.decoded_messages

        t_before = median_time(with_rosbags_decode, repeats=REPEATS)
        t_all_ps = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_all, per_sample=True),
                               repeats=REPEATS)
        t_one_ps = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_one, per_sample=True),
                               repeats=REPEATS)
        t_every = t_every_ps = None
        if tuple(cfg_every.filters) != tuple(cfg_all.filters):
            t_every = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_every), repeats=REPEATS)
            t_every_ps = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_every, per_sample=True),
                                     repeats=REPEATS)
        name = bag.name if tmp is None else "synthetic 20 s"
        emit("eval_read_only", n / t_read, "measurements/s", bag=name, measurements=n)
        emit("eval_decode_bulk", n / t_bulk, "measurements/s", baseline=n / t_read, bag=name, measurements=n)
        emit("eval_throughput_all5", n / t_all, "measurements/s", baseline=n / t_bulk, bag=name, measurements=n,
             seconds=round(t_all, 3), methods=list(cfg_all.filters),
             path=path_all, with_rosbags_decode=round(n / t_before, 1),
             speedup_vs_rosbags_decode=round(t_before / t_all, 3))
        emit("eval_throughput_all5_per_sample", n / t_all_ps, "measurements/s", baseline=n / t_bulk, bag=name,
             measurements=n, seconds=round(t_all_ps, 3), methods=list(cfg_all.filters),
             speedup=round(t_all_ps / t_all, 3))
        emit("eval_throughput_cbkf", n / t_one, "measurements/s", baseline=n / t_bulk, bag=name, measurements=n,
             seconds=round(t_one, 3), per_sample=round(n / t_one_ps, 1), speedup=round(t_one_ps / t_one, 3))
        if t_every is not None and t_every_ps is not None:
            emit("eval_throughput_every", n / t_every, "measurements/s", baseline=n / t_bulk, bag=name,
                 measurements=n, seconds=round(t_every, 3), methods=list(cfg_every.filters),
                 per_sample=round(n / t_every_ps, 1), speedup=round(t_every_ps / t_every, 3))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
