"""Accuracy of ``time_align`` in the twin: known Vega stamp offsets injected and recovered (docs/time_alignment.md).

For each seed and offset: a time-alignment take (:func:`fullperc_eval.sim.sync_take.sync_take`: 8 s of the tool
waved in both trackers' view, the twin's ``ots.stamp_offset_s`` set to the offset) is written as a bag and read back
by ``time_align``'s own path (:func:`fullperc_eval.evaluation.time_align_cli.align_bag`); the error is the estimate
minus the injected offset. Prints one line per take and a JSON summary (RMS and largest error, mean reported sigma).

Run: python scripts/time_align_twin.py [--seeds 0-9] [--offsets-ms=-5,0,5] [--profile paper] [--signal speed]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from fullperc_eval.evaluation.time_align_cli import align_bag
from fullperc_eval.evaluation.twin_report import parse_seeds
from fullperc_eval.sim.dataset import content_from_sim, write_bag
from fullperc_eval.sim.sync_take import sync_take
from fullperc_fusion.calibration.time_offset import AlignmentError


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0-9", help="seeds, e.g. 0-9 or 0,3,5 (default %(default)s)")
    ap.add_argument("--offsets-ms", default="-5,0,5", help="injected Vega stamp offsets [ms] (default %(default)s)")
    ap.add_argument("--profile", default="paper", help="twin profile (default %(default)s)")
    ap.add_argument("--signal", default="speed", help="time_align --signal (default %(default)s)")
    args = ap.parse_args(argv)
    offsets = [float(x) for x in args.offsets_ms.split(",")]
    errs, sigmas, failed = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in parse_seeds(args.seeds):
            for off_ms in offsets:
                run = sync_take(seed=seed, ots_stamp_offset_s=off_ms * 1e-3, profile=args.profile)
                bag = write_bag(Path(tmp) / f"s{seed}_{off_ms:+g}", content_from_sim(run))
                try:
                    r = align_bag(bag, signal=args.signal)
                except AlignmentError as e:
                    failed.append({"seed": seed, "offset_ms": off_ms, "error": str(e)})
                    print(f"seed {seed} offset {off_ms:+.1f} ms: {e}")
                    continue
                err = r.offset_s * 1e3 - off_ms
                errs.append(err)
                sigmas.append(r.offset_sigma_s * 1e3)
                vis = float(run.ots.tools["tool"].visible.mean())
                print(f"seed {seed} offset {off_ms:+.1f} ms: estimate {r.offset_s * 1e3:+.3f} ms, error {err:+.3f} "
                      f"ms, reported sigma {sigmas[-1]:.3f} ms, {len(r.windows)} windows, Vega sees the tool "
                      f"{vis:.0%} of the take")
    e = np.abs(errs)
    print(json.dumps({"profile": args.profile, "signal": args.signal, "takes": len(errs), "failed": failed,
                      "rms_error_ms": float(np.sqrt(np.mean(np.square(errs)))) if errs else None,
                      "max_abs_error_ms": float(e.max()) if errs else None,
                      "within_0_5_ms": int((e <= 0.5).sum()),
                      "mean_sigma_ms": float(np.mean(sigmas)) if errs else None}))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
