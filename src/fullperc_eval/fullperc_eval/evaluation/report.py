"""Report of one evaluated bag: PNG plots and an HTML page (matplotlib, Agg backend, no display needed).

Files written into the output directory:

* ``trajectory.png``  -- x, y, z of the target in ``base`` over time: ground truth and every method, with the
  true path's region (BVV / GVV / PVV from the margin model) shaded in the background;
* ``errors.png``      -- position error [mm] of every method over time, same shading, the B->P segment marked;
* ``orientation.png`` -- orientation error [deg] of every method and of the raw local chain (LOCAL);
* ``box_b_to_p.png``  -- the paper's Figure 9: box plot of each method's errors in the B->P segment
  (whiskers at 1.5 IQR, outliers shown), only when the path has such a segment;
* ``index.html``      -- the headline paragraph (:mod:`.headline`), the region definitions with the margin threshold
  the labels were made with, Table 1 (position and orientation), Table 2, MAE by region, NEES, the segments,
  warnings and the configuration; numbers right-aligned in their columns.

Every method has its own colour, line style and marker (:func:`method_style`): KF and BKF, CKF and CBKF often
give the same curve to a few micrometres, and with colour alone the one drawn last hides the other. The markers
of different methods sit at staggered samples, so two identical curves still show both markers.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from fullperc_common.runs import runs

from .config import METHODS
from .headline import REGION_ORDER, headline, region_definitions

REGION_COLORS = {1: ("#2ca02c", "BVV"), 2: ("#1f77b4", "GVV"), 3: ("#d62728", "PVV")}
# colour, line style, marker per series: the paper's five, the fullperc filter, the raw local chain; any other
# method gets the next unused combination of _CYCLE (method_style), so a newly registered filter is drawn too
_STYLES = {"omc": ("#7f7f7f", "none", "."), "kf": ("#ff7f0e", "-", "o"), "bkf": ("#bcbd22", "--", "s"),
           "ckf": ("#17becf", "-", "^"), "cbkf": ("#9467bd", "--", "v"), "fullperc": ("#d62728", "-", "D"),
           "local": ("#8c564b", "none", "x")}
_CYCLE = [(c, ls, mk) for c in ("#e377c2", "#1f77b4", "#2ca02c", "#000000") for ls in ("-.", ":")
          for mk in ("P", "*", "h")]
MARKERS_PER_LINE = 12   # markers along each curve, staggered per method
LINE_STEP = 0.5         # [pt] each series drawn this much wider than the one drawn after it


def method_style(m: str, order: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """Matplotlib keyword arguments (color, ls, marker, label) of series ``m``; ``order``: every series drawn,
    for a unique fallback style of a method not in the table above."""
    if m in _STYLES:
        c, ls, mk = _STYLES[m]
    else:
        others = [x for x in dict.fromkeys([*order, m]) if x not in _STYLES]
        c, ls, mk = _CYCLE[others.index(m) % len(_CYCLE)]
    return {"color": c, "ls": ls, "marker": mk, "label": m.upper()}


# kept for callers of the former (colour, name) table
METHOD_STYLE = {m: (method_style(m)["color"], m.upper()) for m in (*METHODS, "local")}


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


def _line(ax, x: np.ndarray, y: np.ndarray, m: str, order, i: int, label: str | None = None):
    """One series in its style. Not overdrawn: the i-th of ``order`` is drawn LINE_STEP wider than the next one,
    so curves that coincide show as nested stripes of their colours; markers every len/MARKERS_PER_LINE samples,
    starting at a per-series phase so that coinciding curves still show every marker."""
    st = method_style(m, order)
    n = len(x)
    every = max(1, n // MARKERS_PER_LINE)
    kw = {"color": st["color"], "ls": st["ls"], "marker": st["marker"], "label": label or st["label"],
          "lw": 0.8 + LINE_STEP * (len(order) - 1 - i), "ms": 4, "mfc": "none",
          "markevery": (min(n - 1, (i * every) // max(1, len(order))) if n else 0, every)}
    if st["ls"] == "none":      # a scatter-like series (raw sources): small dots everywhere, its marker on top
        kw.update(markevery=None, ms=2)
    return ax.plot(x, y, **kw)[0]


def error_lines(ax, ev) -> list:
    """Draw every method's position error over time on ``ax``; returns the lines (one per method)."""
    s = ev.series
    t0 = int(s["grid_t_ns"][0])
    lines = []
    for i, m in enumerate(s["methods"]):
        o, e, ok = s["outputs"][m], s["errors"][m], s["valid"][m]
        mae = ev.result["mae_mm"][m]
        lines.append(_line(ax, (o["t_ns"][ok] - t0) * 1e-9, e[ok], m, s["methods"], i,
                           f"{m.upper()} ({mae:.2f})" if mae is not None else m.upper()))
    return lines


def orientation_lines(ax, ev) -> list:
    """Draw every method's orientation error and the raw local chain's on ``ax``; returns the lines."""
    s = ev.series
    t0 = int(s["grid_t_ns"][0])
    oe = s.get("orientation_errors") or {}
    series = list(oe)
    lines = []
    for i, m in enumerate(series):
        t_ns = s["single_sources"]["local"]["t_ns"] if m == "local" else s["outputs"][m]["t_ns"]
        ok = np.isfinite(oe[m])
        mae = ev.result["orientation_mae_deg"].get(m)
        lines.append(_line(ax, (t_ns[ok] - t0) * 1e-9, oe[m][ok], m, series, i,
                           f"{m.upper()} ({mae:.3f})" if mae is not None else m.upper()))
    return lines


def plot_orientation(ev, path: Path) -> Path | None:
    if not ev.series.get("orientation_errors"):
        return None
    plt = _plt()
    s = ev.series
    tg = (s["grid_t_ns"] - int(s["grid_t_ns"][0])) * 1e-9
    fig, ax = plt.subplots(figsize=(10, 4.5))
    _shade(ax, tg, s["labels"])
    orientation_lines(ax, ev)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("orientation error [deg]")
    ax.grid(alpha=0.3)
    _region_legend(ax)
    ax.set_title(f"{ev.result['task']}: orientation error, angle of R_true^T R_est (legend: MAE [deg])")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_trajectory(ev, path: Path) -> Path:
    plt = _plt()
    s = ev.series
    t0 = int(s["grid_t_ns"][0])
    tg = (s["grid_t_ns"] - t0) * 1e-9
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    for k, ax in enumerate(axes):
        _shade(ax, tg, s["labels"])
        ax.plot(tg, s["grid_p"][:, k], color="k", lw=1.2, label="truth (Diana FK)")
        for i, m in enumerate(s["methods"]):
            o = s["outputs"][m]
            _line(ax, (o["t_ns"] - t0) * 1e-9, o["p"][:, k], m, s["methods"], i)
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
    error_lines(ax, ev)
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
    ax.set_xticks(range(1, len(data) + 1), [m.upper() for m in s["methods"]])
    ax.set_ylabel("position error [mm]")
    ax.grid(alpha=0.3, axis="y")
    bp = ev.result["b_to_p"]
    ax.set_title(f"{ev.result['task']}: errors entering PVV from BVV ({bp['t0_s']:.1f}-{bp['t1_s']:.1f} s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


class Num(str):
    """A pre-formatted figure (e.g. a NEES cell ``97%/3.1``): right-aligned like a number."""


def _cell(v: Any, digits: int = 2) -> tuple[str, bool]:
    """(HTML, is a figure) of one cell: figures are right-aligned, labels left (CSS classes num / lbl)."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "&ndash;", True
    if isinstance(v, bool):
        return ("yes" if v else "no"), False
    if isinstance(v, float | np.floating):
        return f"{v:.{digits}f}", True
    if isinstance(v, int | np.integer):
        return str(v), True
    return html.escape(str(v)), isinstance(v, Num)


def _table(rows: list[list[Any]], head: list[str], digits: int = 2) -> str:
    """An HTML table: the first column a left-aligned label, every figure right-aligned (class ``num``)."""
    h = "".join(f"<th class='{'lbl' if i == 0 else 'num'}'>{html.escape(x)}</th>" for i, x in enumerate(head))
    body = []
    for r in rows:
        cells = []
        for c in r:
            text, num = _cell(c, digits)
            cells.append(f"<td class='{'num' if num else 'lbl'}'>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{h}</tr>{''.join(body)}</table>"


def _nees_rows(r: dict[str, Any], ms: list[str]) -> list[list[Any]]:
    rows = []
    for kind, dof in (("position", 3), ("pose", 6)):
        per = {m: (r.get("nees", {}).get(m) or {}).get(kind) or {} for m in ms}
        if not any(v.get("n") for v in per.values()):
            continue
        b = next(v["bound"] for v in per.values() if v.get("bound") is not None)
        rows.append([f"{kind} (dof {dof}): share <= {b:.2f} [%]"]
                    + [100.0 * v["share_95"] if v.get("n") else None for v in per.values()])
        rows.append([f"{kind} (dof {dof}): mean NEES"] + [v.get("mean") for v in per.values()])
    return rows


def render_html(ev, images: list[str]) -> str:
    r = ev.result
    ms = list(r["mae_mm"])
    names = [m.upper() for m in ms]
    reg = r["regions"]
    cfg = r.get("config", {})
    parts = [f"<h1>fullperc evaluation: {html.escape(r['task'])}</h1>",
             f"<p class='headline'>{html.escape(headline(r, str(r.get('target') or 'tool')))}</p>",
             f"<p>bag <code>{html.escape(r['bag'])}</code>, {r['duration_s']:.1f} s, {r['messages']} messages read; "
             f"regions of the true path: <b>{html.escape(reg['order'])}</b>; calibration: "
             f"{html.escape(r['calibration_source'] or '-')}</p>"]
    if reg.get("threshold_deg") is not None:
        defs = region_definitions(reg["threshold_deg"])
        parts.append("<h2>Regions</h2><dl>" + "".join(
            f"<dt><b>{k}</b> ({(reg.get('seconds') or {}).get(k, 0.0):.1f} s in this run)</dt>"
            f"<dd>{html.escape(defs[k])}</dd>" for k in REGION_ORDER) + "</dl>"
            f"<p>View margin: the paper's Algorithm 1, summed over the OMC camera pairs that see the point; threshold "
            f"{reg['threshold_deg']:g} deg from the layout <code>{html.escape(str(cfg.get('layout', '')))}</code>. "
            "Labels are of the true path.</p>")
    parts += ["<h2>Table 1: MAE [mm]</h2>",
              _table([["every output"] + [r["mae_mm"][m] for m in ms],
                      [f"common stamps ({r['common_stamps']})"] + [r["mae_common_mm"][m] for m in ms],
                      ["RMSE"] + [r["rmse_mm"][m] for m in ms], ["max"] + [r["max_mm"][m] for m in ms],
                      ["outputs"] + [r["outputs"][m] for m in ms]], [""] + names)]
    ori = r.get("orientation_mae_deg") or {}
    if ori:
        cols = list(ori)
        parts += ["<h2>Table 1b: orientation error [deg] (angle of R<sub>true</sub><sup>T</sup> R<sub>est</sub>; "
                  "LOCAL = the raw Vega chain mapped into base)</h2>",
                  _table([["MAE"] + [ori[m] for m in cols],
                          ["p95"] + [(r.get("orientation_p95_deg") or {}).get(m) for m in cols]]
                         + [[f"MAE in {k}"] + [v.get(m) for m in cols]
                            for k, v in (r.get("orientation_by_region_deg") or {}).items()],
                         [""] + [m.upper() for m in cols], digits=3)]
    nees_rows = _nees_rows(r, ms)
    if nees_rows:
        parts += ["<h2>Covariance consistency (NEES)</h2><p>NEES = e<sup>T</sup> C<sup>-1</sup> e of each output's "
                  "true error e and reported covariance C; an honest covariance gives 95 % of the outputs inside the "
                  "chi2 95 % bound and a mean NEES equal to the degrees of freedom. The full pose only for methods "
                  "that fuse the orientation (a copied source orientation with a fixed std is not checked).</p>",
                  _table(nees_rows, [""] + names)]
    parts.append("<h2>Table 2: B&rarr;P segment [mm]</h2>")
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
    parts.append(_table([[f"{s['from']}->{s['to']}", Num(f"{s['t0_s']:.2f}-{s['t1_s']:.2f}")]
                         + [s["stats_mm"][m]["median"] for m in ms] for s in r["segments"]], ["segment", "time [s]"]
                        + names))
    for img in images:
        parts.append(f'<p><img src="{html.escape(img)}" alt="{html.escape(img)}" style="max-width:100%"></p>')
    if r["warnings"]:
        parts.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in r["warnings"]) + "</ul>")
    parts.append("<h2>Configuration</h2><pre>" + html.escape("\n".join(f"{k}: {v}" for k, v in cfg.items()))
                 + "</pre>")
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 8px}.num{text-align:right;font-variant-numeric:tabular-nums}"
             ".lbl{text-align:left}.headline{font-size:1.1em;background:#f4f4f4;padding:8px}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(r['task'])}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")


def write_report(ev, out_dir: str | Path) -> Path:
    """Write the plots and index.html of one evaluation into ``out_dir``; returns the HTML path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [plot_trajectory(ev, out / "trajectory.png").name, plot_errors(ev, out / "errors.png").name]
    for extra in (plot_orientation(ev, out / "orientation.png"), plot_box(ev, out / "box_b_to_p.png")):
        if extra is not None:
            images.append(extra.name)
    index = out / "index.html"
    index.write_text(render_html(ev, images))
    return index
