"""SVG building blocks of the HTML pages: colour ramps, number formatting, the (x, y) grid
geometry, cell maps with axes, and the legend. Pages compose them; nothing here reads a run."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from falsify.reports.page import esc
from falsify.results.miou_maps import axis_texts

# viridis at 0, 0.1, ..., 1 (matplotlib): perceptually uniform and colour-blind safe.
VIRIDIS = ["#440154", "#482475", "#414487", "#355f8d", "#2a788e", "#21918c", "#22a884",
           "#44bf70", "#7ad151", "#bddf26", "#fde725"]
# PuOr (ColorBrewer, colour-blind safe): orange = worse, purple = better.
PUOR = ["#b35806", "#e08214", "#fdb863", "#fee0b6", "#f7f7f7", "#d8daeb", "#b2abd2", "#8073ac",
        "#542788"]
BLIND_STROKE = "#e4002b"
FONT = 'system-ui, -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif'


# -- small helpers ------------------------------------------------------------------------
def f3(value: float | None) -> str:
    """A number rounded to 3 places, or an em dash when undefined."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return f"{float(value):.3f}"


def num(value: float) -> str:
    """SVG coordinate: 1 decimal, no trailing zeros."""
    s = f"{value:.1f}"
    return s[:-2] if s.endswith(".0") else s


def _hex(c: str) -> np.ndarray:
    return np.array([int(c[i:i + 2], 16) for i in (1, 3, 5)], np.float64)


def _ramp(stops: Sequence[str], t: float) -> str:
    t = min(1.0, max(0.0, t))
    pos = t * (len(stops) - 1)
    i = min(int(pos), len(stops) - 2)
    rgb = _hex(stops[i]) + (_hex(stops[i + 1]) - _hex(stops[i])) * (pos - i)
    return "#" + "".join(f"{int(round(v)):02x}" for v in rgb)


def viridis(value: float) -> str:
    """Sequential colour of an IoU in [0, 1]."""
    return _ramp(VIRIDIS, value)


def viridis_rgb(values: np.ndarray, missing: str = "#e9ebef") -> np.ndarray:
    """`viridis` of every value at once as uint8 RGB (the same colours), `missing` for NaN."""
    stops = np.array([_hex(c) for c in VIRIDIS])
    t = np.clip(np.nan_to_num(values, nan=0.0), 0.0, 1.0)
    pos = t * (len(stops) - 1)
    i = np.minimum(pos.astype(np.int64), len(stops) - 2)
    rgb = stops[i] + (stops[i + 1] - stops[i]) * (pos - i)[..., None]
    rgb = np.round(rgb)
    rgb[np.isnan(values)] = _hex(missing)
    return rgb.astype(np.uint8)


def diverging(change: float, span: float) -> str:
    """Diverging colour of a change in [-span, span]."""
    return _ramp(PUOR, 0.5 + change / (2 * span))


def luminance(colour: str) -> float:
    """WCAG 2 relative luminance of a #rrggbb colour (0 black, 1 white)."""
    c = _hex(colour) / 255.0
    c = np.where(c <= 0.03928, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return float(c @ np.array([0.2126, 0.7152, 0.0722]))


def contrast(a: str, b: str) -> float:
    """WCAG 2 contrast ratio of two #rrggbb colours (1 to 21; body text needs 4.5)."""
    la, lb = sorted((luminance(a), luminance(b)))
    return (lb + 0.05) / (la + 0.05)


def ink(fill: str) -> str:
    """Black or white text, whichever has the higher WCAG contrast on `fill` (at least 4.58:1
    on any colour; a weighted-RGB rule put white on viridis' mid greens at 2.5:1)."""
    return "#000" if contrast(fill, "#000000") >= contrast(fill, "#ffffff") else "#fff"


# -- grid geometry --------------------------------------------------------------------------
@dataclass(frozen=True)
class Grid:
    """Pixel layout of an (x, y) map: x left to right, y (forward) upwards, sensor below."""

    xs: tuple
    ys: tuple
    cw: float
    ch: float
    left: float = 0.0
    top: float = 0.0

    @property
    def width(self) -> float:
        return len(self.xs) * self.cw

    @property
    def height(self) -> float:
        return len(self.ys) * self.ch

    def cell(self, i: int, j: int) -> tuple[float, float]:
        """Top-left pixel of cell (column i, row j); row 0 (nearest) is drawn at the bottom."""
        return self.left + i * self.cw, self.top + (len(self.ys) - 1 - j) * self.ch

    def px(self, x: float) -> float:
        return self.left + interp(x, self.xs, self.cw)

    def py(self, y: float) -> float:
        return self.top + self.height - interp(y, self.ys, self.ch)

    @cached_property
    def _texts(self) -> tuple[dict, dict]:
        return axis_texts(self.xs), axis_texts(self.ys)

    def x_text(self, i: int) -> str:
        """Column i's value as its label (`axis_texts`: no two columns read alike)."""
        return self._texts[0][self.xs[i]]

    def y_text(self, j: int) -> str:
        return self._texts[1][self.ys[j]]

    @staticmethod
    def sized(xs: tuple, ys: tuple, width: float, height: float, left: float = 0.0,
              top: float = 0.0, lo: float = 4.0, hi: float = 110.0) -> Grid:
        cw = min(hi, max(lo, width / max(1, len(xs))))
        ch = min(hi * 0.7, max(lo * 0.7, height / max(1, len(ys))))
        return Grid(xs, ys, cw, ch, left, top)


def interp(v: float, values: tuple, size: float) -> float:
    """Pixel offset of a value along an axis whose cell centres sit at `values`."""
    vals = [float(a) for a in values]
    centres = [(k + 0.5) * size for k in range(len(vals))]
    if len(vals) == 1:
        return centres[0] + (v - vals[0]) * size
    if v <= vals[0]:
        return centres[0] + (v - vals[0]) / (vals[1] - vals[0]) * size
    if v >= vals[-1]:
        return centres[-1] + (v - vals[-1]) / (vals[-1] - vals[-2]) * size
    return float(np.interp(v, vals, centres))


def cells_svg(grid: Grid, values: np.ndarray, fill: Callable[[float], str],
              tip: Callable[[int, int], str], cls: str, outline: np.ndarray | None = None,
              label: Callable[[int, int], str] | None = None,
              attrs: Callable[[int, int], str] | None = None,
              present: np.ndarray | None = None,
              absent: str = "no sample in this cell") -> str:
    """One rect per cell (hatched where NaN), optional in-cell labels and outlines on top.
    Where `present` is given, only its cells get a rect, over one hatched rect (its tip
    `absent`) for the rest: a search over a fine grid leaves most cells without a sample."""
    parts, labels, outlines = [], [], []
    inset = min(1.5, min(grid.cw, grid.ch) / 4)   # an outline inside its cell, however small
    if present is not None and not present.all():
        parts.append(f'<rect class="absent {cls}-absent" x="{num(grid.left)}" '
                     f'y="{num(grid.top)}" width="{num(grid.width)}" '
                     f'height="{num(grid.height)}" fill="url(#hatch)">'
                     f'<title>{esc(absent)}</title></rect>')
    for j in range(len(grid.ys)):
        for i in range(len(grid.xs)):
            if present is not None and not present[j, i]:
                continue
            x, y = grid.cell(i, j)
            v = values[j, i]
            empty = bool(np.isnan(v))
            colour = "url(#hatch)" if empty else fill(float(v))
            text = tip(i, j)
            klass = cls + (" empty" if empty else "") + (
                " blind" if outline is not None and outline[j, i] else "")
            extra = attrs(i, j) if attrs else ""
            parts.append(f'<rect class="{klass}" x="{num(x)}" y="{num(y)}" '
                         f'width="{num(grid.cw)}" height="{num(grid.ch)}" fill="{colour}"'
                         f'{extra}><title>{esc(text)}</title></rect>')
            if label is not None and not empty:
                labels.append(f'<text class="lbl" x="{num(x + grid.cw / 2)}" '
                              f'y="{num(y + grid.ch / 2 + 3.5)}" fill="{ink(fill(float(v)))}">'
                              f'{esc(label(i, j))}</text>')
            if outline is not None and outline[j, i]:
                outlines.append(f'<rect class="outline" x="{num(x + inset)}" '
                                f'y="{num(y + inset)}" width="{num(grid.cw - 2 * inset)}" '
                                f'height="{num(grid.ch - 2 * inset)}"/>')
    # labels and outlines repeat what each cell's title says: hidden from screen readers
    marks = "".join(labels) + "".join(outlines)
    return "".join(parts) + (f'<g aria-hidden="true">{marks}</g>' if marks else "")


def axes_svg(grid: Grid, sensor: bool = True) -> str:
    """Tick labels under the columns and left of the rows, axis titles, and the sensor."""
    out = []
    # 11 px digits are about 6.2 px wide: a label every `every_x` columns leaves 6 px between
    longest = max((len(grid.x_text(i)) for i in range(len(grid.xs))), default=1)
    every_x = max(1, math.ceil(max(26.0, 6.2 * longest + 6) / grid.cw))
    every_y = max(1, math.ceil(14 / grid.ch))
    base = grid.top + grid.height
    for i in range(len(grid.xs)):
        if i % every_x == 0:
            cx = grid.left + (i + 0.5) * grid.cw
            out.append(f'<text x="{num(cx)}" y="{num(base + 14)}" text-anchor="middle">'
                       f'{esc(grid.x_text(i))}</text>')
    for j in range(len(grid.ys)):
        if j % every_y == 0:
            _, cy = grid.cell(0, j)
            out.append(f'<text x="{num(grid.left - 6)}" y="{num(cy + grid.ch / 2 + 4)}" '
                       f'text-anchor="end">{esc(grid.y_text(j))}</text>')
    out.append(f'<text x="{num(grid.left + grid.width / 2)}" y="{num(base + 30)}" '
               'text-anchor="middle" class="axis">X (m), right positive</text>')
    ymid = grid.top + grid.height / 2
    out.append(f'<text transform="translate({num(grid.left - 36)} {num(ymid)}) rotate(-90)" '
               'text-anchor="middle" class="axis">Y (m), forward ↑</text>')
    if sensor:
        sx = min(max(grid.px(0.0), grid.left), grid.left + grid.width)
        sy = base + 40
        out.append(f'<path class="sensor" d="M{num(sx)} {num(sy)} l-7 12 h14 z"/>'
                   f'<text x="{num(sx + 11)}" y="{num(sy + 11)}">sensor (0, 0)</text>')
    return "".join(out)


def svg_element(content: str, width: float, height: float, klass: str, ident: str = "",
                label: str = "", role: str = "img") -> str:
    """An inline chart named `label` for screen readers: role "img" (one picture) for a static
    chart, "group" for one whose marks the keyboard reaches (an img hides its children)."""
    idattr = f' id="{ident}"' if ident else ""
    return (f'<svg{idattr} class="{klass}" xmlns="http://www.w3.org/2000/svg" '
            f'width="{num(width)}" height="{num(height)}" '
            f'viewBox="0 0 {num(width)} {num(height)}" role="{role}" '
            f'aria-label="{esc(label)}">{content}</svg>')


# -- sections ----------------------------------------------------------------------------


def legend_svg(threshold: float) -> str:
    """Vertical viridis bar 0..1 with the threshold marked, plus the hatched and blind keys."""
    top, h, x0 = 20, 240, 8
    ty = top + h * (1 - threshold)
    ticks = "".join(
        f'<text x="{x0 + 24}" y="{num(top + h * (1 - v) + 4)}">{v:.2f}</text>'
        for v in (0.0, 0.25, 0.5, 0.75, 1.0))
    body = (f'<text x="{x0}" y="{top - 8}" class="axis">mIoU</text>'
            f'<rect x="{x0}" y="{top}" width="16" height="{h}" fill="url(#vir)" stroke="#888"/>'
            f"{ticks}"
            f'<line x1="{x0 - 4}" x2="{x0 + 20}" y1="{num(ty)}" y2="{num(ty)}" '
            f'stroke="{BLIND_STROKE}" stroke-width="2.5"/>'
            f'<text x="{x0 + 62}" y="{num(ty + 4)}" class="thr">threshold {threshold:.3f}'
            "</text>"
            f'<rect x="{x0}" y="{top + h + 18}" width="16" height="16" fill="url(#hatch)" '
            'stroke="#888"/>'
            f'<text x="{x0 + 24}" y="{top + h + 30}">no valid sample</text>'
            f'<rect x="{x0}" y="{top + h + 42}" width="16" height="16" fill="{viridis(0.3)}"/>'
            f'<rect class="outline" x="{x0 + 1.5}" y="{top + h + 43.5}" width="13" '
            'height="13"/>'
            f'<text x="{x0 + 24}" y="{top + h + 54}">blind spot (&lt; {threshold:.3f})</text>')
    return svg_element(body, 170, top + h + 66, "legend", "", "colour scale")
