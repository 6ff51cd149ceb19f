"""Where both devices see a target (BVV): which raw source is the better one, and where fusion lands (issue 41).

``make accuracy``'s check ``mae_vs_omc_every_task_seed`` asks ``fullperc`` to be at or below the raw OMC in every
task-seed. Where the Vega sees the target, fusion combines two devices whose errors at that spot are, per room, a
draw: the OMC's position-dependent error (lens residual, per-camera pose errors) and the local chain's (the Vega plus
the calibrated static links). The two devices observe only the difference of their errors, so no causal filter can
tell which of them is the better one in a given room -- it weighs them by their statistics over rooms. This script
scores, per bag, the three against the truth where the true path is in BVV *and* the Vega actually reports the target
(``metrics.local_seen_mask``: the margin model's BVV can begin a second before the Vega's first sample): the OMC's own
chain (``single_sources["global"]``, no filter), the local chain's (``single_sources["local"]``) and ``fullperc``'s
output; and counts the bags where the raw OMC beats the raw local chain, and where ``fullperc`` is above the raw OMC.
The truth scores; nothing here sets anything.

Every position is compared with the true position linearly interpolated on the evaluation's truth grid
(``series["grid_p"]``: joint-state stamps for the arm-held tool, the recorded truth for other targets), so the three
are scored the same way; ``test_sources_in_bvv.py`` holds the OMC's and ``fullperc``'s figures to the evaluation's
on a bag where the Vega reports the target all through BVV.

Run: python scripts/sources_in_bvv.py --target instrument ~/.cache/fullperc/accuracy/spec-<hash>/seed{0..9}/*
     (bag directories, or directories holding bags)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fullperc_eval.evaluation.evaluate_all import find_bags
from fullperc_eval.evaluation.metrics import evaluate_bag, local_seen_mask

BVV = 1   # the margin model's label of "both devices see it" (metrics.LETTER)


def _true_at(grid_t: np.ndarray, grid_p: np.ndarray, grid_ok: np.ndarray, t_ns: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """True positions at ``t_ns`` by linear interpolation on the truth grid; False where outside it or a neighbour
    is not valid."""
    k = np.clip(np.searchsorted(grid_t, t_ns), 1, len(grid_t) - 1)
    t0, t1 = grid_t[k - 1].astype(float), grid_t[k].astype(float)
    w = ((t_ns - t0) / np.maximum(t1 - t0, 1.0))[:, None]
    ok = (t_ns >= grid_t[0]) & (t_ns <= grid_t[-1]) & grid_ok[k - 1] & grid_ok[k]
    return grid_p[k - 1] * (1 - w) + grid_p[k] * w, ok


def bvv_mae(bag: Path, target: str, fusion_config: Path | None = None) -> dict[str, float] | None:
    """MAE [mm] in BVV, where the Vega reports the target, of the raw OMC chain, the raw local chain and ``fullperc`` in
    one bag; None: no such sample.
    ``fusion_config``: a fusion_node parameter file instead of the shipped ``fusion.yaml`` (e.g. the one
    ``python -m fullperc_eval.evaluation.accuracy --noise-model calibrated`` writes beside the seeds' bags, with the
    room's own noise model)."""
    s = evaluate_bag(bag, target=target, progress=False, fusion_config=fusion_config).series
    grid_t, labels = s["grid_t_ns"], s["labels"]
    grid_p, grid_ok = s["grid_p"], np.asarray(s["grid_ok"], dtype=bool)
    tracks = {"omc": s["single_sources"]["global"], "local": s["single_sources"]["local"],
              "fullperc": s["outputs"]["fullperc"]}
    out = {}
    for name, tr in tracks.items():
        t = np.asarray(tr["t_ns"], dtype=np.int64)
        truth, ok = _true_at(grid_t, grid_p, grid_ok, t)
        lab = labels[np.clip(np.searchsorted(grid_t, t, side="right") - 1, 0, len(grid_t) - 1)]
        seen = local_seen_mask(t, tracks["local"]["t_ns"])
        sel = ok & (lab == BVV) & seen & np.isfinite(tr["p"]).all(axis=1)
        if not sel.any():
            return None
        out[name] = float(np.linalg.norm(tr["p"][sel] - truth[sel], axis=1).mean() * 1e3)
    return out


def bags_under(paths: list[Path]) -> list[Path]:
    """Each path that is a bag, and the bags in each that is not (``evaluate_all.find_bags``: in task order)."""
    return [b for p in paths for b in ([p] if (p / "metadata.yaml").exists() else find_bags(p))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="+", type=Path, help="bag directories, or directories holding bags")
    ap.add_argument("--target", default="instrument", help="the target evaluated (default: instrument)")
    ap.add_argument("--fusion-config", type=Path, help="a fusion_node parameter file (default: the shipped one)")
    a = ap.parse_args(argv)
    rows = []
    print(f"{'bag':40s} {'omc':>6s} {'local':>6s} {'fullperc':>8s}  [mm, BVV]")
    for bag in bags_under(a.paths):
        r = bvv_mae(bag, a.target, a.fusion_config)
        if r is None:
            continue
        rows.append(r)
        print(f"{'/'.join(bag.parts[-2:]):40s} {r['omc']:6.3f} {r['local']:6.3f} {r['fullperc']:8.3f}", flush=True)
    if not rows:
        print("no bag with the target in BVV")
        return 1
    m = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    omc_better = int((m["omc"] < m["local"]).sum())
    above, below_both = int((m["fullperc"] > m["omc"]).sum()), int(((m["fullperc"] < m["omc"])
                                                                    & (m["fullperc"] < m["local"])).sum())
    print(f"{len(rows)} bags: mean omc {m['omc'].mean():.3f}, local {m['local'].mean():.3f}, fullperc "
          f"{m['fullperc'].mean():.3f} mm; the raw OMC better than the raw local chain in {omc_better}, fullperc "
          f"above the raw OMC in {above}, below both raw sources in {below_both}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
