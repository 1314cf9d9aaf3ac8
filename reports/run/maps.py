"""The run report's maps over position: the mIoU heat map with its per-background small
multiples, the inserted and real objects' maps (real backgrounds) and the per-class maps."""

from __future__ import annotations

import base64
import math

import numpy as np

from falsify.images.png import encode_png
from falsify.reports.charts import (
    Grid,
    axes_svg,
    cells_svg,
    f3,
    legend_svg,
    svg_element,
    viridis,
    viridis_rgb,
)
from falsify.reports.page import esc, scroll_open
from falsify.reports.run.common import (
    CELL_ROWS,
    bg_values,
    model_heading,
    objective_name,
    objective_title,
    other_dims,
    placed_name,
)
from falsify.results.metrics import Status, column
from falsify.results.miou_maps import CellMap, snap
from falsify.results.store import RunData

MAX_MULTIPLES = 30
# A small map of more cells than this is one picture, a pixel a cell: its cells are too small
# to point at, and a rect each made a page of 40 MB for two maps of 56,000 cells.
SMALL_MAP_RECTS = 2_500


def _cell_tip(x: str, y: str, miou: float | None, n: int, undefined: int, invalid: int,
              threshold: float) -> str:
    where = f"x = {x} m, y = {y} m"
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


def heatmap_section(data: RunData, cmap: CellMap, threshold: float) -> str:
    grid = Grid.sized(cmap.a_values, cmap.b_values, 480, 430, left=52, top=8)
    blind = np.nan_to_num(cmap.miou, nan=1.0) < threshold

    def tip(i: int, j: int) -> str:
        m = cmap.miou[j, i]
        text = _cell_tip(grid.x_text(i), grid.y_text(j), None if np.isnan(m) else float(m),
                         int(cmap.samples[j, i]), int(cmap.undefined[j, i]),
                         int(cmap.invalid[j, i]), threshold)
        if cmap.lower is not None and cmap.upper is not None and np.isfinite(m):
            text += (f"\nestimate of the grid's mIoU; interval {cmap.lower[j, i]:.3f} to "
                     f"{cmap.upper[j, i]:.3f}")
        return text

    rows_at = np.argwhere(cmap.filled)   # (j, i), nearest row first: the first Tab stop
    first = (int(rows_at[0][1]), int(rows_at[0][0])) if len(rows_at) else (0, 0)

    def attrs(i: int, j: int) -> str:
        m = cmap.miou[j, i]
        return (f' data-x="{esc(grid.x_text(i))}" data-y="{esc(grid.y_text(j))}" '
                f'data-miou="{"" if np.isnan(m) else f3(float(m))}" '
                f'data-n="{int(cmap.samples[j, i])}" tabindex="{0 if (i, j) == first else -1}"')

    show = grid.cw >= 34 and grid.ch >= 14
    body = cells_svg(grid, cmap.miou, viridis, tip, "cell", blind,
                     (lambda i, j: f3(float(cmap.miou[j, i]))) if show else None, attrs,
                     present=cmap.filled)
    selbox = '<rect id="selbox" x="0" y="0" width="0" height="0" visibility="hidden"/>'
    n_blind = int(blind.sum())
    scored = int((~np.isnan(cmap.miou)).sum())
    # one Tab stop (the cell with tabindex 0; run.js moves it with the arrow keys), so the
    # keyboard reaches the rest of the page without stepping through every cell
    svg = svg_element(body + axes_svg(grid) + selbox, grid.left + grid.width + 8,
                      grid.top + grid.height + 60, "map", "heatmap",
                      f"mIoU heat map over x and y, {n_blind} of {scored} cells blind", "group")
    multiples = multiples_section(data, threshold)
    what = objective_name(data)
    mean_what = f"Mean {what}"
    estimated = ""
    if cmap.estimated:
        options = data.meta.get("sampler_options") or {}
        estimated = (f"""
<p class="note">Estimated map (level-set sampler): {len(data.frame)} of the grid's samples were
scored; each cell shows its estimate of the mean the full grid would give, and its tip the
{float(options.get("confidence", 0.95)):.0%} interval. A cell is decided once its interval
excludes the threshold.</p>""")
    placed = placed_name(data)
    most = int(data.frame.groupby([snap(data.frame["x"], data.space, "x"),
                                   snap(data.frame["y"], data.space, "y")]).size().max()) \
        if len(data.frame) else 0
    capped = "" if most <= CELL_ROWS else (
        f" A cell lists its {CELL_ROWS} lowest samples (of up to {most} here); every sample is "
        f"in the run's table, {esc(data.path / 'results.csv')}.")
    return f"""
<section id="map-section">
<h2>mIoU over position ({placed} 1){objective_title(data)}</h2>
<p class="note">{mean_what} of the valid samples in each cell (over backgrounds and every
other dimension), seen from above: the sensor at the bottom, forward (Y) up. {n_blind} of
{scored} scored cells are blind spots (mIoU &lt; {threshold:.3f}, outlined). Hover or focus a
cell (Tab, then the arrow keys) for its value; click it or press Enter to list its
samples.</p>{estimated}
<div class="row">
<figure class="main-map">{svg}</figure>
<figure>{legend_svg(threshold)}</figure>
{multiples}
</div>
<div id="cell-samples">
<h3 id="cell-title" aria-live="polite">Samples of a cell</h3>
<p id="cell-hint" class="note">Click a cell of the map to list its samples here.{capped}</p>
{scroll_open("Samples of the selected cell", hidden=True)}
<table id="cell-table" hidden><thead><tr><th>eval</th><th>x</th><th>y</th>
<th>yaw</th><th>{model_heading(data)}</th><th>count</th><th>background</th><th>status</th><th>{what}</th>
<th>precision</th><th>recall</th><th>reason</th>{"<th>other dims</th>" if other_dims(data) else ""}
</tr></thead><tbody></tbody></table></div>
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
            grid.x_text(i), grid.y_text(j), None if np.isnan(m) else float(m),
            int(cmap.samples[j, i]), int(cmap.undefined[j, i]), int(cmap.invalid[j, i]),
            threshold)

    if cmap.miou.size > SMALL_MAP_RECTS:
        grid = Grid(cmap.a_values, cmap.b_values, 84 / len(cmap.a_values),
                    96 / len(cmap.b_values))
        png = encode_png(viridis_rgb(cmap.miou[::-1]))   # row 0, the nearest, at the bottom
        body = (f'<image class="mpic" width="84" height="96" preserveAspectRatio="none" '
                f'href="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'
                f"<title>{esc(tip_prefix)}: {cmap.miou.size:,} cells, a pixel each; point at "
                "the main map for a cell's value</title></image>")
    else:
        body = cells_svg(grid, cmap.miou, viridis, tip, "mcell", blind, present=cmap.filled)
    valid = cmap.miou[~np.isnan(cmap.miou)]
    mean = f3(float(valid.mean())) if valid.size else "—"
    return (svg_element(body, grid.width, grid.height, "small", "", title), mean,
            int(blind.sum()))


def multiples_section(data: RunData, threshold: float) -> str:
    """One small mIoU map per background, same colours and axes as the main map."""
    bgs = bg_values(data)
    if len(bgs) < 2:
        return ""
    shown = bgs[:MAX_MULTIPLES]
    figs = []
    for bg in shown:
        cmap = data.cell_map(data.frame[data.frame["background"] == bg])
        name = data.space.background_name(bg)   # a street names the place it stands for
        real = bool(data.space.real_backgrounds)
        label = name if real else name.replace("street", "background", 1)
        svg, mean, n_blind = _small_map(cmap, threshold, label, label)
        short = name if real else name.replace("street", "bg", 1)
        figs.append(f'<figure class="multiple">{svg}'
                    f"<figcaption>{esc(short)} · {mean}<br>{n_blind} blind"
                    "</figcaption></figure>")
    more = (f'<p class="note">showing {len(shown)} of {len(bgs)} backgrounds</p>'
            if len(bgs) > len(shown) else "")
    return (f'<div class="multiples-wrap"><h3>Per background</h3><div class="multiples">'
            f'{"".join(figs)}</div>{more}</div>')


def inserted_section(data: RunData, threshold: float) -> str:
    """The placed object's own IoU and recall maps, and per background the placed objects and
    the background's own (a real scan's, or a street's parked ones) of the class scored apart,
    each with the other left out."""
    if "inserted_iou" not in data.frame:
        return ""
    o = data.objective
    thing = "car" if o in ("car", "miou") else o
    real = bool(data.space.real_backgrounds)
    ins, own = ("inserted", "real") if real else ("placed", "parked")
    figs = []
    for col, title in (("inserted_iou", f"{ins} {thing} IoU"),
                       ("inserted_recall", f"{ins} {thing} recall")):
        svg, mean, n_blind = _small_map(data.cell_map(column=col), threshold, title, title)
        figs.append(f'<figure class="multiple">{svg}<figcaption>{esc(title)} · {mean}<br>'
                    f"{n_blind} below {threshold:.2f}</figcaption></figure>")
    frame = data.frame
    rows = []
    for bg in bg_values(data):
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
    box = scroll_open(f"{ins.capitalize()} and {own} {thing}s per "
                      f"{'real scan' if real else 'street'}")
    thing = esc(thing)
    note = (f"""Each sample is a real scan with the {thing} inserted. The inserted {thing} is
scored with the scan's real {thing}s left out, and the real {thing}s with the inserted one left
out, so a map of the inserted {thing} shows where the network loses it. A position where the
{thing} would stand in a real car, wall or tree is invalid, counted and never merged.""" if real
            else f"""Each sample is a street with the {thing} placed. The placed {thing} is
scored with the street's own {thing}s (parked ones) left out, and those with the placed one left
out, so a map of the placed {thing} shows where the network loses it, and compares with a run
on real scans.""")
    return f"""
<section id="inserted">
<h2>{ins.capitalize()} and {own} {thing}s</h2>
<p class="note">{note}</p>
<div class="multiples">{"".join(figs)}</div>
{box}
<table class="small"><thead><tr><th>{"real scan" if real else "street"}</th>
<th>valid</th><th>invalid</th><th>mean {objective_name(data)}</th><th>{ins} IoU / recall</th>
<th>{own} IoU / recall</th></tr></thead><tbody>{"".join(rows)}</tbody></table></div>
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
