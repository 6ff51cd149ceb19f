"""Can a position-dependent OMC bias learnt in BVV be carried outside it? A raw-sensor check (issue 18).

``fullperc`` and CBKF learn the OMC's error while the Vega sees the tool (BVV) and carry it out of BVV as a constant
(CBKF) or fading (fullperc) bias. On the ``paper`` twin the OMC's error is a smooth function of position (the lens
residual, docs/evaluation.md "The twin's two profiles"), so a bias that is linear in position might carry further.
This script
asks the sensor data, not a filter: per bag, the raw OMC position error (the node's own frame chain against the Diana
forward kinematics: ``scripts/raw_sensor_stats.py``'s rows) on the samples stamped within the Vega's sightings is fitted
two ways -- a constant b, and b + J (x - x_mean) by least squares -- and each is used to predict the error of the OMC
samples before and after that span. Printed per bag and phase: the mean error norm [mm] raw, after subtracting the
constant, after subtracting the linear model, and the span of the fitting positions [mm].

Run: python scripts/omc_bias_extrapolation.py bags/paper
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from raw_sensor_stats import EX, EZ, PX, PZ, T, bag_rows  # this directory: the same rows, from the node's chain

from fullperc_fusion.margin.layout import default_layout_path, load_layout


def _mae(err: np.ndarray) -> float:
    return float(np.linalg.norm(err, axis=1).mean() * 1e3)


def main(root: Path) -> None:
    print(f"{'bag':8s} {'phase':6s} {'raw':>5s} {'const':>6s} {'linear':>6s}  positions spanned in BVV [mm]")
    layout = load_layout(default_layout_path())
    for bag in sorted(p for p in root.iterdir() if (p / "metadata.yaml").exists()):
        g, o = bag_rows(bag, layout)
        if len(o) == 0:
            continue
        t, e, x = g[:, T], g[:, EX:EZ + 1], g[:, PX:PZ + 1]
        span = (o[:, T].min(), o[:, T].max())
        inb = (t >= span[0]) & (t <= span[1])
        xm = x[inb].mean(axis=0)
        A = np.column_stack([np.ones(inb.sum()), x[inb] - xm])
        coef, *_ = np.linalg.lstsq(A, e[inb], rcond=None)
        b = e[inb].mean(axis=0)
        for phase, sel in (("before", t < span[0]), ("after", t > span[1])):
            if not sel.any():
                continue
            lin = np.column_stack([np.ones(sel.sum()), x[sel] - xm]) @ coef
            raw, const, linear = (_mae(e[sel] - pred) for pred in (0.0, b, lin))
            print(f"{bag.name:8s} {phase:6s} {raw:5.2f} {const:6.2f} {linear:6.2f}  "
                  f"{np.round(np.ptp(x[inb], axis=0) * 1e3).astype(int).tolist()}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "bags/paper"))
