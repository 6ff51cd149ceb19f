"""``evaluate``: offline evaluation of one bag -- the paper's Table 1 (MAE) and Table 2 (B->P segment).

    evaluate BAG [--out DIR] [--json FILE] [--calibration FILE] [--layout FILE] [--fusion-config FILE]
                 [--target tool] [--quiet] [--live] [--per-sample]

(the ``evaluate`` executable; ``python -m fullperc_eval.evaluation.cli`` is the same). What it computes is in
:mod:`.metrics`; how the bag is replayed in :mod:`.replay`; the ground truth in :mod:`.ground_truth`.

Bad input (missing/corrupt bag, missing metadata.yaml, a topic with an unexpected type, no joint states, no
calibration) ends with ``error: ...`` on stderr and exit code 1, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fullperc_eval.bag.calibration import CalibrationError
from fullperc_eval.bag.errors import BagError

from .config import EvaluationError
from .metrics import evaluate_bag
from .report import write_report
from .tables import format_table1, format_table2, write_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="evaluate", description=__doc__.split("\n")[0])
    ap.add_argument("bag", help="rosbag2 bag directory (with metadata.yaml)")
    ap.add_argument("--out", help="write the report (PNG plots, index.html, eval.json) into this directory")
    ap.add_argument("--json", help="write all figures as JSON to this file")
    ap.add_argument("--calibration", help="calibration YAML (default: <bag>/calibration.yaml)")
    ap.add_argument("--layout", help="camera layout YAML (default: fullperc_fusion's or_layout.yaml)")
    ap.add_argument("--fusion-config", help="fusion_node params file (default: fullperc_fusion's fusion.yaml)")
    ap.add_argument("--target", default="tool",
                    help="fused target name (default: tool, the arm-held target, truth from the Diana's joints; any "
                         "other needs its simulator truth /sim/truth/<target> in the bag, e.g. the twin's instrument)")
    ap.add_argument("--quiet", action="store_true", help="no progress output")
    ap.add_argument("--live", action="store_true",
                    help="evaluate the fused poses recorded live (/fullperc/<target>/...) instead of re-running")
    ap.add_argument("--per-sample", action="store_true",
                    help="replay one message at a time through the fusion pipeline (the reference) instead of the "
                         "batched replay; same result, slower (the batched replay falls back to it by itself for "
                         "what it does not support)")
    args = ap.parse_args(argv)
    try:
        ev = evaluate_bag(args.bag, calibration=args.calibration, layout=args.layout,
                          fusion_config=args.fusion_config, target=args.target, progress=not args.quiet,
                          live=args.live, per_sample=args.per_sample)
        r = ev.result
        print(format_table1([r]))
        print()
        print(format_table2(r))
        for w in r["warnings"]:
            print(f"warning: {w}", file=sys.stderr)
        if args.json:
            write_json(args.json, r)
        if args.out:
            index = write_report(ev, args.out)
            write_json(Path(args.out) / "eval.json", r)
            print(f"report: {index}")
    except (EvaluationError, BagError, CalibrationError) as e:
        print("error: " + " ".join(str(e).split()), file=sys.stderr)   # one line, also for YAML parser messages
        return 1
    except OSError as e:
        print(f"error: {e.filename or ''}: {e.strerror or e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
