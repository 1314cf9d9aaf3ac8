"""The run report's comparison with an earlier run: the difference map, its colour scale and
the sorted per-cell change plot."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from falsify.reports.charts import (
    PUOR,
    Grid,
    axes_svg,
    cells_svg,
    diverging,
    num,
    svg_element,
)
from falsify.reports.page import esc
from falsify.results.miou_maps import CellMap, axis_texts
from falsify.results.miou_maps import compare as compare_maps
from falsify.results.store import RunData


def compare_section(before: RunData, after: RunData, after_map: CellMap,
                    threshold: float, ascending: bool = False,
                    differences: tuple[str, ...] = ()) -> str:
    """The difference map (after − before) and the paper's sorted per-cell change plot
    (ascending, as the paper draws it, when `ascending`); `differences`, what else differs
    between the runs' spaces, stands above them as a warning."""
    bmap = before.cell_map()
    bidx = {(float(x), float(y)): (i, j) for j, y in enumerate(bmap.b_values)
            for i, x in enumerate(bmap.a_values)}
    diff = np.full(after_map.miou.shape, np.nan)
    prev = np.full(after_map.miou.shape, np.nan)
    for j, y in enumerate(after_map.b_values):
        for i, x in enumerate(after_map.a_values):
            hit = bidx.get((float(x), float(y)))
            if hit is not None:
                prev[j, i] = bmap.miou[hit[1], hit[0]]
                diff[j, i] = after_map.miou[j, i] - prev[j, i]
    finite = diff[~np.isnan(diff)]
    span = max(0.1, math.ceil(float(np.abs(finite).max()) * 10) / 10) if finite.size else 0.1
    grid = Grid.sized(after_map.a_values, after_map.b_values, 480, 430, left=52, top=8)

    def tip(i: int, j: int) -> str:
        where = f"x = {grid.x_text(i)} m, y = {grid.y_text(j)} m"
        if np.isnan(diff[j, i]):
            return f"{where}\nnot scored in both runs"
        return (f"{where}\nmIoU {prev[j, i]:.3f} → {after_map.miou[j, i]:.3f} "
                f"({diff[j, i]:+.3f})")

    show = grid.cw >= 34 and grid.ch >= 14
    body = cells_svg(grid, diff, lambda v: diverging(v, span), tip, "dcell",
                     label=(lambda i, j: f"{diff[j, i]:+.3f}") if show else None,
                     present=np.isfinite(diff), absent="not scored in both runs")
    diff_svg = svg_element(body + axes_svg(grid), grid.left + grid.width + 8,
                    grid.top + grid.height + 60, "map", "diffmap", "mIoU difference map")
    legend = diverging_legend(span)

    table = compare_maps(bmap, after_map)
    if ascending:
        table = table.iloc[::-1].reset_index(drop=True)
    changes = table["change"].to_numpy(dtype=float)
    plot = improvement_svg(table, span)
    before_blind = {(float(x), float(y)) for x, y in _blind_keys(bmap, threshold)}
    after_blind = {(float(x), float(y)) for x, y in _blind_keys(after_map, threshold)}
    fixed, new = len(before_blind - after_blind), len(after_blind - before_blind)
    mean = f"{float(changes.mean()):+.3f}" if changes.size else "—"
    meta = before.meta
    warning = "" if not differences else (
        '<p class="warn" id="compare-differs"><b>The two runs are of different spaces:</b> '
        "the change below mixes the network's with the scenes'.</p><ul class=\"warn\">"
        + "".join(f"<li>{esc(d)}</li>" for d in differences) + "</ul>")
    only = len(after_map.a_values) * len(after_map.b_values) - changes.size
    return f"""
<section id="compare-section">
<h2>Comparison with the run before</h2>
{warning}
<p class="note">Before: {esc(before.path)} (model {esc(meta.get("model_name", "?"))}
{esc(str(meta.get("model_hash") or "")[:12])}, config {esc(meta.get("space_name", "?"))}).
Over the {changes.size} cells scored in both runs (this run's other {only} are not) the mIoU
changed by {mean} on average:
{int((changes > 0).sum())} improved, {int((changes < 0).sum())} got worse. Blind spots
{len(before_blind)} → {len(after_blind)} ({fixed} fixed, {new} new).</p>
<div class="row">
<figure><figcaption>Difference map (after − before)</figcaption>{diff_svg}</figure>
<figure>{legend}</figure>
<figure><figcaption>Per-cell change, sorted {"ascending" if ascending else "descending"}
(the paper's improvement plot)</figcaption>
{plot}</figure>
</div>
</section>"""


def _blind_keys(cmap: CellMap, threshold: float) -> list[tuple]:
    return [(c.a, c.b) for c in cmap.blind_spots(threshold)]


def diverging_legend(span: float) -> str:
    top, h, x0 = 20, 240, 8
    stops = "".join(f'<rect x="{x0}" y="{num(top + h * k / 40)}" width="16" '
                    f'height="{num(h / 40 + 0.5)}" fill="{diverging(span * (1 - k / 20), span)}"/>'
                    for k in range(40))
    ticks = "".join(f'<text x="{x0 + 24}" y="{num(top + h * (1 - (v / span + 1) / 2) + 4)}">'
                    f"{v:+.2f}</text>" for v in (-span, -span / 2, 0.0, span / 2, span))
    body = (f'<text x="{x0}" y="{top - 8}" class="axis">change</text>{stops}'
            f'<rect x="{x0}" y="{top}" width="16" height="{h}" fill="none" stroke="#888"/>'
            f"{ticks}"
            f'<text x="{x0}" y="{top + h + 18}">purple: better</text>'
            f'<text x="{x0}" y="{top + h + 34}">orange: worse</text>')
    return svg_element(body, 120, top + h + 44, "legend", "", "difference colour scale")


def improvement_svg(table: pd.DataFrame, span: float) -> str:
    """Bars of per-cell change, sorted from most improved to most worsened."""
    w, h, left, top, bottom = 440, 260, 46, 12, 40
    pw, ph = w - left - 12, h - top - bottom
    n = len(table)

    def sy(v: float) -> float:
        return top + ph / 2 - v / span * ph / 2

    out = [f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" class="frame"/>']
    for v in (-span, -span / 2, 0.0, span / 2, span):
        out.append(f'<line class="grid" x1="{left}" x2="{left + pw}" y1="{num(sy(v))}" '
                   f'y2="{num(sy(v))}"/><text x="{left - 6}" y="{num(sy(v) + 4)}" '
                   f'text-anchor="end">{v:+.2f}</text>')
    bw = pw / max(1, n)
    xs, ys = axis_texts(table["x"]), axis_texts(table["y"])
    for k, row in enumerate(table.itertuples(index=False)):
        c = float(row.change)
        y0, y1 = sorted((sy(0.0), sy(c)))
        text = (f"x = {xs[row.x]}, y = {ys[row.y]}: {row.miou_before:.3f} → "
                f"{row.miou_after:.3f} ({c:+.3f})")
        out.append(f'<rect class="bar" x="{num(left + k * bw)}" y="{num(y0)}" '
                   f'width="{num(max(bw - 0.4, 0.6))}" height="{num(max(y1 - y0, 0.5))}" '
                   f'fill="{PUOR[-2] if c >= 0 else PUOR[1]}">'
                   f"<title>{esc(text)}</title></rect>")
    out.append(f'<line x1="{left}" x2="{left + pw}" y1="{num(sy(0))}" y2="{num(sy(0))}" '
               'stroke="#333"/>')
    out.append(f'<text x="{left + pw / 2}" y="{h - 6}" text-anchor="middle" class="axis">'
               f"{n} cells, sorted by change</text>")
    return svg_element("".join(out), w, h, "plot", "improvement", "sorted per-cell improvement")
