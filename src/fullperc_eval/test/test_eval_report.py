"""The report a newcomer reads (evaluation/report.py, headline.py; issue 17 item 4).

Headline figures are recomputed here from the evaluation's own result (never typed in); the region definitions
must quote the threshold the labels were made with; every method must be drawn distinguishably; figures in the
HTML tables right-aligned.
"""

from __future__ import annotations

import re
from html import escape
from html.parser import HTMLParser

import numpy as np
import pytest

from fullperc_eval.evaluation.headline import headline, region_definitions
from fullperc_eval.evaluation.metrics import evaluate_bag
from fullperc_eval.evaluation.report import error_lines, method_style, orientation_lines, render_html, write_report
from fullperc_eval.sim.dataset import synthetic_content, write_bag

HOP_AT = 5.0


@pytest.fixture(scope="module")
def ev(tmp_path_factory):
    content, _ = synthetic_content(8.0, omc_offset=(0.003, 0.0, 0.0), omc_offset_after=(-0.002, 0.003, 0.0),
                                   t_offset_change_s=HOP_AT, ots_window_s=(0.0, 6.0), omc_noise_m=1e-4,
                                   ots_noise_m=5e-5)
    return evaluate_bag(write_bag(tmp_path_factory.mktemp("rep") / "synth", content), progress=False)


def test_headline_numbers_come_from_the_metrics(ev):
    r = ev.result
    text = headline(r)
    mae = {m: v for m, v in r["mae_mm"].items() if v is not None}
    best = min(mae, key=lambda m: mae[m])
    assert best != "omc"
    assert f"{best.upper()}, MAE {mae[best]:.2f} mm" in text
    assert f"{100 * (mae['omc'] - mae[best]) / mae['omc']:.0f} % below the raw OMC ({mae['omc']:.2f} mm)" in text
    ori = {m: v for m, v in r["orientation_mae_deg"].items() if v is not None and m != "local"}
    ob = min(ori, key=lambda m: ori[m])
    assert f"best orientation: {ob.upper()}, {ori[ob]:.3f} deg" in text
    loc = r["orientation_mae_deg"]["local"]
    assert f"the raw local chain, only where the Vega sees the tool: {loc:.3f} deg" in text
    assert len(r["omc_hops"]) == 1 and abs(r["omc_hops"][0]["t_s"] - HOP_AT) < 0.05
    h = r["omc_hops"][0]
    assert f"{h['t_s']:.1f} s ({h['jump_mm']:.1f} mm)" in text
    for k, sec in r["regions"]["seconds"].items():
        assert f"{sec:.1f} s in {k}" in text


def test_headline_says_when_no_method_beat_the_omc():
    r = {"task": "X", "duration_s": 3.0, "mae_mm": {"omc": 1.0, "cbkf": 1.5}, "omc_hops": [],
         "regions": {"order": "P", "seconds": {"BVV": 0.0, "GVV": 0.5, "PVV": 2.5}}}
    text = headline(r)
    assert "OMC, MAE 1.00 mm -- no fusion method beat the raw OMC" in text
    assert "no OMC hop" in text and "2.5 s in PVV" in text


def test_region_definitions_quote_the_threshold_used(ev):
    r = ev.result
    html = render_html(ev, [])
    thr = r["regions"]["threshold_deg"]
    defs = region_definitions(thr)
    for k in ("BVV", "GVV", "PVV"):
        assert f"<dt><b>{k}</b>" in html
        assert escape(defs[k]) in html
    assert f">= {thr:g} deg" in defs["GVV"] and f"< {thr:g} deg" in defs["PVV"]
    assert f"threshold {thr:g} deg" in html
    ev.result["regions"]["threshold_deg"] = 33.25                 # another layout, another number
    try:
        other = render_html(ev, [])
    finally:
        ev.result["regions"]["threshold_deg"] = thr
    assert "&gt;= 33.25 deg" in other and f"&gt;= {thr:g} deg" not in other   # (HTML-escaped)


def _style(line) -> tuple:
    return (line.get_color(), line.get_linestyle(), line.get_marker())


def test_every_method_has_its_own_style_and_coinciding_curves_stay_visible(ev):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(2)
    try:
        lines = error_lines(a1, ev)
        methods = ev.series["methods"]
        assert len(lines) == len(methods)
        assert len({_style(ln) for ln in lines}) == len(methods)
        widths = [ln.get_linewidth() for ln in lines]
        assert all(a > b for a, b in zip(widths, widths[1:], strict=False))   # earlier lines show around later ones
        phases = [ln.get_markevery() for ln in lines if ln.get_linestyle() != "None"]
        assert len({p for p in phases}) == len(phases)                       # markers at staggered samples
        olines = orientation_lines(a2, ev)
        assert [ln.get_label().split()[0] for ln in olines] == [m.upper() for m in ev.result["orientation_mae_deg"]]
        assert len({_style(ln) for ln in olines}) == len(olines)
    finally:
        plt.close(fig)
    names = [*methods, "local", "new_a", "new_b", "new_c"]   # filters registered later get unused styles too
    styles = [tuple(method_style(m, names)[k] for k in ("color", "ls", "marker")) for m in names]
    assert len(set(styles)) == len(names)


class _Cells(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.cells: list[tuple[str, str]] = []
        self._cls: str | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "td":
            self._cls = dict(attrs).get("class", "")
            self.cells.append((self._cls, ""))

    def handle_endtag(self, tag):
        if tag == "td":
            self._cls = None

    def handle_data(self, data):
        if self._cls is not None:
            cls, text = self.cells[-1]
            self.cells[-1] = (cls, text + data)


def test_html_figures_are_right_aligned(ev, tmp_path):
    index = write_report(ev, tmp_path)
    text = index.read_text()
    assert re.search(r"\.num\{text-align:right", text)
    p = _Cells()
    p.feed(text)
    number = re.compile(r"^(-?\d+(\.\d+)?|–|\d+%/\S+|[\d.]+-[\d.]+)$")
    assert p.cells
    for cls, cell in p.cells:
        if number.match(cell.strip()):
            assert cls == "num", (cls, cell)
        else:
            assert cls == "lbl", (cls, cell)
    for name in ("trajectory.png", "errors.png", "orientation.png"):
        assert (tmp_path / name).stat().st_size > 10_000 and name in text
    assert headline(ev.result).split(":")[0] in text
    assert "Table 1b: orientation error" in text and "Covariance consistency (NEES)" in text
    assert np.isfinite(ev.result["orientation_mae_deg"]["local"])
