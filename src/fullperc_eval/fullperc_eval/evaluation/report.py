"""Report of one evaluated bag: PNG plots and an HTML page (matplotlib, Agg backend, no display needed).

Files written into the output directory:

* ``trajectory.png`` -- x, y, z of the target in ``base`` over time: ground truth, raw OMC, CBKF, with the
  true path's region (BVV / GVV / PVV from the margin model) shaded in the background;
* ``errors.png``     -- position error [mm] of every method over time, same shading, the B->P segment marked;
* ``box_b_to_p.png`` -- the paper's Figure 9: box plot of each method's errors in the B->P segment
  (whiskers at 1.5 IQR, outliers shown), only when the path has such a segment;
* ``index.html``     -- Table 1 row, Table 2, MAE by region, the segments, warnings and the configuration.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from fullperc_common.runs import runs

from .config import METHODS

REGION_COLORS = {1: ("#2ca02c", "BVV"), 2: ("#1f77b4", "GVV"), 3: ("#d62728", "PVV")}
# (colour, legend name) per method, in the order of METHODS (omc, kf, bkf, ckf, cbkf)
METHOD_STYLE = {m: (c, m.upper()) for m, c in zip(
    METHODS, ("#7f7f7f", "#ff7f0e", "#bcbd22", "#17becf", "#9467bd"), strict=True)}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _shade(ax, t_s: np.ndarray, labels: np.ndarray) -> None:
    for lab, a, b in runs(labels):
        color, _ = REGION_COLORS.get(lab, ("#ffffff", "?"))
        t1 = t_s[b + 1] if b + 1 < len(t_s) else t_s[b]
        ax.axvspan(t_s[a], t1, color=color, alpha=0.12, lw=0)


def _region_legend(ax) -> None:
    from matplotlib.patches import Patch

    handles, names = ax.get_legend_handles_labels()
    handles += [Patch(color=c, alpha=0.25) for c, _ in REGION_COLORS.values()]
    names += [n for _, n in REGION_COLORS.values()]
    ax.legend(handles, names, loc="upper right", fontsize=7, ncol=2)


def plot_trajectory(ev, path: Path) -> Path:
    plt = _plt()
    s = ev.series
    t0 = int(s["grid_t_ns"][0])
    tg = (s["grid_t_ns"] - t0) * 1e-9
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    for k, ax in enumerate(axes):
        _shade(ax, tg, s["labels"])
        ax.plot(tg, s["grid_p"][:, k], color="k", lw=1.2, label="truth (Diana FK)")
        for m, kw in (("omc", {"ls": "none", "marker": ".", "ms": 1.5}), ("cbkf", {"lw": 0.9})):
            if m in s["outputs"]:
                o = s["outputs"][m]
                color, name = METHOD_STYLE[m]
                ax.plot((o["t_ns"] - t0) * 1e-9, o["p"][:, k], color=color, label=name, **kw)
        ax.set_ylabel(f"{'xyz'[k]} in base [m]")
        ax.grid(alpha=0.3)
    _region_legend(axes[0])
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{ev.result['task']}: target position (regions of the true path: {ev.result['regions']['order']})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_errors(ev, path: Path) -> Path:
    plt = _plt()
    s = ev.series
    t0 = int(s["grid_t_ns"][0])
    tg = (s["grid_t_ns"] - t0) * 1e-9
    fig, ax = plt.subplots(figsize=(10, 4.5))
    _shade(ax, tg, s["labels"])
    for m in s["methods"]:
        o, e, ok = s["outputs"][m], s["errors"][m], s["valid"][m]
        color, name = METHOD_STYLE.get(m, ("k", m))
        ax.plot((o["t_ns"][ok] - t0) * 1e-9, e[ok], color=color, lw=0.8, label=f"{name} ({ev.result['mae_mm'][m]:.2f})"
                if ev.result["mae_mm"][m] is not None else name)
    bp = ev.result.get("b_to_p")
    if bp:
        for x in (bp["t0_s"], bp["t1_s"]):
            ax.axvline(x, color="k", ls="--", lw=0.8)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [mm]")
    ax.grid(alpha=0.3)
    _region_legend(ax)
    ax.set_title(f"{ev.result['task']}: error per method (legend: MAE [mm]); dashed: B->P segment")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_box(ev, path: Path) -> Path | None:
    s = ev.series
    i = s["b_to_p_index"]
    if i is None:
        return None
    plt = _plt()
    data = [s["seg_errors"][i][m] for m in s["methods"]]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.boxplot(data, whis=1.5, showfliers=True, flierprops={"markersize": 2})
    ax.set_xticks(range(1, len(data) + 1), [METHOD_STYLE.get(m, ("", m))[1] for m in s["methods"]])
    ax.set_ylabel("position error [mm]")
    ax.grid(alpha=0.3, axis="y")
    bp = ev.result["b_to_p"]
    ax.set_title(f"{ev.result['task']}: errors entering PVV from BVV ({bp['t0_s']:.1f}-{bp['t1_s']:.1f} s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _cell(v: Any) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, float):
        return f"{v:.2f}"
    return html.escape(str(v))


def _table(rows: list[list[Any]], head: list[str]) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in head)
    b = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{b}</table>"


def render_html(ev, images: list[str]) -> str:
    r = ev.result
    ms = list(r["mae_mm"])
    names = [METHOD_STYLE.get(m, ("", m))[1] for m in ms]
    parts = [f"<h1>fullperc evaluation: {html.escape(r['task'])}</h1>",
             f"<p>bag <code>{html.escape(r['bag'])}</code>, {r['duration_s']:.1f} s, {r['messages']} messages read; "
             f"regions of the true path: <b>{html.escape(r['regions']['order'])}</b>; calibration: "
             f"{html.escape(r['calibration_source'] or '-')}</p>",
             "<h2>Table 1: MAE [mm]</h2>",
             _table([["every output"] + [r["mae_mm"][m] for m in ms],
                     [f"common stamps ({r['common_stamps']})"] + [r["mae_common_mm"][m] for m in ms],
                     ["RMSE"] + [r["rmse_mm"][m] for m in ms], ["max"] + [r["max_mm"][m] for m in ms],
                     ["outputs"] + [r["outputs"][m] for m in ms]], [""] + names),
             "<h2>Table 2: B&rarr;P segment [mm]</h2>"]
    bp = r.get("b_to_p")
    if bp:
        parts.append(f"<p>{bp['t0_s']:.2f}&ndash;{bp['t1_s']:.2f} s (from the last BVV sample to the end of the "
                     "following PVV run)</p>")
        parts.append(_table([["max"] + [bp["max_mm"][m] for m in ms], ["median"] + [bp["median_mm"][m] for m in ms],
                             ["n"] + [bp["n"][m] for m in ms]], [""] + names))
    else:
        parts.append("<p>This path has no BVV run directly followed by a PVV run.</p>")
    parts.append("<h2>MAE by region of the true path [mm]</h2>")
    parts.append(_table([[k] + [v[m] for m in ms] for k, v in r["mae_by_region_mm"].items()], ["region"] + names))
    parts.append("<h2>Segments (last sample of a run to the end of the next run): median error [mm]</h2>")
    parts.append(_table([[f"{s['from']}&rarr;{s['to']}".replace("&rarr;", "->"), f"{s['t0_s']:.2f}-{s['t1_s']:.2f}"]
                         + [s["stats_mm"][m]["median"] for m in ms] for s in r["segments"]], ["segment", "time [s]"]
                        + names))
    for img in images:
        parts.append(f'<p><img src="{html.escape(img)}" alt="{html.escape(img)}" style="max-width:100%"></p>')
    if r["warnings"]:
        parts.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in r["warnings"]) + "</ul>")
    cfg = r.get("config", {})
    parts.append("<h2>Configuration</h2><pre>" + html.escape("\n".join(f"{k}: {v}" for k, v in cfg.items()))
                 + "</pre>")
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(r['task'])}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")


def write_report(ev, out_dir: str | Path) -> Path:
    """Write the plots and index.html of one evaluation into ``out_dir``; returns the HTML path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [plot_trajectory(ev, out / "trajectory.png").name, plot_errors(ev, out / "errors.png").name]
    box = plot_box(ev, out / "box_b_to_p.png")
    if box is not None:
        images.append(box.name)
    index = out / "index.html"
    index.write_text(render_html(ev, images))
    return index
