"""Is the static link's covariance the size of the link's error? (issue 18, docs/fullperc_filter.md "The link's
covariance and the bridge link"). Raw sensor data only: no filter output is looked at.

Replays each bag the way the evaluation does (:func:`fullperc_eval.evaluation.metrics.evaluate_bag`, default fusion
config) and records, for every Vega sample, the link T_base_ots it was mapped through and that link's 6x6 covariance
(the calibrated robust mean, or the 30-sample average that bridges until it is done). Every Vega sample mapped
through one link carries that link's error, so the mean of the raw Vega chain's error against the Diana truth over
those samples is the link's error at the tool (the Vega's own noise averages out over hundreds of samples). Per link
it prints that mean [mm], the std the covariance predicts for it at the samples' mean lever arm
(:func:`fullperc_fusion.filters.measurement_models.link_covariance_at`) [mm] and their ratio z per axis; at the
end the rms of z per axis over all links: ~1 when the covariance is the size of the error, well above 1 when it is
too small.

Run: python scripts/link_cov_check.py BAG [BAG ...]
"""

from __future__ import annotations

import argparse

import numpy as np

import fullperc_fusion.pipeline.measure as pipeline  # where the pipeline looks local_covariance up
from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_fusion.filters.measurement_models import link_covariance_at


def link_errors(bag: str) -> list[dict]:
    """Per link used for the bag's Vega samples: n, mean raw error [m], predicted std [m] (3 each)."""
    used: list[tuple[np.ndarray, np.ndarray | None]] = []
    original = pipeline.local_covariance

    def recording(A, T_dev, link_cov, **kw):   # A = T_base_ots for the static chain (T_base_tool = A T_ots_tool)
        used.append((A[:3, 3].copy(), link_cov))
        return original(A, T_dev, link_cov, **kw)

    pipeline.local_covariance = recording
    try:
        ev = evaluate_bag(bag, progress=False)
    finally:
        pipeline.local_covariance = original
    s = ev.series
    loc = s["single_sources"]["local"]
    tg, pg = s["grid_t_ns"], s["grid_p"]
    if len(used) != len(loc["t_ns"]):
        raise RuntimeError(f"{bag}: {len(used)} Vega samples mapped, {len(loc['t_ns'])} recorded by the tap")
    err = loc["p"] - np.stack([np.interp(loc["t_ns"], tg, pg[:, k]) for k in range(3)], 1)
    groups: dict[int, list[int]] = {}
    for i, (_, cov) in enumerate(used):
        if cov is not None:
            groups.setdefault(id(cov), []).append(i)
    out = []
    for idx in groups.values():
        origin, cov = used[idx[0]]
        lever = loc["p"][idx].mean(axis=0) - origin
        sd = np.sqrt(np.diag(link_covariance_at(cov, lever))[:3])
        out.append({"n": len(idx), "mean": err[idx].mean(axis=0), "sd": sd})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bags", nargs="+")
    args = ap.parse_args(argv)
    z = []
    for bag in args.bags:
        for g in link_errors(bag):
            zz = g["mean"] / g["sd"]
            z.append(zz)
            print(f"{bag}: {g['n']} Vega samples, link error at the tool {np.round(g['mean'] * 1e3, 3)} mm, "
                  f"predicted sd {np.round(g['sd'] * 1e3, 3)} mm, z {np.round(zz, 2)}")
    if not z:
        raise SystemExit("no Vega sample was mapped through a link with a covariance")
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    print(f"rms z per axis over {len(z)} links: {np.round(rms, 2)}")


if __name__ == "__main__":
    main()
