"""View-margin model timings (issue 4 goals: room map <= 10 s, one point <= 50 µs on the project machine).

Figures (medians), each with a baseline measured in this run:
  * margin_map_6x5x3_2cm: the default layout (12 cameras, 5 occluders, Vega) over the 6 x 5 x 3 m room at 2 cm
    (~11.4 M points). Baseline: the float64 reference path ``compute_margin`` timed on 200 k random room points and
    scaled to the same number of points.
  * label_point: one labelled point (margin + OTS volume test) on the single-point path, median over points spread
    over the room. Baseline: ``label_points`` (the vectorized path) called with one point.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import emit, median_time  # noqa: E402

from fullperc_fusion.margin.layout import default_layout_path, load_layout  # noqa: E402
from fullperc_fusion.margin.map import compute_margin_map  # noqa: E402
from fullperc_fusion.margin.view_margin import compute_margin, label_point, label_points  # noqa: E402


def main() -> None:
    layout = load_layout(default_layout_path())
    res = 0.02

    # --- room map
    t_map = median_time(lambda: compute_margin_map(layout, res), repeats=3)
    mmap = compute_margin_map(layout, res)
    n = mmap.labels.size
    rng = np.random.default_rng(0)
    sample = rng.uniform(layout.room_min, layout.room_max, size=(200_000, 3))
    t_ref = median_time(lambda: compute_margin(layout, sample), repeats=3) * n / len(sample)
    emit("margin_map_6x5x3_2cm", t_map, "s", baseline=t_ref, points=n, shape=list(mmap.shape),
         cameras=layout.n_cameras, occluders=len(layout.occluders), goal_s=10.0,
         fractions={k: round(v, 4) for k, v in mmap.fractions().items()})

    # --- one point
    pts = rng.uniform(layout.room_min, layout.room_max, size=(200, 3))
    pts[:100] = rng.uniform([-1.0, -1.0, 0.3], [1.0, 0.3, 1.9], size=(100, 3))  # half near the table

    def per_point(fn, number=20):
        times = []
        for p in pts:
            t0 = time.perf_counter()
            for _ in range(number):
                fn(p)
            times.append((time.perf_counter() - t0) / number)
        return float(np.median(times))

    per_point(lambda p: label_point(layout, p), 5)  # warm-up (caches of triangular index sets)
    t_pt = min(per_point(lambda p: label_point(layout, p)) for _ in range(3))
    t_vec1 = min(per_point(lambda p: label_points(layout, p[None])) for _ in range(3))
    emit("label_point", t_pt * 1e6, "us", baseline=t_vec1 * 1e6, goal_us=50.0, cameras=layout.n_cameras,
         occluders=len(layout.occluders))


if __name__ == "__main__":
    main()
