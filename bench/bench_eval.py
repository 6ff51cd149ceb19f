"""Offline evaluation throughput: measurements/s through ``evaluate`` (bag reading + all five methods + truth).

Figures (medians over repeats; a "measurement" is one message the evaluator reads: an OMC/OTS pose of the
target, base or rig, or a joint state):
  eval_throughput_all5     evaluate_bag with omc, kf, bkf, ckf, cbkf side by side   baseline: reading only
  eval_throughput_cbkf     the same with the cbkf filter alone                      baseline: reading only
  eval_read_only           BagReader.messages + CDR decode of the same topics (the floor)
ratio = value / baseline (< 1: the share of the reading-only rate that the evaluation reaches).

Bag: bags/paper/G-B-P (the committed sample) when present, else a 20 s synthetic recording (same rates).
Run: python bench/bench_eval.py
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


def main() -> None:
    from fullperc_eval.bag.reader import BagReader
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
        cfg_all, _ = load_fusion_config()
        cfg_one, _ = load_fusion_config(filters=("cbkf",))
        topics = [f"/omc/{b}/pose" for b in ("tool", "base", "ots_rig")] + \
                 [f"/ots/{b}/pose" for b in ("tool", "base")] + [JOINT_TOPIC]
        n = evaluate_bag(bag, progress=False, config=cfg_all).result["messages"]

        def read_only():
            r = BagReader(bag).open()
            for m in r.messages(topics):
                r.deserialize(m.data, m.msgtype)
            r.close()

        t_read = median_time(read_only, repeats=REPEATS)
        t_all = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_all), repeats=REPEATS)
        t_one = median_time(lambda: evaluate_bag(bag, progress=False, config=cfg_one), repeats=REPEATS)
        name = bag.name if tmp is None else "synthetic 20 s"
        emit("eval_read_only", n / t_read, "measurements/s", bag=name, measurements=n)
        emit("eval_throughput_all5", n / t_all, "measurements/s", baseline=n / t_read, bag=name, measurements=n,
             seconds=round(t_all, 3))
        emit("eval_throughput_cbkf", n / t_one, "measurements/s", baseline=n / t_read, bag=name, measurements=n,
             seconds=round(t_one, 3))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
