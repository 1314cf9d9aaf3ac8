"""One self-contained HTML report of a run: summary, mIoU heat map, worst samples, comparisons.

Everything is inline (CSS, JS, SVG, PNG previews as data: URIs) and a Content-Security-Policy
forbids any fetch, so the file opens offline and leaks nothing. Output bytes depend only on the
run (and the compared run): no render time, sorted data, fixed number formats.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from falsify.reports.charts import (
    BLIND_STROKE,
    FONT,
    PUOR,
    VIRIDIS,
    Grid,
    axes_svg,
    cells_svg,
    diverging,
    f3,
    legend_svg,
    num,
    svg_element,
    tip_attr,
    viridis,
)
from falsify.reports.explain_page import explain_section
from falsify.reports.page import esc, head

import falsify
from falsify.results.explain import Explanation
from falsify.results.metrics import Status, column
from falsify.results.miou_maps import CellMap, fmt_value
from falsify.results.miou_maps import compare as compare_maps
from falsify.results.store import RunData

WORST = 12
MAX_MULTIPLES = 30


def png_uri(rgb: np.ndarray) -> str:
    from falsify.images.png import encode_png
    return "data:image/png;base64," + base64.b64encode(encode_png(rgb)).decode("ascii")


def script_json(obj: object) -> str:
    """JSON that is safe inside <script>: no `<`, `>` or `&` can end the element."""
    text = json.dumps(obj, separators=(",", ":"), sort_keys=True, ensure_ascii=True,
                      allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _clean(value: object) -> object:
    """Plain JSON value: NaN → None, numpy scalars → Python, floats to 3 places."""
    if value is None:
        return None
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return None if math.isnan(v) else round(v, 3)
    return str(value)


def cell_key(x: float, y: float) -> str:
    return f"{fmt_value(x)}|{fmt_value(y)}"


def _bg_values(data: RunData) -> tuple:
    return tuple(data.space.dims["background"].grid()) if "background" in data.space.dims else ()


def _cell_tip(x: float, y: float, miou: float | None, n: int, undefined: int, invalid: int,
              threshold: float) -> str:
    where = f"x = {fmt_value(x)} m, y = {fmt_value(y)} m"
    extra = []
    if undefined:
        extra.append(f"{undefined} undefined")
    if invalid:
        extra.append(f"{invalid} invalid")
    more = f" ({', '.join(extra)})" if extra else ""
    if miou is None:
        return f"{where}\nno valid sample{more}"
    s = f"{where}\nmIoU {miou:.3f} · {n} sample{'s' * (n != 1)}{more}"
    if miou < threshold:
        s += f"\nblind spot: {threshold - miou:.3f} below {threshold:.3f}"
    return s


def objective_name(data: RunData) -> str:
    """What the run's map averages: car IoU, another class's IoU, or mIoU over its classes."""
    o = data.objective
    return "car IoU" if o == "car" else "mIoU over the scored classes" if o == "miou" else \
        f"{esc(o)} IoU"


def objective_title(data: RunData) -> str:
    """The map's title suffix for a run with another objective than car ('' for car)."""
    return "" if data.objective == "car" else f": objective {esc(data.objective)}"


def heatmap_section(data: RunData, cmap: CellMap, threshold: float) -> str:
    grid = Grid.sized(cmap.a_values, cmap.b_values, 480, 430, left=52, top=8)
    blind = np.nan_to_num(cmap.miou, nan=1.0) < threshold

    def tip(i: int, j: int) -> str:
        m = cmap.miou[j, i]
        text = _cell_tip(cmap.a_values[i], cmap.b_values[j], None if np.isnan(m) else float(m),
                         int(cmap.samples[j, i]), int(cmap.undefined[j, i]),
                         int(cmap.invalid[j, i]), threshold)
        if cmap.lower is not None and cmap.upper is not None and np.isfinite(m):
            text += (f"\nestimate of the grid's mIoU; interval {cmap.lower[j, i]:.3f} to "
                     f"{cmap.upper[j, i]:.3f}")
        return text

    def attrs(i: int, j: int) -> str:
        m = cmap.miou[j, i]
        return (f' data-x="{esc(fmt_value(cmap.a_values[i]))}" '
                f'data-y="{esc(fmt_value(cmap.b_values[j]))}" '
                f'data-miou="{"" if np.isnan(m) else f3(float(m))}" '
                f'data-n="{int(cmap.samples[j, i])}" tabindex="0"')

    show = grid.cw >= 34 and grid.ch >= 14
    body = cells_svg(grid, cmap.miou, viridis, tip, "cell", blind,
                     (lambda i, j: f3(float(cmap.miou[j, i]))) if show else None, attrs)
    selbox = '<rect id="selbox" x="0" y="0" width="0" height="0" visibility="hidden"/>'
    svg = svg_element(body + axes_svg(grid) + selbox, grid.left + grid.width + 8,
               grid.top + grid.height + 60, "map", "heatmap", "mIoU heat map over x and y")
    multiples = multiples_section(data, threshold)
    what = objective_name(data)
    mean_what = f"Mean {what}"
    n_blind = int(blind.sum())
    scored = int((~np.isnan(cmap.miou)).sum())
    estimated = ""
    if cmap.estimated:
        options = data.meta.get("sampler_options") or {}
        estimated = (f"""
<p class="note">Estimated map (level-set sampler): {len(data.frame)} of the grid's samples were
scored; each cell shows its estimate of the mean the full grid would give, and its tip the
{float(options.get("confidence", 0.95)):.0%} interval. A cell is decided once its interval
excludes the threshold.</p>""")
    placed = "car" if data.space.model_dim == "car_model" else "actor"
    return f"""
<section id="map-section">
<h2>mIoU over position ({placed} 1){objective_title(data)}</h2>
<p class="note">{mean_what} of the valid samples in each cell (over backgrounds and every
other dimension), seen from above: the sensor at the bottom, forward (Y) up. {n_blind} of
{scored} scored cells are blind spots (mIoU &lt; {threshold:.3f}, outlined). Hover a cell for
its value; click it to list its samples.</p>{estimated}
<div class="row">
<figure class="main-map">{svg}</figure>
<figure>{legend_svg(threshold)}</figure>
{multiples}
</div>
<div id="cell-samples">
<h3 id="cell-title">Samples of a cell</h3>
<p id="cell-hint" class="note">Click a cell of the map to list its samples here.</p>
<div class="scroll"><table id="cell-table" hidden><thead><tr><th>eval</th><th>x</th><th>y</th>
<th>yaw</th><th>{model_heading(data)}</th><th>count</th><th>background</th><th>status</th><th>{what}</th>
<th>precision</th><th>recall</th><th>reason</th></tr></thead><tbody></tbody></table></div>
</div>
</section>"""


def _small_map(cmap: CellMap, threshold: float, tip_prefix: str, title: str
               ) -> tuple[str, str, int]:
    """A small map in the main map's colours: its SVG, its mean over scored cells (text) and
    its number of blind cells."""
    grid = Grid.sized(cmap.a_values, cmap.b_values, 84, 96, lo=3, hi=42)
    blind = np.nan_to_num(cmap.miou, nan=1.0) < threshold

    def tip(i: int, j: int) -> str:
        m = cmap.miou[j, i]
        return f"{tip_prefix}\n" + _cell_tip(
            cmap.a_values[i], cmap.b_values[j], None if np.isnan(m) else float(m),
            int(cmap.samples[j, i]), int(cmap.undefined[j, i]), int(cmap.invalid[j, i]),
            threshold)

    body = cells_svg(grid, cmap.miou, viridis, tip, "mcell", blind)
    valid = cmap.miou[~np.isnan(cmap.miou)]
    mean = f3(float(valid.mean())) if valid.size else "—"
    return (svg_element(body, grid.width, grid.height, "small", "", title), mean,
            int(blind.sum()))


def multiples_section(data: RunData, threshold: float) -> str:
    """One small mIoU map per background, same colours and axes as the main map."""
    bgs = _bg_values(data)
    if len(bgs) < 2:
        return ""
    shown = bgs[:MAX_MULTIPLES]
    figs = []
    for bg in shown:
        cmap = data.cell_map(data.frame[data.frame["background"] == bg])
        label = (data.space.background_name(bg) if data.space.real_backgrounds
                 else f"background {bg}")
        svg, mean, n_blind = _small_map(cmap, threshold, label, label)
        short = label if data.space.real_backgrounds else f"bg {bg}"
        figs.append(f'<figure class="multiple">{svg}'
                    f"<figcaption>{esc(short)} · {mean}<br>{n_blind} blind"
                    "</figcaption></figure>")
    more = (f'<p class="note">showing {len(shown)} of {len(bgs)} backgrounds</p>'
            if len(bgs) > len(shown) else "")
    return (f'<div class="multiples-wrap"><h3>Per background</h3><div class="multiples">'
            f'{"".join(figs)}</div>{more}</div>')


def inserted_section(data: RunData, threshold: float) -> str:
    """Runs on real backgrounds: the inserted object's own IoU and recall maps, and per real
    scan the inserted and the real objects of the class scored apart (each with the other left
    out)."""
    if "inserted_iou" not in data.frame:
        return ""
    o = data.objective
    thing = "car" if o in ("car", "miou") else o
    figs = []
    for col, title in (("inserted_iou", f"inserted {thing} IoU"),
                       ("inserted_recall", f"inserted {thing} recall")):
        svg, mean, n_blind = _small_map(data.cell_map(column=col), threshold, title, title)
        figs.append(f'<figure class="multiple">{svg}<figcaption>{esc(title)} · {mean}<br>'
                    f"{n_blind} below {threshold:.2f}</figcaption></figure>")
    frame = data.frame
    rows = []
    for bg in _bg_values(data):
        mine = frame[frame["background"] == bg]
        ok = mine[mine["status"] == Status.OK.value]

        def mean(col: str, ok=ok) -> str:
            v = ok[col].astype(float).mean() if col in ok and len(ok) else float("nan")
            return "—" if math.isnan(v) else f3(v)
        rows.append(
            f"<tr><td>{esc(data.space.background_name(bg))}</td>"
            f'<td class="num">{len(ok)}</td>'
            f'<td class="num">{int((mine["status"] == Status.INVALID.value).sum())}</td>'
            f'<td class="num">{mean(data.score_column)}</td>'
            f'<td class="num">{mean("inserted_iou")} / {mean("inserted_recall")}</td>'
            f'<td class="num">{mean("real_iou")} / {mean("real_recall")}</td></tr>')
    thing = esc(thing)
    return f"""
<section id="inserted">
<h2>Inserted and real {thing}s</h2>
<p class="note">Each sample is a real scan with the {thing} inserted. The inserted {thing} is
scored with the scan's real {thing}s left out, and the real {thing}s with the inserted one left
out, so a map of the inserted {thing} shows where the network loses it. A position where the
{thing} would stand in a real car, wall or tree is invalid, counted and never merged.</p>
<div class="multiples">{"".join(figs)}</div>
<table class="small"><thead><tr><th>real scan</th><th>valid</th><th>invalid</th>
<th>mean {esc(objective_name(data))}</th><th>inserted IoU / recall</th>
<th>real IoU / recall</th></tr></thead><tbody>{"".join(rows)}</tbody></table>
</section>"""


def class_maps_section(data: RunData, threshold: float) -> str:
    """One small (x, y) IoU map per class the run scored (runs with SemanticKITTI classes or
    an objective other than car): where each class, not only the objective, is lost."""
    names = [c for c in data.meta.get("scored_classes") or [] if c not in ("unknown",
                                                                          "unlabeled")]
    figs = []
    for name in names:
        col = f"{column(name)}_iou"
        if col not in data.frame:
            continue
        svg, mean, _ = _small_map(data.cell_map(column=col), threshold, name, f"{name} IoU")
        figs.append(f'<figure class="multiple">{svg}<figcaption>{esc(name)} · {mean}'
                    "</figcaption></figure>")
    if not figs:
        return ""
    return f"""
<section id="class-maps">
<h2>IoU per class over position</h2>
<p class="note">Each class's mean IoU per cell over the samples where the class is in the label
or the prediction (blank: nowhere); the main map above shows the objective,
{esc(data.objective)}.</p>
<div class="multiples">{"".join(figs)}</div>
</section>"""


def distance_section(data: RunData, threshold: float) -> str:
    """IoU of every valid sample against car 1's distance, with the mean per metre."""
    ok = data.ok
    d = np.hypot(ok["x"].astype(float), ok["y"].astype(float)).to_numpy()
    iou = ok[data.score_column].astype(float).to_numpy()
    w, h, left, top, bottom = 560, 260, 46, 12, 40
    pw, ph = w - left - 12, h - top - bottom
    dmax = max(5.0, math.ceil((float(d.max()) if d.size else 5.0) / 5.0) * 5.0)

    def sx(v: float) -> float:
        return left + v / dmax * pw

    def sy(v: float) -> float:
        return top + (1 - v) * ph

    out = _iou_frame(left, top, pw, ph, sy)
    step = 5.0 if dmax > 10 else 1.0
    for k in range(int(dmax / step) + 1):
        v = k * step
        out.append(f'<text x="{num(sx(v))}" y="{top + ph + 15}" text-anchor="middle">'
                   f'{v:g}</text>')
    out.append(f'<text x="{left + pw / 2}" y="{h - 6}" text-anchor="middle" class="axis">'
               "distance of car 1 from the sensor (m)</text>")
    out.append(f'<line class="thrline" x1="{left}" x2="{left + pw}" y1="{num(sy(threshold))}" '
               f'y2="{num(sy(threshold))}"/><text class="thr" x="{left + pw - 4}" '
               f'y="{num(sy(threshold) - 4)}" text-anchor="end">threshold {threshold:.3f}'
               "</text>")
    eval_ix = ok["eval_index"].to_numpy()
    for di, vi, ei in zip(d, iou, eval_ix, strict=True):
        out.append(f'<circle class="pt" cx="{num(sx(di))}" cy="{num(sy(vi))}" r="2.2">'
                   f"<title>eval {int(ei)}: {di:.1f} m, IoU {vi:.3f}</title></circle>")
    if d.size:
        bins = np.floor(d).astype(int)
        pts = []
        for b in sorted(set(bins.tolist())):
            m = float(iou[bins == b].mean())
            pts.append(f"{num(sx(b + 0.5))},{num(sy(m))}")
        out.append(f'<polyline class="meanline" points="{" ".join(pts)}"/>')
    svg = svg_element("".join(out), w, h, "plot", "distance", "IoU against distance")
    return f"""
<section id="distance-section">
<h2>IoU against distance</h2>
<p class="note">Each dot is one valid sample; the orange line is the mean per metre of
distance (hypot(x, y) of car 1).</p>
<figure>{svg}</figure>
</section>"""


def _iou_frame(left: float, top: float, pw: float, ph: float,
               sy: Callable[[float], float]) -> list[str]:
    """A plot's frame with IoU grid lines and labels at 0, 0.25, ..., 1."""
    out = [f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" class="frame"/>']
    for v in (0.0, 0.25, 0.5, 0.75, 1.0):
        out.append(f'<line class="grid" x1="{left}" x2="{left + pw}" y1="{num(sy(v))}" '
                   f'y2="{num(sy(v))}"/><text x="{left - 6}" y="{num(sy(v) + 4)}" '
                   f'text-anchor="end">{v:.2f}</text>')
    return out


def search_section(data: RunData, cmap: CellMap, threshold: float) -> str:
    """Lowest IoU so far against evaluations, and where the search went on the map's axes."""
    what = objective_name(data)
    curve = data.meta.get("curve")
    if not isinstance(curve, list):
        curve = [None if pd.isna(v) else float(v) for v in data.frame[data.score_column]]
    vals = [None if not isinstance(v, int | float) or isinstance(v, bool) else float(v)
            for v in curve]
    n = len(vals)
    w, h, left, top, bottom = 560, 240, 46, 12, 40
    pw, ph = w - left - 12, h - top - bottom

    def sx(k: float) -> float:
        return left + (k / max(1, n - 1)) * pw

    def sy(v: float) -> float:
        return top + (1 - v) * ph

    out = _iou_frame(left, top, pw, ph, sy)
    for k in sorted({0, n // 4, n // 2, 3 * n // 4, max(0, n - 1)}):
        out.append(f'<text x="{num(sx(k))}" y="{top + ph + 15}" text-anchor="middle">{k}'
                   "</text>")
    out.append(f'<text x="{left + pw / 2}" y="{h - 6}" text-anchor="middle" class="axis">'
               "evaluation</text>")
    out.append(f'<line class="thrline" x1="{left}" x2="{left + pw}" y1="{num(sy(threshold))}" '
               f'y2="{num(sy(threshold))}"/>')
    best, steps = math.inf, []
    for k, v in enumerate(vals):
        if v is not None:
            out.append(f'<circle class="pt" cx="{num(sx(k))}" cy="{num(sy(v))}" r="2">'
                       f"<title>eval {k}: IoU {v:.3f}</title></circle>")
            best = min(best, v)
        if best < math.inf:
            steps.append(f"{num(sx(k))},{num(sy(best))}")
    if steps:
        out.append(f'<polyline class="minline" points="{" ".join(steps)}"/>')
    lowest = f3(best) if best < math.inf else "—"
    curve_svg = svg_element("".join(out), w, h, "plot", "curve", "lowest IoU against evaluations")

    # where the search went: the heat map faded, the evaluations in order on top
    grid = Grid.sized(cmap.a_values, cmap.b_values, 480, 430, left=52, top=8)
    faded = cells_svg(grid, cmap.miou, viridis, lambda i, j: "", "pcell")
    frame = data.frame.sort_values("eval_index", kind="stable")
    xs, ys = frame["x"].astype(float).to_numpy(), frame["y"].astype(float).to_numpy()
    ious = frame[data.score_column].astype(float).to_numpy()
    lo_x, hi_x = grid.left, grid.left + grid.width
    lo_y, hi_y = grid.top, grid.top + grid.height
    pts = [(min(max(grid.px(x), lo_x), hi_x), min(max(grid.py(y), lo_y), hi_y))
           for x, y in zip(xs, ys, strict=True)]
    path = " ".join(f"{num(px)},{num(py)}" for px, py in pts)
    dots = []
    for k, ((px, py), ev, v) in enumerate(zip(pts, frame["eval_index"], ious, strict=True)):
        fill = "#9aa0a6" if np.isnan(v) else viridis(float(v))
        text = (f"eval {int(ev)}: x = {xs[k]:.3f}, y = {ys[k]:.3f}, IoU "
                f"{'undefined' if np.isnan(v) else f'{v:.3f}'}")
        dots.append(f'<circle class="step" cx="{num(px)}" cy="{num(py)}" r="4.5" '
                    f'fill="{fill}"{tip_attr(text)}><title>{esc(text)}</title></circle>')
    if np.isfinite(ious).any():
        k = int(np.nanargmin(ious))
        px, py = pts[k]
        dots.append(f'<circle class="ring" cx="{num(px)}" cy="{num(py)}" r="8"/>')
    body = (faded + f'<polyline class="path" points="{path}"/>' + "".join(dots)
            + axes_svg(grid))
    path_svg = svg_element(body, grid.left + grid.width + 8, grid.top + grid.height + 60, "map",
                    "searchpath", "where the search went")
    return f"""
<section id="search-section">
<h2>Search</h2>
<p class="note">{esc(data.meta.get("algorithm", "search"))}, {n} evaluations; lowest {what}
found {lowest}. Left: each evaluation's IoU (dots) and the lowest so far (line). Right: where
each evaluation put car 1, in order (grey path), coloured by IoU on the map's axes; the ring
marks the lowest.</p>
<div class="row"><figure>{curve_svg}</figure><figure>{path_svg}</figure></div>
</section>"""


def compare_section(before: RunData, after: RunData, after_map: CellMap,
                    threshold: float, ascending: bool = False) -> str:
    """The difference map (after − before) and the paper's sorted per-cell change plot
    (ascending, as the paper draws it, when `ascending`)."""
    bmap = before.cell_map()
    bidx = {cell_key(x, y): (i, j) for j, y in enumerate(bmap.b_values)
            for i, x in enumerate(bmap.a_values)}
    diff = np.full(after_map.miou.shape, np.nan)
    prev = np.full(after_map.miou.shape, np.nan)
    for j, y in enumerate(after_map.b_values):
        for i, x in enumerate(after_map.a_values):
            hit = bidx.get(cell_key(x, y))
            if hit is not None:
                prev[j, i] = bmap.miou[hit[1], hit[0]]
                diff[j, i] = after_map.miou[j, i] - prev[j, i]
    finite = diff[~np.isnan(diff)]
    span = max(0.1, math.ceil(float(np.abs(finite).max()) * 10) / 10) if finite.size else 0.1
    grid = Grid.sized(after_map.a_values, after_map.b_values, 480, 430, left=52, top=8)

    def tip(i: int, j: int) -> str:
        where = (f"x = {fmt_value(after_map.a_values[i])} m, "
                 f"y = {fmt_value(after_map.b_values[j])} m")
        if np.isnan(diff[j, i]):
            return f"{where}\nnot scored in both runs"
        return (f"{where}\nmIoU {prev[j, i]:.3f} → {after_map.miou[j, i]:.3f} "
                f"({diff[j, i]:+.3f})")

    show = grid.cw >= 34 and grid.ch >= 14
    body = cells_svg(grid, diff, lambda v: diverging(v, span), tip, "dcell",
                     label=(lambda i, j: f"{diff[j, i]:+.3f}") if show else None)
    diff_svg = svg_element(body + axes_svg(grid), grid.left + grid.width + 8,
                    grid.top + grid.height + 60, "map", "diffmap", "mIoU difference map")
    legend = diverging_legend(span)

    table = compare_maps(bmap, after_map)
    if ascending:
        table = table.iloc[::-1].reset_index(drop=True)
    changes = table["change"].to_numpy(dtype=float)
    plot = improvement_svg(table, span)
    before_blind = {cell_key(x, y) for x, y in _blind_keys(bmap, threshold)}
    after_blind = {cell_key(x, y) for x, y in _blind_keys(after_map, threshold)}
    fixed, new = len(before_blind - after_blind), len(after_blind - before_blind)
    mean = f"{float(changes.mean()):+.3f}" if changes.size else "—"
    meta = before.meta
    return f"""
<section id="compare-section">
<h2>Comparison with the run before</h2>
<p class="note">Before: {esc(before.path)} (model {esc(meta.get("model_name", "?"))}
{esc(str(meta.get("model_hash") or "")[:12])}, config {esc(meta.get("space_name", "?"))}).
Over {changes.size} cells scored in both runs the mIoU changed by {mean} on average:
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
    for k, row in enumerate(table.itertuples(index=False)):
        c = float(row.change)
        y0, y1 = sorted((sy(0.0), sy(c)))
        text = (f"x = {fmt_value(row.x)}, y = {fmt_value(row.y)}: {row.miou_before:.3f} → "
                f"{row.miou_after:.3f} ({c:+.3f})")
        out.append(f'<rect class="bar" x="{num(left + k * bw)}" y="{num(y0)}" '
                   f'width="{num(max(bw - 0.4, 0.6))}" height="{num(max(y1 - y0, 0.5))}" '
                   f'fill="{PUOR[-2] if c >= 0 else PUOR[1]}"{tip_attr(text)}>'
                   f"<title>{esc(text)}</title></rect>")
    out.append(f'<line x1="{left}" x2="{left + pw}" y1="{num(sy(0))}" y2="{num(sy(0))}" '
               'stroke="#333"/>')
    out.append(f'<text x="{left + pw / 2}" y="{h - 6}" text-anchor="middle" class="axis">'
               f"{n} cells, sorted by change</text>")
    return svg_element("".join(out), w, h, "plot", "improvement", "sorted per-cell improvement")


# -- worst samples with previews ----------------------------------------------------------------
@dataclass(frozen=True)
class Preview:
    """Inline pictures of one sample's scan: labels, and the model's prediction if it ran."""

    label_range: str
    label_bev: str
    pred_range: str | None = None
    pred_bev: str | None = None
    error: str = ""


@dataclass(frozen=True)
class ReplayedScan:
    """One worst sample as the report job replayed it: its scan image and car 1's position, and
    the model's classes where it ran; `error` says what failed (no image: the scan did)."""

    image: np.ndarray | None
    car: tuple[float, float] | None = None
    classes: np.ndarray | None = None
    error: str = ""


@dataclass(frozen=True)
class ReportInput:
    """Everything a report draws: the run, the run compared with, the worst samples' scans."""

    run: RunData
    before: RunData | None = None
    scans: Mapping[int, ReplayedScan] = field(default_factory=dict)   # by eval index
    note: str = ""
    worst: int = WORST
    retrain: dict | None = None   # a `falsify retrain` summary: adds the experiment's section
    # the run's explanation (`falsify explain`), or one line saying why there is none;
    # None leaves the Explain section out
    explanation: Explanation | str | None = None


BEV_AHEAD, BEV_SIDE, BEV_SIZE = 32.0, 16.0, 128


def _preview(s: ReplayedScan) -> Preview:
    """The pictures of a replayed scan: labels, and the prediction over the same points."""
    if s.image is None:
        return Preview("", "", error=s.error)
    lr, lb = _pictures(s.image, s.car)
    if s.classes is None:
        return Preview(lr, lb, error=s.error)
    pimg = s.image.copy()
    pimg[..., 5] = np.where(s.image[..., 4] > 0, s.classes, 0)
    pr, pb = _pictures(pimg, s.car)
    return Preview(lr, lb, pr, pb)


def _pictures(image: np.ndarray, car: tuple[float, float] | None = None) -> tuple[str, str]:
    """Range image (2 px per beam, at most 1024 columns) and a bird's-eye view with car 1
    bracketed, as PNG data URIs."""
    from falsify.images.scan_pictures import bev_rgb, range_image_rgb
    ranges = range_image_rgb(image, row_scale=2)
    if ranges.shape[1] > 1024:
        ranges = ranges[:, :: math.ceil(ranges.shape[1] / 1024)]
    bev = bev_rgb(image, size=BEV_SIZE, ahead=BEV_AHEAD, side=BEV_SIDE)
    if car is not None:
        _bracket(bev, *car)
    return png_uri(ranges), png_uri(bev)


def _bracket(bev: np.ndarray, x: float, y: float, half: float = 3.0) -> None:
    """Draw a white square around space point (x right, y forward) into the BEV picture."""
    size = bev.shape[0]
    scale_c, scale_r = size / (2 * BEV_SIDE), size / BEV_AHEAD
    c0, c1 = int((x - half + BEV_SIDE) * scale_c), int((x + half + BEV_SIDE) * scale_c)
    r0, r1 = int((BEV_AHEAD - y - half) * scale_r), int((BEV_AHEAD - y + half) * scale_r)
    c0, c1 = max(c0, 0), min(c1, size - 1)
    r0, r1 = max(r0, 0), min(r1, size - 1)
    if c0 >= c1 or r0 >= r1:
        return
    white = (255, 255, 255)
    bev[r0, c0:c1 + 1] = white
    bev[r1, c0:c1 + 1] = white
    bev[r0:r1 + 1, c0] = white
    bev[r0:r1 + 1, c1] = white


def worst_section(data: RunData, scans: Mapping[int, ReplayedScan], note: str,
                  worst: int) -> str:
    rows = data.worst(worst)
    col, what = data.score_column, objective_name(data)
    prec, rec = col.replace("_iou", "_precision"), col.replace("_iou", "_recall")
    previews = {ev: _preview(s) for ev, s in scans.items()}
    with_pred = any(p.pred_range for p in previews.values())
    head = ("<tr><th>#</th><th>eval</th><th>x, y (m)</th><th>yaw</th>"
            f"<th>{model_heading(data)}</th>"
            f"<th>bg</th><th>{what}</th><th>precision /<br>recall</th>"
            "<th>car points<br>label / pred.</th><th>scan: range image, bird's-eye view"
            + (" (label above, prediction below)" if with_pred else " (label)")
            + "</th></tr>")
    body = []
    for rank, (_, r) in enumerate(rows.iterrows(), start=1):
        p = previews.get(int(r["eval_index"]))
        pics = ""
        if p is not None and p.label_range:
            pics = _pics_html(p.label_range, p.label_bev, "label")
            if p.pred_range:
                pics += _pics_html(p.pred_range, p.pred_bev or "", "prediction")
        if p is not None and p.error:
            pics += f'<p class="note">{esc(p.error)}</p>'
        body.append(
            f"<tr><td>{rank}</td><td>{int(r['eval_index'])}</td>"
            f'<td class="num">{esc(_dimtext(r, "x"))}, {esc(_dimtext(r, "y"))}</td>'
            f'<td class="num">{esc(_dimtext(r, "yaw"))}</td>'
            f"<td>{esc(_dimtext(r, data.space.model_dim))}</td>"
            f"<td>{esc(_bg_text(data, r))}</td>"
            f'<td class="num bad">{f3(r[col])}</td>'
            f'<td class="num">{f3(r.get(prec))} /<br>{f3(r.get(rec))}</td>'
            f'<td class="num">{_int(r.get("label_points"))} / {_int(r.get("car_points"))}</td>'
            f'<td class="pics">{pics}</td></tr>')
    legend = ('<span class="key" style="background:#e63c32"></span>car '
              '<span class="key" style="background:#3278e6"></span>pedestrian '
              '<span class="key" style="background:#f0be1e"></span>cyclist '
              '<span class="key" style="background:#969696"></span>other (shaded by range)')
    note_html = f'<p class="note">{esc(note)}</p>' if note else ""
    empty = "" if body else '<p class="note">No valid sample.</p>'
    return f"""
<section id="worst-section">
<h2>The {len(rows)} worst samples</h2>
<p class="note">Lowest {what} first. Each scan is regenerated from its sample: the range image
(rows = beams, columns = azimuth) over a bird's-eye view (sensor at the bottom, forward up).
{legend}</p>
{note_html}{empty}
<div class="scroll"><table class="worst">{head}{"".join(body)}</table></div>
</section>"""


def _pics_html(ranges: str, bev: str, what: str) -> str:
    return (f'<div class="pic"><img src="{ranges}" alt="range image, {what}" width="448">'
            f'<img src="{bev}" alt="bird\'s-eye view, {what}" width="112" '
            f'height="112"></div>')


def _bg_text(data: RunData, row: pd.Series) -> str:
    """A row's background: the real scan's name on real backgrounds, else the street's id."""
    text = _dimtext(row, "background")
    if data.space.real_backgrounds and text != "—":
        return data.space.background_name(int(float(text)))
    return text


def _dimtext(row: pd.Series, name: str) -> str:
    if name not in row.index:
        return "—"
    v = row[name]
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    if isinstance(v, str):
        return v
    return f"{float(v):.3f}".rstrip("0").rstrip(".") if name in ("x", "y", "yaw") else \
        fmt_value(v)


def _int(v: object) -> str:
    return "—" if v is None or pd.isna(v) else str(int(v))


# -- summary and page -------------------------------------------------------------------------
def summary_section(data: RunData, cmap: CellMap, threshold: float) -> str:
    meta, frame = data.meta, data.frame
    status = frame["status"]
    ok = data.ok
    blind = cmap.blind_spots(threshold)
    scored = int((~np.isnan(cmap.miou)).sum())
    if len(ok):
        low = data.worst(1).iloc[0]
        lowest = (f"{f3(low[data.score_column])} at x = {_dimtext(low, 'x')}, "
                  f"y = {_dimtext(low, 'y')}"
                  f", background {esc(_bg_text(data, low))} (eval {int(low['eval_index'])})")
    else:
        lowest = "—"
    scored_cells = sorted((c for c in cmap.cells() if c.miou is not None),
                          key=lambda c: (c.miou, str(c.a), str(c.b)))
    worst_cell = "—"
    if scored_cells:
        w = scored_cells[0]
        worst_cell = f"{w.miou:.3f} at x = {fmt_value(w.a)}, y = {fmt_value(w.b)}"
    elapsed = meta.get("elapsed_s")
    took = []
    if isinstance(elapsed, int | float):
        took.append(f"{float(elapsed):.1f} s")
    if meta.get("workers"):
        took.append(f"{esc(meta['workers'])} workers")
    started = str(meta.get("started") or "—").replace("T", " ")
    timing = (f"{esc(started)}<br><span class=\"note\">"
              f"{' on '.join(took) or 'duration unknown'}</span>")
    model = f"{esc(meta.get('model_name', '—'))} <code>{esc(str(meta.get('model_hash') or '')[:12])}</code>"  # noqa: E501
    model_path = meta.get("model_path")
    search = str(meta.get("command", "")) or "—"
    if meta.get("algorithm"):
        search += f" · {meta['algorithm']}"
    if meta.get("budget") is not None:
        search += f" · budget {meta['budget']}"
    if meta.get("seed") is not None:
        search += f" · seed {meta['seed']}"
    items = [
        ("Model", model + f'<br><span class="note">{esc(model_path or "bundled model")}'
         f' · {esc(meta.get("backend", "onnx"))}</span>'),
        ("Config", f"{esc(meta.get('space_name', data.space.name))}<br><span class=\"note\">"
         f"{esc(meta.get('config_path', '—'))}</span>"),
        ("Sensor", esc(meta.get("sensor", data.space.sensor))),
        ("Run", esc(search)),
        ("Samples", f"{len(frame)} ({len(ok)} valid)"),
        ("Invalid samples", str(int((status == Status.INVALID).sum()))),
        ("Undefined samples", str(int((status == Status.UNDEFINED).sum()))),
        ("Blind spots", f'<span class="{"bad" if blind else ""}">{len(blind)}</span> of '
         f"{scored} cells (mIoU &lt; {threshold:.3f})"),
        ("Worst cell", worst_cell),
        ("Lowest IoU", lowest),
        ("Time", timing),
    ]
    cards = "".join(f"<div><dt>{k}</dt><dd>{v}</dd></div>" for k, v in items)
    return f'<section id="summary"><dl class="summary">{cards}</dl></section>'


def model_heading(data: RunData) -> str:
    """The model column's heading: "car model" in spaces that name the dim so, else "actor"."""
    return "car model" if data.space.model_dim == "car_model" else "actor"


def samples_json(data: RunData) -> dict:
    """The rows the click-to-list table needs, keyed to their heat-map cell."""
    from falsify.results.miou_maps import snap

    f = data.frame
    cx = snap(f["x"], data.space, "x")
    cy = snap(f["y"], data.space, "y")
    cols = ["cell", "eval", "x", "y", "yaw", "car_model", "count", "background", "status",
            "iou", "precision", "recall", "reason"]
    col = data.score_column
    src = {"eval": "eval_index", "iou": col, "precision": col.replace("_iou", "_precision"),
           "recall": col.replace("_iou", "_recall"), "car_model": data.space.model_dim}
    rows = []
    for k in range(len(f)):
        r = f.iloc[k]
        row: list = [cell_key(cx.iloc[k], cy.iloc[k])]
        for c in cols[1:]:
            name = src.get(c, c)
            v = r[name] if name in f.columns else None
            if v is not None and not isinstance(v, str) and pd.isna(v):
                v = None
            elif c in ("count", "background") and v is not None and not isinstance(v, str):
                v = fmt_value(v)
            row.append(_clean(v))
        rows.append(row)
    return {"columns": cols, "rows": rows}


CSS = """
:root{--fg:#1d2430;--muted:#5b6573;--line:#d9dee5;--panel:#f5f7fa}
*{box-sizing:border-box}
body{font:14px/1.45 $FONT;color:var(--fg);margin:0;background:#fff}
main{max-width:1240px;margin:0 auto;padding:20px 24px 48px}
h1{font-size:22px;margin:0 0 2px}h2{font-size:17px;margin:28px 0 8px;padding-bottom:4px;
border-bottom:1px solid var(--line)}h3{font-size:14px;margin:10px 0 6px}
.sub{color:var(--muted);margin:0 0 14px}
.summary{display:grid;grid-template-columns:repeat(auto-fill,minmax(220px,1fr));gap:8px;margin:0}
.summary div{background:var(--panel);border-radius:6px;padding:8px 10px}
.summary dt{color:var(--muted);font-size:12px}.summary dd{margin:0;font-weight:600;
overflow-wrap:anywhere}
.summary .note{font-weight:400;font-size:12px}
.note{color:var(--muted)}.bad{color:#b00020}
.row{display:flex;flex-wrap:wrap;gap:18px;align-items:flex-start}
figure{margin:0}figcaption{font-size:12px;color:var(--muted);margin:2px 0}
svg text{font:11px $FONT;fill:#333}svg text.axis{fill:#5b6573}
svg text.thr{fill:$BLIND;font-weight:600}
.cell{cursor:pointer}.cell:hover,.cell:focus{stroke:#111;stroke-width:2;outline:none}
#selbox{fill:none;stroke:#000;stroke-width:3;pointer-events:none}
.outline{fill:none;stroke:$BLIND;stroke-width:2.5;pointer-events:none}
.small .outline{stroke-width:1}
svg text.lbl{font-size:10px;text-anchor:middle;pointer-events:none}
.sensor{fill:#1d2430}
.frame{fill:#fbfcfd;stroke:#c8ced6}.grid{stroke:#e6e9ee}
.thrline{stroke:$BLIND;stroke-dasharray:5 4;stroke-width:1.5}
.pt{fill:#2a4d8f;fill-opacity:.35}.meanline{fill:none;stroke:#e08214;stroke-width:2.5}
.minline{fill:none;stroke:$BLIND;stroke-width:2}
.pcell{opacity:.28}.path{fill:none;stroke:#5b6573;stroke-width:1;stroke-opacity:.6}
.step{stroke:#fff;stroke-width:1}.ring{fill:none;stroke:$BLIND;stroke-width:2.5}
.multiples-wrap{flex:1 1 300px;min-width:280px}
.multiples{display:grid;grid-template-columns:repeat(auto-fill,minmax(96px,1fr));gap:8px}
.multiple figcaption{font-size:11px}
#tip{position:fixed;display:none;pointer-events:none;background:#1d2430;color:#fff;
padding:6px 9px;border-radius:5px;font-size:12px;max-width:340px;z-index:10;
white-space:pre-line;box-shadow:0 2px 8px rgba(0,0,0,.25)}
table{border-collapse:collapse;font-size:13px}th,td{padding:4px 8px;
border-bottom:1px solid var(--line);text-align:left;vertical-align:top}th{background:var(--panel)}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.scroll{overflow-x:auto;max-width:100%}
#cell-samples .scroll{max-height:360px;overflow-y:auto}
#cell-samples th{position:sticky;top:0}
.pic{display:flex;gap:6px;margin:0 0 4px}.pic img{display:block;image-rendering:auto}
.key{display:inline-block;width:10px;height:10px;margin:0 3px 0 8px;border-radius:2px}
code{font-size:12px}footer{margin-top:32px;color:var(--muted);font-size:12px}
#explain .row{margin-top:6px}#explain .row>div{flex:1 1 340px;max-width:600px}
td.sbar{width:160px}
td.sbar span{display:block;height:10px;margin-top:4px;background:#2a4d8f;border-radius:2px}
""".replace("$FONT", FONT).replace("$BLIND", BLIND_STROKE)

JS = """
(function () {
  var data = JSON.parse(document.getElementById('falsify-data').textContent);
  var tip = document.getElementById('tip');
  function place(ev) {
    var pad = 14, x = ev.clientX + pad, y = ev.clientY + pad, r = tip.getBoundingClientRect();
    if (x + r.width > window.innerWidth) x = Math.max(0, ev.clientX - r.width - pad);
    if (y + r.height > window.innerHeight) y = Math.max(0, ev.clientY - r.height - pad);
    tip.style.left = x + 'px'; tip.style.top = y + 'px';
  }
  document.addEventListener('mouseover', function (ev) {
    var el = ev.target.closest ? ev.target.closest('[data-tip]') : null;
    if (!el || !el.getAttribute('data-tip')) { tip.style.display = 'none'; return; }
    tip.textContent = el.getAttribute('data-tip');
    tip.style.display = 'block';
    place(ev);
  });
  document.addEventListener('mousemove', function (ev) {
    if (tip.style.display === 'block') place(ev);
  });
  var cols = data.samples.columns, rows = data.samples.rows, at = {};
  cols.forEach(function (c, i) { at[c] = i; });
  function fmt(v, c) {
    if (v === null || v === undefined || v === '') return '\\u2014';
    if (typeof v === 'number' && (c === 'iou' || c === 'precision' || c === 'recall'))
      return v.toFixed(3);
    return String(v);
  }
  function showCell(cell) {
    var key = cell.getAttribute('data-x') + '|' + cell.getAttribute('data-y');
    var sel = document.querySelectorAll('#heatmap .cell.selected');
    for (var s = 0; s < sel.length; s++) sel[s].classList.remove('selected');
    cell.classList.add('selected');
    var box = document.getElementById('selbox');
    ['x', 'y', 'width', 'height'].forEach(function (a) {
      box.setAttribute(a, cell.getAttribute(a));
    });
    box.setAttribute('visibility', 'visible');
    var hits = rows.filter(function (r) { return r[at.cell] === key; });
    hits.sort(function (a, b) {
      var u = a[at.iou], v = b[at.iou];
      if (u === null && v === null) return a[at.eval] - b[at.eval];
      if (u === null) return 1;
      if (v === null) return -1;
      return u - v || a[at.eval] - b[at.eval];
    });
    var table = document.getElementById('cell-table'), body = table.tBodies[0];
    while (body.firstChild) body.removeChild(body.firstChild);
    var show = ['eval', 'x', 'y', 'yaw', 'car_model', 'count', 'background', 'status', 'iou',
                'precision', 'recall', 'reason'];
    hits.forEach(function (r) {
      var tr = document.createElement('tr');
      show.forEach(function (c) {
        var td = document.createElement('td');
        td.textContent = fmt(r[at[c]], c);
        if (typeof r[at[c]] === 'number') td.className = 'num';
        tr.appendChild(td);
      });
      body.appendChild(tr);
    });
    var m = cell.getAttribute('data-miou');
    document.getElementById('cell-title').textContent = 'Samples of cell x = ' +
      cell.getAttribute('data-x') + ', y = ' + cell.getAttribute('data-y') + ' (' +
      hits.length + ' rows, mIoU ' + (m ? m : 'none') + ')';
    document.getElementById('cell-hint').hidden = true;
    table.hidden = false;
  }
  var map = document.getElementById('heatmap');
  map.addEventListener('click', function (ev) {
    var cell = ev.target.closest('.cell'); if (cell) showCell(cell);
  });
  map.addEventListener('keydown', function (ev) {
    var cell = ev.target.closest('.cell');
    if (cell && (ev.key === 'Enter' || ev.key === ' ')) { ev.preventDefault(); showCell(cell); }
  });
})();
"""

CSP = ("default-src 'none'; img-src data:; style-src 'unsafe-inline'; "
       "script-src 'unsafe-inline'; base-uri 'none'; form-action 'none'")

DEFS = ('<svg width="0" height="0" style="position:absolute" aria-hidden="true"><defs>'
        '<pattern id="hatch" width="6" height="6" patternUnits="userSpaceOnUse" '
        'patternTransform="rotate(45)"><rect width="6" height="6" fill="#eceef1"/>'
        '<line x1="0" y1="0" x2="0" y2="6" stroke="#b4bac3" stroke-width="2"/></pattern>'
        '<linearGradient id="vir" x1="0" y1="1" x2="0" y2="0">'
        + "".join(f'<stop offset="{k / 10:.1f}" stop-color="{c}"/>'
                  for k, c in enumerate(VIRIDIS))
        + "</linearGradient></defs></svg>")


def render(report: ReportInput) -> str:
    """The report as one self-contained HTML string (deterministic for its input); a
    `falsify retrain` summary in `report.retrain` adds the retraining experiment's section."""
    data, before, retrain = report.run, report.before, report.retrain
    threshold = data.threshold
    cmap = data.cell_map()
    meta = data.meta
    name = meta.get("space_name") or data.space.name
    sections = [summary_section(data, cmap, threshold), heatmap_section(data, cmap, threshold)]
    sections.append(inserted_section(data, threshold))
    if meta.get("scored_classes") and "inserted_iou" not in data.frame:
        sections.append(class_maps_section(data, threshold))
    if report.explanation is not None:
        sections.append(explain_section(data, report.explanation))
    if meta.get("command") == "search":
        sections.append(search_section(data, cmap, threshold))
    if before is not None and retrain is not None:
        from falsify.reports.retrain_page import retrain_section
        sections.append(retrain_section(before, data, cmap, threshold, retrain))
    if before is not None:
        sections.append(compare_section(before, data, cmap, threshold,
                                        ascending=retrain is not None))
    sections.append(distance_section(data, threshold))
    sections.append(worst_section(data, report.scans, report.note, report.worst))
    payload = script_json({"samples": samples_json(data), "threshold": threshold})
    return f"""{head(f"falsify report: {esc(name)}", CSP, CSS)}
<body>
{DEFS}
<main>
<h1>falsify report: {esc(name)}</h1>
<p class="sub">{esc(meta.get("command", "run"))} run in {esc(data.path)} ·
{objective_name(data)} of {esc(meta.get("model_name", "the model"))} per sample · threshold
{threshold:.3f}</p>
{"".join(sections)}
<footer>falsify {esc(falsify.__version__)} · config hash
<code>{esc(str(meta.get("config_hash") or "")[:12])}</code> · model hash
<code>{esc(str(meta.get("model_hash") or "")[:12])}</code></footer>
</main>
<div id="tip" role="tooltip"></div>
<script type="application/json" id="falsify-data">{payload}</script>
<script>{JS}</script>
</body>
</html>
"""
