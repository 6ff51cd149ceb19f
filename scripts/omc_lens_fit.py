"""Can the OMC's lens residual be learnt while the Vega sees the tool and carried outside? Raw-sensor check, issue 18.

The ``paper`` twin's OMC error is mostly a lens residual common to all cameras (docs/evaluation.md "The twin's two
profiles": a focal-length error ``s`` and a radial term ``k1``). Its effect on a triangulated point is not a free
field but a fixed function of the camera geometry, linear in (s, k1) to first order:

    e_omc(P) ~ s a(P) + k1 c(P),

a and c the shift of the least-squares intersection of the rays of the layout's cameras that see P
(:func:`margin.camera_visibility`: field of view, range, the layout's occluders) when every ray is bent by a unit
``s`` or ``k1`` (the model of ``sim/omc_lens.py``, back-projected through undistorted intrinsics, rays weighted
1/d^2 as the OMC's second pass). The error of the tool in ``base`` then is R_omc_base^T (e(P_tool) - e(P_base))
plus a constant (the base marker's own lens and extrinsic error). Two numbers instead of the nine of a gradient:
if they could be learnt in BVV, the error outside BVV would be predicted from the geometry alone.

Per bag (raw OMC error against the Diana truth, ``raw_sensor_stats.bag_rows``, no filter): the error on the samples
within the Vega's sightings is fitted (a) as a constant and (b) as a constant + s a + k1 c by least squares, and
each predicts the samples before and after that span; (c) uses the constant fitted with the profile's *true* lens
residual (simulator truth from ``profile_<name>.yaml``: an upper bound of what a separate OMC intrinsic calibration
could give, not something a filter knows); (d) is (b) with a prior, s ~ N(0, 0.01^2), k1 ~ N(0, 0.05^2), the
span's samples counted as span / 3 s independent ones of 1 mm per axis (the error decorrelates over ~3 s; what the
two terms leave is the hops of the per-camera error). Printed: fitted s and k1 (without, with prior), and the mean
error norm [mm] raw / (a) const / (b) lens / (d) prior / (c) true per phase; at the end the means over all
bag-phases. Only the "after" phases matter to a causal filter (it cannot use the Vega before it sees the tool).

Run: python scripts/omc_lens_fit.py bags/paper [more bag directories ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import yaml
from raw_sensor_stats import EX, EZ, PX, PZ, T, bag_rows  # this directory: the same rows, from the node's chain

from fullperc_eval.bag.calibration import load_calibration
from fullperc_eval.sim.omc_lens import LensResidual
from fullperc_eval.sim.omc_model import triangulate
from fullperc_fusion.margin.layout import default_layout_path, load_layout
from fullperc_fusion.margin.view_margin import camera_visibility

EPS = 1e-4
KEYS = ("raw", "const", "lens", "prior", "true")
SYS_TIME = 3.0                          # [s] the raw OMC error's correlation time (FullpercParams.sys_time)
RESID_STD = 1.0e-3                      # [m] what the two terms leave per axis: the hops of the per-camera error
PRIOR_STD = np.array([0.01, 0.05])      # s, k1: what a wand calibration that passed its checks can leave


def lens_point(layout, P: np.ndarray, s: float, k1: float, see: np.ndarray) -> np.ndarray:
    """Where the layout's cameras that ``see`` the points P (N, 3) [omc] put them when each image point is moved by
    a lens residual (s, k1) and back-projected through the undistorted model."""
    C, R = layout.cam_pos, layout.cam_R
    d = P[:, None, :] - C[None]
    pc = np.einsum("nkj,kji->nki", d, R)
    x, y = pc[..., 0] / pc[..., 2], pc[..., 1] / pc[..., 2]
    xr, yr = LensResidual(focal_scale=s, k1=k1).distort(x, y)
    dw = np.einsum("kij,nkj->nki", R, np.stack([xr, yr, np.ones_like(x)], axis=-1))
    dw /= np.linalg.norm(dw, axis=-1, keepdims=True)
    return triangulate(C, dw, see, weights=1.0 / np.einsum("nki,nki->nk", d, d))[0]


def lens_regressors(layout, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a(P), c(P) (N, 3): the shift per unit s and per unit k1 (finite differences at EPS)."""
    see, _ = camera_visibility(layout, P)
    X0 = lens_point(layout, P, 0.0, 0.0, see)
    return (lens_point(layout, P, EPS, 0.0, see) - X0) / EPS, (lens_point(layout, P, 0.0, EPS, see) - X0) / EPS


def true_lens(bag: Path) -> tuple[float, float] | None:
    """The simulator's lens residual of the profile named in the bag's calibration.yaml ``source`` line."""
    src = str(yaml.safe_load((bag / "calibration.yaml").read_text()).get("source", ""))
    for name in ("paper", "spec"):
        if f"profile {name}" in src:
            cfg = Path(__file__).resolve().parents[1] / "src/fullperc_eval/config" / f"profile_{name}.yaml"
            lr = LensResidual.from_config(
                ((yaml.safe_load(cfg.read_text()).get("overrides") or {}).get("omc") or {}).get("lens_residual"))
            return (lr.focal_scale, lr.k1) if lr is not None else (0.0, 0.0)
    return None


def _mae(err: np.ndarray) -> float:
    return float(np.linalg.norm(err, axis=1).mean() * 1e3)


def main(roots: list[Path]) -> None:
    layout = load_layout(default_layout_path())
    print(f"{'bag':16s} {'s':>8s} {'k1':>8s} {'s prior':>8s} {'k1 prior':>8s}  phase: {' '.join(KEYS)} [mm]")
    totals: dict[str, list[float]] = {k: [] for k in KEYS}
    for root in roots:
        for bag in sorted(p for p in root.iterdir() if (p / "metadata.yaml").exists()):
            g, o = bag_rows(bag, layout)
            cal = load_calibration(bag)
            if len(o) == 0 or cal.T_omc_base is None:
                continue
            t, e, p = g[:, T], g[:, EX:EZ + 1], g[:, PX:PZ + 1]
            R, t0 = cal.T_omc_base[:3, :3], cal.T_omc_base[:3, 3]
            a, c = lens_regressors(layout, p @ R.T + t0)
            ab, cb = lens_regressors(layout, t0[None])
            La, Lc = (a - ab) @ R, (c - cb) @ R          # R^T (a(P) - a(P_base)) per row
            ok = np.isfinite(La).all(axis=1) & np.isfinite(Lc).all(axis=1)
            span = (o[:, T].min(), o[:, T].max())
            inb = (t >= span[0]) & (t <= span[1]) & ok
            n = int(inb.sum())
            A = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), np.stack([La[inb], Lc[inb]], -1)], -1)
            A2, y2 = A.reshape(-1, 5), e[inb].reshape(-1)
            coef, *_ = np.linalg.lstsq(A2, y2, rcond=None)
            # (d) the same with a prior: the samples are not independent (the error decorrelates over SYS_TIME), so
            # the span counts as span / SYS_TIME samples of RESID_STD; s, k1 ~ N(0, PRIOR_STD^2)
            w = (np.ptp(t[inb]) / SYS_TIME) / n / RESID_STD**2
            prec = np.diag([0.0, 0.0, 0.0, *(1.0 / np.square(PRIOR_STD))])
            coef_p = np.linalg.solve(w * A2.T @ A2 + prec, w * A2.T @ y2)
            truth = true_lens(bag)
            lt = (truth[0] * La + truth[1] * Lc) if truth else np.zeros_like(La)
            b_true = (e[inb] - lt[inb]).mean(axis=0)
            line = f"{root.name[-8:]}/{bag.name:7s} {coef[3]:+8.4f} {coef[4]:+8.4f} {coef_p[3]:+8.4f} {coef_p[4]:+8.4f}"
            for phase, sel in (("before", (t < span[0]) & ok), ("after", (t > span[1]) & ok)):
                if sel.sum() < 20:
                    continue
                pred = {"raw": 0.0, "const": e[inb].mean(axis=0),
                        "lens": coef[:3] + La[sel] * coef[3] + Lc[sel] * coef[4],
                        "prior": coef_p[:3] + La[sel] * coef_p[3] + Lc[sel] * coef_p[4], "true": b_true + lt[sel]}
                vals = {k: _mae(e[sel] - v) for k, v in pred.items()}
                for k, v in vals.items():
                    totals[k].append(v)
                line += f" {phase}: " + " ".join(f"{vals[k]:5.2f}" for k in KEYS)
            print(line)
    print(f"mean over {len(totals['raw'])} bag-phases: "
          + ", ".join(f"{k} {np.mean(v):.2f} mm" for k, v in totals.items()))


if __name__ == "__main__":
    main([Path(a) for a in (sys.argv[1:] or ["bags/paper"])])
