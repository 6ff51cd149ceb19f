"""Where a method's orientation error is spent: before the Vega first sees the tool, while it sees it, after it lost it.

Issue 18's orientation goal on the same samples (``orientation_vs_single_sources_same_samples``) splits a task's
outputs into those where the Vega sees the tool (``metrics.local_seen_mask``) and the others; this script splits the
others once more, at the Vega's first sample: before it no method has anything but the OMC, after it a method may
carry what it learnt while the Vega saw the tool (``fullperc``'s orientation bias beta). Printed per bag: the
orientation MAE [deg] of ``fullperc`` and of the raw OMC in each phase (number of outputs in brackets) and the raw
local chain's (LOCAL: only where the Vega sees the tool). Replays each bag with the given fusion configuration, as
``evaluate`` does. ``--raw``: also the raw sensors' rotation error while the Vega sees the tool (the node's frame
chain against the Diana truth, ``sensor_stats.bag_rows``, no filter): per axis its spread (std) and its white part
(frame-to-frame differences / sqrt 2) [mrad], for the OMC and the local chain -- equal figures mean white noise.

Run: python scripts/orientation_phases.py ~/.cache/fullperc/accuracy/paper-<hash>/seed100/P-G-B-P [--fusion-config F]
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from fullperc_eval.evaluation import sensor_stats
from fullperc_eval.evaluation.metrics import evaluate_bag, local_seen_mask
from fullperc_fusion.margin.layout import default_layout_path, load_layout

METHODS = ("fullperc", "omc")


def phases(ev) -> dict[str, dict[str, tuple[float, int]]]:
    """{method: {phase: (orientation MAE [deg], outputs)}} of one evaluation; phases ``before`` (the Vega's first
    sample), ``seen`` and ``after`` (not seen, after that sample); NaN where a phase has no output."""
    s = ev.series
    local_t = s["single_sources"]["local"]["t_ns"]
    out: dict[str, dict[str, tuple[float, int]]] = {}
    for f in METHODS:
        t = s["outputs"][f]["t_ns"]
        err = s["orientation_errors"][f]
        seen = local_seen_mask(t, local_t)
        t1 = int(np.min(local_t)) if len(local_t) else np.iinfo(np.int64).max
        masks = {"before": ~seen & (t < t1), "seen": seen, "after": ~seen & (t >= t1)}
        out[f] = {k: (float(np.nanmean(err[m])) if m.any() else float("nan"), int(m.sum())) for k, m in masks.items()}
    return out


def raw_seen(bag: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{"omc" | "local": (per-axis std, per-axis white std) [rad]} of the raw rotation error within the span of the
    Vega's samples."""
    omc, ots = sensor_stats.bag_rows(Path(bag), load_layout(default_layout_path()))
    rot = slice(sensor_stats.RX, sensor_stats.RZ + 1)
    t0, t1 = ots[:, sensor_stats.T].min(), ots[:, sensor_stats.T].max()
    inside = (omc[:, sensor_stats.T] >= t0) & (omc[:, sensor_stats.T] <= t1)
    out = {}
    for name, e in (("omc", omc[inside, rot]), ("local", ots[:, rot])):
        out[name] = (e.std(0), np.sqrt((np.diff(e, axis=0) ** 2).mean(0) / 2))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bags", nargs="+", help="bag directories")
    ap.add_argument("--fusion-config", default=None, help="fusion.yaml to replay with (default: fusion_node's)")
    ap.add_argument("--raw", action="store_true", help="also the raw sensors' rotation error where the Vega sees")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    for bag in args.bags:
        ev = evaluate_bag(bag, fusion_config=args.fusion_config, progress=False)
        cells = [f"{f} {k} {v:.3f} ({n})" for f, ph in phases(ev).items() for k, (v, n) in ph.items()]
        local = ev.result["single_sources"].get("local", {}).get("orientation_mae_deg")
        print(f"{bag}: " + ", ".join(cells) + f", LOCAL {local if local is None else round(local, 3)}")
        if args.raw:
            for name, (sd, white) in raw_seen(bag).items():
                print(f"  raw {name} rotation error where the Vega sees the tool [mrad per axis]: std "
                      f"{np.round(sd * 1e3, 2)}, white {np.round(white * 1e3, 2)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
