"""The run report's worst samples: a table of the lowest-scoring samples with each replayed
scan's range image and bird's-eye view (label, and prediction where the model ran)."""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from falsify.reports.charts import f3
from falsify.reports.page import esc, scroll_open
from falsify.reports.run.common import (
    bg_text,
    dim_text,
    model_heading,
    objective_name,
    other_dims,
    other_text,
    score_parts,
)
from falsify.results.metrics import column
from falsify.results.store import RunData


def png_uri(rgb: np.ndarray) -> str:
    from falsify.images.png import encode_png
    return "data:image/png;base64," + base64.b64encode(encode_png(rgb)).decode("ascii")


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
    prec, rec = score_parts(col)
    others = other_dims(data)
    previews = {ev: _preview(s) for ev, s in scans.items()}
    with_pred = any(p.pred_range for p in previews.values())
    head = ("<tr><th>#</th><th>eval</th><th>x, y (m)</th><th>yaw</th>"
            f"<th>{model_heading(data)}</th>"
            f"<th>bg</th>" + ("<th>other dims</th>" if others else "")
            + f"<th>{what}</th><th>precision /<br>recall</th>"
            f"<th>{esc(points_name(data))} points<br>label / pred.</th>"
            "<th>scan: range image, bird's-eye view"
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
            f'<td class="num">{esc(dim_text(r, "x"))}, {esc(dim_text(r, "y"))}</td>'
            f'<td class="num">{esc(dim_text(r, "yaw"))}</td>'
            f"<td>{esc(dim_text(r, data.space.model_dim))}</td>"
            f"<td>{esc(bg_text(data, r))}</td>"
            + (f"<td>{esc(other_text(r, others))}</td>" if others else "")
            + f'<td class="num bad">{f3(r[col])}</td>'
            f'<td class="num">{f3(r.get(prec) if prec else None)} /<br>'
            f'{f3(r.get(rec) if rec else None)}</td>'
            f'<td class="num">{points_text(data, r)}</td>'
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
{scroll_open(f"The {len(rows)} worst samples")}
<table class="worst">{head}{"".join(body)}</table></div>
</section>"""


def _pics_html(ranges: str, bev: str, what: str) -> str:
    return (f'<div class="pic"><img src="{ranges}" alt="range image, {what}" width="448">'
            f'<img src="{bev}" alt="bird\'s-eye view, {what}" width="112" '
            f'height="112"></div>')


def points_name(data: RunData) -> str:
    """The class whose points the worst table counts: the objective's, car for car and miou
    runs (the store's own car_points and label_points)."""
    return "car" if data.objective in ("car", "miou") else data.objective


def points_text(data: RunData, r: pd.Series) -> str:
    """A row's labelled / predicted points of `points_name`'s class: another objective's from
    its tp, fp and fn (a pedestrian run's car counts said nothing of the pedestrian)."""
    name = points_name(data)
    if name == "car":
        return f"{_int(r.get('label_points'))} / {_int(r.get('car_points'))}"
    tp, fp, fn = (r.get(f"{column(name)}_{m}") for m in ("tp", "fp", "fn"))
    if any(v is None or pd.isna(v) for v in (tp, fp, fn)):
        return "— / —"
    return f"{int(tp) + int(fn)} / {int(tp) + int(fp)}"


def _int(v: object) -> str:
    return "—" if v is None or pd.isna(v) else str(int(v))
