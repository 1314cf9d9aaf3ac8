"""The run report's IoU plots: IoU against object 1's distance, and a search's lowest IoU
against evaluations beside where its evaluations went on the map."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pandas as pd

from falsify.reports.charts import (
    Grid,
    axes_svg,
    cells_svg,
    f3,
    num,
    svg_element,
    viridis,
)
from falsify.reports.page import esc
from falsify.reports.run.common import MAX_POINTS, objective_name, placed_name
from falsify.results.miou_maps import CellMap
from falsify.results.store import RunData


def distance_section(data: RunData, threshold: float) -> str:
    """IoU of every valid sample against object 1's distance (car 1, or actor 1 in a space of
    actors), with the mean per metre."""
    placed = f"{placed_name(data)} 1"
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
               f"distance of {placed} from the sensor (m)</text>")
    out.append(f'<line class="thrline" x1="{left}" x2="{left + pw}" y1="{num(sy(threshold))}" '
               f'y2="{num(sy(threshold))}"/><text class="thr" x="{left + pw - 4}" '
               f'y="{num(sy(threshold) - 4)}" text-anchor="end">threshold {threshold:.3f}'
               "</text>")
    eval_ix = ok["eval_index"].to_numpy()
    dense = d.size > MAX_POINTS
    if dense:
        out += _density(d, iou, dmax, sx, sy, pw, ph)
    else:
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
<p class="note">{f"The {d.size} valid samples, binned: the darker a box, the more samples in it"
if dense else "Each dot is one valid sample"}; the orange line is the mean per metre of
distance (hypot(x, y) of {placed}).</p>
<figure>{svg}</figure>
</section>"""


DENSITY_BINS = (100, 50)   # distance bins, IoU bins of a plot of more than MAX_POINTS samples


def _density(d: np.ndarray, iou: np.ndarray, dmax: float, sx: Callable[[float], float],
             sy: Callable[[float], float], pw: float, ph: float) -> list[str]:
    """Samples binned by distance and IoU, a box per non-empty bin shaded by its count (log
    scale): as many marks as bins at most, however many samples."""
    nd, ni = DENSITY_BINS
    keep = np.isfinite(d) & np.isfinite(iou)
    counts, _, _ = np.histogram2d(d[keep], np.clip(iou[keep], 0.0, 1.0), bins=(nd, ni),
                                  range=((0.0, dmax), (0.0, 1.0)))
    most = math.log1p(float(counts.max())) if counts.size and counts.max() > 0 else 1.0
    w, h = dmax / nd, 1.0 / ni
    out = []
    for a, b in zip(*np.nonzero(counts), strict=True):
        n = int(counts[a, b])
        shade = 0.15 + 0.85 * math.log1p(n) / most
        out.append(f'<rect class="bin" x="{num(sx(a * w))}" y="{num(sy((b + 1) * h))}" '
                   f'width="{num(pw / nd)}" height="{num(ph / ni)}" fill="#3b6ea5" '
                   f'fill-opacity="{shade:.2f}"><title>{n} sample{"s" * (n != 1)}: '
                   f"{a * w:.1f} to {(a + 1) * w:.1f} m, IoU {b * h:.2f} to {(b + 1) * h:.2f}"
                   "</title></rect>")
    return out


def _iou_frame(left: float, top: float, pw: float, ph: float,
               sy: Callable[[float], float]) -> list[str]:
    """A plot's frame with IoU grid lines and labels at 0, 0.25, ..., 1."""
    out = [f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" class="frame"/>']
    for v in (0.0, 0.25, 0.5, 0.75, 1.0):
        out.append(f'<line class="grid" x1="{left}" x2="{left + pw}" y1="{num(sy(v))}" '
                   f'y2="{num(sy(v))}"/><text x="{left - 6}" y="{num(sy(v) + 4)}" '
                   f'text-anchor="end">{v:.2f}</text>')
    return out


CURVE_BINS = 500   # bins of evaluations a curve of more than MAX_POINTS draws (one per 1-2 px)


def _ranges(vals: list[float | None], sx: Callable[[float], float],
            sy: Callable[[float], float], pw: float) -> list[str]:
    """Evaluations binned in order, a bar per bin from its lowest IoU to its highest: as many
    marks as bins, however many evaluations."""
    n = len(vals)
    edges = np.unique(np.linspace(0, n, CURVE_BINS + 1).round().astype(int))
    arr = np.array([np.nan if v is None else v for v in vals], float)
    out = []
    for a, b in zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True):
        part = arr[a:b]
        part = part[np.isfinite(part)]
        if not part.size:
            continue
        lo, hi = float(part.min()), float(part.max())
        out.append(f'<rect class="range" x="{num(sx(a))}" y="{num(sy(hi))}" '
                   f'width="{num(max(sx(b - 1) - sx(a), 0.8))}" '
                   f'height="{num(max(sy(lo) - sy(hi), 0.8))}">'
                   f"<title>evals {a} to {b - 1}: IoU {lo:.3f} to {hi:.3f}</title></rect>")
    return out


def _search_note(data: RunData, n: int, points: int) -> str:
    """What the two search plots show: every evaluation, or (over MAX_POINTS) bins of them
    and the lowest ones."""
    placed = placed_name(data)
    if n <= MAX_POINTS and points <= MAX_POINTS:
        return ("Left: each evaluation's IoU (dots) and the lowest so far (line). Right: where "
                f"each evaluation put {placed} 1, in order (grey path), coloured by IoU on the "
                "map's axes; the ring marks the lowest.")
    return (f"Left: the range of IoU (bars) over each run of about {max(1, n // CURVE_BINS)} "
            "evaluations, and the lowest so far (line). Right: where the "
            f"{min(points, MAX_POINTS)} lowest of the {points} evaluations put {placed} 1, "
            "coloured by IoU on the map's axes; the ring marks the lowest. Every evaluation is "
            f"in the run's table, {esc(data.path / 'results.csv')}.")


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
    if n > MAX_POINTS:
        out += _ranges(vals, sx, sy, pw)
        arr = np.array([math.inf if v is None else v for v in vals], float)
        running = np.minimum.accumulate(arr)
        best = float(running[-1])
        ends = np.unique(np.linspace(0, n - 1, CURVE_BINS + 1).round().astype(int))
        steps = [f"{num(sx(k))},{num(sy(running[k]))}" for k in ends.tolist()
                 if running[k] < math.inf]
    else:
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
    faded = cells_svg(grid, cmap.miou, viridis, lambda i, j: "", "pcell",
                      present=cmap.filled)
    frame = data.frame.sort_values("eval_index", kind="stable")
    xs, ys = frame["x"].astype(float).to_numpy(), frame["y"].astype(float).to_numpy()
    ious = frame[data.score_column].astype(float).to_numpy()
    lo_x, hi_x = grid.left, grid.left + grid.width
    lo_y, hi_y = grid.top, grid.top + grid.height
    pts = [(min(max(grid.px(x), lo_x), hi_x), min(max(grid.py(y), lo_y), hi_y))
           for x, y in zip(xs, ys, strict=True)]
    many = len(pts) > MAX_POINTS
    path = "" if many else " ".join(f"{num(px)},{num(py)}" for px, py in pts)
    shown = range(len(pts))
    if many:   # the MAX_POINTS lowest (undefined last), in evaluation order; no path
        shown = sorted(np.lexsort((np.arange(len(ious)), np.nan_to_num(ious, nan=np.inf)))
                       [:MAX_POINTS].tolist())
    evals = frame["eval_index"].to_numpy()
    dots = []
    for k in shown:
        (px, py), ev, v = pts[k], evals[k], ious[k]
        fill = "#9aa0a6" if np.isnan(v) else viridis(float(v))
        text = (f"eval {int(ev)}: x = {xs[k]:.3f}, y = {ys[k]:.3f}, IoU "
                f"{'undefined' if np.isnan(v) else f'{v:.3f}'}")
        dots.append(f'<circle class="step" cx="{num(px)}" cy="{num(py)}" r="4.5" '
                    f'fill="{fill}"><title>{esc(text)}</title></circle>')
    if np.isfinite(ious).any():
        k = int(np.nanargmin(ious))
        px, py = pts[k]
        dots.append(f'<circle class="ring" cx="{num(px)}" cy="{num(py)}" r="8"/>')
    body = (faded + (f'<polyline class="path" points="{path}"/>' if path else "") + "".join(dots)
            + axes_svg(grid))
    path_svg = svg_element(body, grid.left + grid.width + 8, grid.top + grid.height + 60, "map",
                    "searchpath", "where the search went")
    return f"""
<section id="search-section">
<h2>Search</h2>
<p class="note">{esc(data.meta.get("algorithm", "search"))}, {n} evaluations; lowest {what}
found {lowest}. {_search_note(data, n, len(pts))}</p>
<div class="row"><figure>{curve_svg}</figure><figure>{path_svg}</figure></div>
</section>"""
