"""What crosses ``fullperc``'s hop gate in one bag, and what it does to the bias (docs/fullperc_filter.md).

Replays the bag the way the evaluation does (:func:`fullperc_eval.evaluation.metrics.evaluate_bag`, the fusion
config given or the default) with every ``fullperc`` update logged, and prints

* each update inside ``--from``/``--to`` [s from the first output] that flagged a hop (or every update with
  ``--all``): time, sources (1 OMC alone, 3 a pair), position / rotation hop, the global NIS, the OMC innovation
  [mm], the change of b and of g [mm], the velocity before and after the update and the true one [mm/s] (the Diana's
  forward kinematics, finite differences). With ``motion: auto`` each stamp is updated once per motion model (the
  IMM, :mod:`fullperc_fusion.filters.fullperc_imm`): a stamp counts as a hop when any model flagged one, and its
  line is that model's (else the last model's), named after the row (``model arm`` ...);
* a summary: position and rotation hops per source layout, the velocity error's rms over the window [mm/s], the
  raw OMC error against the truth over the window (mean ± sd per axis [mm]), its frame-to-frame scatter (the std of
  consecutive differences / sqrt 2, per axis [mm]) next to the white std the OMC model gave those samples (median
  of the per-axis mean of the covariance's position diagonal, before the noise scale [mm]) and the median noise
  scale lambda, and every method's MAE in the window and over the task.

Run: python scripts/hop_trace.py BAG [--fusion-config F] [--from 16.8] [--to 21.0] [--all]
"""

from __future__ import annotations

import argparse

import numpy as np

import fullperc_fusion.filters.fullperc as ff
from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_fusion.filters.motion import PRESETS


def _model_name(params) -> str:
    """The motion preset a filter runs as (one model of ``motion: auto``: :func:`.motion.with_preset`), else
    ``fixed``."""
    for name, fields in PRESETS.items():
        if all(getattr(params, k) == v for k, v in fields.items()):
            return name
    return "fixed"


def shown_updates(log: list[tuple]) -> dict[int, tuple]:
    """The update shown per stamp, from the logged ones (stamp, ..., position hops [2], rotation hops [3], ...,
    model name [10]): a rewind replays updates, so the last one of each stamp and model counts (what the outputs are);
    of a stamp's models, the first that flagged a hop, else the last model's."""
    per_model: dict[int, dict[str, tuple]] = {}
    for rec in log:
        per_model.setdefault(rec[0], {})[rec[10]] = rec
    return {t: next((r for r in recs.values() if r[2] or r[3]), list(recs.values())[-1])
            for t, recs in per_model.items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag")
    ap.add_argument("--fusion-config", default=None)
    ap.add_argument("--from", dest="t_from", type=float, default=0.0)
    ap.add_argument("--to", dest="t_to", type=float, default=1e9)
    ap.add_argument("--all", action="store_true", help="print every update in the window, not only hops")
    args = ap.parse_args(argv)

    log = []
    update = ff.FullpercFilter.update

    def logged(self, *ms):   # the filter's own update; the state before and after is recorded around it
        x0, hp, hr, lam = list(self._x), self.hop_counts["position"], self.hop_counts["rotation"], self._lam
        st = update(self, *ms)
        cov = next((m.cov for m in ms if m.source == ff.SOURCE_GLOBAL and m.cov is not None), None)
        white = float(np.sqrt(np.diag(cov)[0:3]).mean()) if cov is not None else np.nan
        log.append((st.t_ns, int(st.sources), self.hop_counts["position"] - hp, self.hop_counts["rotation"] - hr,
                    st.nis_global, st.innovation.copy(), np.array(x0), np.array(self._x), white, lam,
                    _model_name(self.params)))
        return st

    ff.FullpercFilter.update = logged
    try:
        ev = evaluate_bag(args.bag, fusion_config=args.fusion_config, progress=False)
    finally:
        ff.FullpercFilter.update = update
    s = ev.series
    tg, pg = s["grid_t_ns"], s["grid_p"]
    vg = np.gradient(pg, tg * 1e-9, axis=0)
    t0 = s["outputs"]["omc"]["t_ns"][0]
    last = shown_updates(log)
    counts = {}
    dv, white, lams = [], [], []
    for t in sorted(last):
        t_ns, src, hp, hr, nis, y, x0, x1, w, lam, model = last[t]
        r = (t_ns - t0) * 1e-9
        if not args.t_from <= r <= args.t_to:
            continue
        vt = np.array([np.interp(t_ns, tg, vg[:, k]) for k in range(3)])
        dv.append(x1[3:6] - vt)
        if src & 1:
            white.append(w)
            lams.append(lam)
        key = ("OMC alone" if src == 1 else "pair" if src == 3 else "Vega alone")
        c = counts.setdefault(key, [0, 0, 0])
        c[0] += 1
        c[1] += hp
        c[2] += hr
        if hp or hr or args.all:
            print(f"{r:8.3f} s src {src} hop p{hp} r{hr} model {model} NIS {nis:6.1f} y {np.round(y * 1e3, 2)} mm "
                  f"db {np.round((x1[6:9] - x0[6:9]) * 1e3, 2)} dg {np.round((x1[18:21] - x0[18:21]) * 1e3, 2)} mm "
                  f"v {np.round(x0[3:6] * 1e3, 1)} -> {np.round(x1[3:6] * 1e3, 1)} true {np.round(vt * 1e3, 1)} mm/s")
    print("updates, position hops, rotation hops in the window:", counts)
    if dv:
        print(f"velocity error rms over the window: {np.sqrt(np.mean(np.square(dv), axis=0)) * 1e3} mm/s per axis")
    o = s["outputs"]["omc"]
    sel = (o["t_ns"] - t0 >= args.t_from * 1e9) & (o["t_ns"] - t0 <= args.t_to * 1e9) & s["valid"]["omc"]
    truth = np.stack([np.interp(o["t_ns"][sel], tg, pg[:, k]) for k in range(3)], 1)
    e = (o["p"][sel] - truth) * 1e3
    if e.size:
        print(f"raw OMC error in the window: mean {np.round(e.mean(0), 2)} sd {np.round(e.std(0), 2)} mm per axis")
    if len(e) > 2:
        scatter = np.diff(e, axis=0).std(0) / np.sqrt(2)
        print(f"OMC frame-to-frame scatter {np.round(scatter, 3)} mm per axis; the model's white std "
              f"{np.nanmedian(white) * 1e3:.3f} mm, noise scale lambda median {np.median(lams):.2f} (std x "
              f"{np.sqrt(np.median(lams)):.2f})")
    win = {}
    for m, out in s["outputs"].items():
        k = (out["t_ns"] - t0 >= args.t_from * 1e9) & (out["t_ns"] - t0 <= args.t_to * 1e9) & s["valid"][m]
        if k.any():
            win[m] = round(float(s["errors"][m][k].mean()), 3)
    print("MAE in the window [mm]:", win)
    print("task MAE [mm]:", {m: round(v, 3) for m, v in ev.result["mae_mm"].items()})


if __name__ == "__main__":
    main()
