"""One self-contained HTML report of a run: the page assembled from its sections, with the
stylesheet and script (reports/assets/) and the click-to-list data inlined.

Everything is inline (CSS, JS, SVG, PNG previews as data: URIs) and a Content-Security-Policy
forbids any fetch, so the file opens offline and leaks nothing. Output bytes depend only on the
run (and the compared run): no render time, sorted data, fixed number formats.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

import falsify
from falsify.reports.charts import BLIND_STROKE, FONT, VIRIDIS
from falsify.reports.explain_page import explain_section
from falsify.reports.page import esc, head
from falsify.reports.run.common import (
    CELL_ROWS,
    objective_name,
    other_dims,
    other_text,
    score_parts,
)
from falsify.reports.run.compare import compare_section
from falsify.reports.run.maps import class_maps_section, heatmap_section, inserted_section
from falsify.reports.run.plots import distance_section, search_section
from falsify.reports.run.summary import summary_section
from falsify.reports.run.worst import ReplayedScan, worst_section
from falsify.results.explain import Explanation
from falsify.results.miou_maps import axis_texts, fmt_value
from falsify.results.store import RunData

WORST = 12
ASSETS = Path(__file__).resolve().parent.parent / "assets"


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
    # what differs between the two runs' spaces besides the model (one line each)
    differences: tuple[str, ...] = ()


def samples_json(data: RunData, per_cell: int = CELL_ROWS) -> dict:
    """The rows the click-to-list table needs, keyed to their heat-map cell: per cell its
    `per_cell` lowest (the order the table lists them in: lowest score first, undefined and
    invalid rows last, ties by evaluation), so a run of 50,000 rows does not embed them all;
    `cells` holds every cell's full row count (the rest are in the run's results.csv)."""
    from falsify.results.miou_maps import axis_values, snap

    f = data.frame
    others = other_dims(data)
    cols = ["cell", "eval", "x", "y", "yaw", "car_model", "count", "background", "status",
            "iou", "precision", "recall", "reason"] + (["other"] if others else [])
    col = data.score_column
    prec, rec = score_parts(col)
    src = {"eval": "eval_index", "iou": col, "precision": prec, "recall": rec,
           "car_model": data.space.model_dim}
    # the map's own cell texts (`axis_texts`), so each row lands in the cell its key names
    cx = snap(f["x"], data.space, "x").map(axis_texts(axis_values(data.space, "x")))
    cy = snap(f["y"], data.space, "y").map(axis_texts(axis_values(data.space, "y")))
    keys = (cx + "|" + cy).rename("_cell")
    score = pd.to_numeric(f[col], errors="coerce") if col in f.columns else \
        pd.Series(np.nan, index=f.index)
    order = pd.DataFrame({"_cell": keys, "_none": score.isna(), "_score": score,
                          "_eval": f["eval_index"]}).sort_values(
        ["_cell", "_none", "_score", "_eval"], kind="stable")
    kept = order.groupby("_cell", sort=False).head(per_cell).sort_values("_eval",
                                                                         kind="stable")
    sub = f.loc[kept.index]
    values: list[list] = [kept["_cell"].tolist()]
    for c in cols[1:]:
        if c == "other":
            values.append([other_text(r, others) for _, r in sub[list(others)].iterrows()])
            continue
        name = src.get(c, c)
        if name not in f.columns:
            values.append([None] * len(sub))
            continue
        out = []
        for v in sub[name].tolist():
            if v is not None and not isinstance(v, str) and pd.isna(v):
                v = None
            elif c in ("count", "background") and v is not None and not isinstance(v, str):
                v = fmt_value(v)
            out.append(_clean(v))
        values.append(out)
    counts = keys.value_counts()
    return {"columns": cols, "rows": [list(r) for r in zip(*values, strict=True)],
            "cells": {k: int(counts[k]) for k in sorted(counts.index)}, "per_cell": per_cell}


def _asset(name: str) -> str:
    """A file of reports/assets/ as the page inlines it: after a newline, as the file holds it;
    in the stylesheet $FONT and $BLIND stand for the charts' font and blind-spot colour."""
    text = "\n" + (ASSETS / name).read_text(encoding="utf-8")
    return text.replace("$FONT", FONT).replace("$BLIND", BLIND_STROKE)


CSS = _asset("run.css")
JS = _asset("run.js")

CSP = ("default-src 'none'; img-src data:; style-src 'unsafe-inline'; "
       "script-src 'unsafe-inline'; base-uri 'none'; form-action 'none'")

DEFS = ('<svg width="0" height="0" style="position:absolute" aria-hidden="true"><defs>'
        '<pattern id="hatch" width="6" height="6" patternUnits="userSpaceOnUse" '
        'patternTransform="rotate(45)"><rect width="6" height="6" fill="#eceef1"/>'
        '<line x1="0" y1="0" x2="0" y2="6" stroke="#b4bac3" stroke-width="2"/></pattern>'
        # a blind cell's outline edged in black and white: it stands out on every fill
        '<filter id="halo"><feMorphology in="SourceAlpha" operator="dilate" radius="3" '
        'result="w"/><feFlood flood-color="#fff"/><feComposite in2="w" operator="in" '
        'result="W"/><feMorphology in="SourceAlpha" operator="dilate" radius="1.5" result="b"/>'
        '<feFlood flood-color="#000"/><feComposite in2="b" operator="in" result="B"/><feMerge>'
        '<feMergeNode in="W"/><feMergeNode in="B"/><feMergeNode in="SourceGraphic"/></feMerge>'
        '</filter>'
        '<linearGradient id="vir" x1="0" y1="1" x2="0" y2="0">'
        + "".join(f'<stop offset="{k / 10:.1f}" stop-color="{c}"/>'
                  for k, c in enumerate(VIRIDIS))
        + "</linearGradient></defs></svg>")


def incomplete_note(data: RunData) -> str:
    """A warning above the summary for a run stopped before its end: what it holds and the
    command that finishes it; empty for a complete run or one that does not say."""
    done = data.completeness
    if done.complete is not False:
        return ""
    return (f'<p id="incomplete" class="bad"><strong>Incomplete run:</strong> {esc(done.text())}'
            " are stored; the maps, blind spots and samples below cover only those. Finish it "
            f"with <code>{esc(data.resume_command())}</code>.</p>\n")


def page_title(name: str, run: Path) -> str:
    """The browser tab's title: the space's name and the run's folder, so two runs of one config
    (two models, before and after) read apart; the folder alone where it is the name."""
    folder = Path(run).name
    return f"falsify report: {name}" + (f" · {folder}" if folder and folder != name else "")


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
    if meta.get("scored_classes") and not data.space.real_backgrounds:
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
                                        ascending=retrain is not None,
                                        differences=report.differences))
    sections.append(distance_section(data, threshold))
    sections.append(worst_section(data, report.scans, report.note, report.worst))
    payload = script_json({"samples": samples_json(data), "threshold": threshold})
    return f"""{head(esc(page_title(str(name), data.path)), CSP, CSS)}
<body>
{DEFS}
<main>
<h1>falsify report: {esc(name)}</h1>
<p class="sub">{esc(meta.get("command", "run"))} run in {esc(data.path)} ·
{objective_name(data)} of {esc(meta.get("model_name", "the model"))} per sample · threshold
{threshold:.3f}</p>
{incomplete_note(data)}{"".join(sections)}
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
