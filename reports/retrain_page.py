"""The retraining experiment's part of the comparison page: before and after maps side by side,
the selected cells, the regression checks and the issue's criteria (from `falsify retrain`)."""

from __future__ import annotations

import numpy as np

from falsify.reports.charts import Grid, axes_svg, cells_svg, f3, legend_svg, svg_element, viridis
from falsify.reports.page import esc, scroll_open
from falsify.results.miou_maps import CellMap, axis_texts
from falsify.results.store import RunData


def _map_svg(cmap: CellMap, threshold: float, ident: str, title: str) -> str:
    grid = Grid.sized(cmap.a_values, cmap.b_values, 330, 330, left=52, top=8)
    blind = np.nan_to_num(cmap.miou, nan=1.0) < threshold

    def tip(i: int, j: int) -> str:
        m = cmap.miou[j, i]
        value = "not scored" if np.isnan(m) else f"mIoU {float(m):.3f}"
        return f"{title}: x = {grid.x_text(i)} m, y = {grid.y_text(j)} m\n{value}"

    show = grid.cw >= 30 and grid.ch >= 14
    body = cells_svg(grid, cmap.miou, viridis, tip, "rcell", blind,
                     (lambda i, j: f3(float(cmap.miou[j, i]))) if show else None)
    return svg_element(body + axes_svg(grid), grid.left + grid.width + 8,
                grid.top + grid.height + 60, "map", ident, f"{title} mIoU map")


def _yes(v: object) -> str:
    return {True: "met", False: "NOT met", None: "not measured"}.get(v, esc(v))  # type: ignore


def retrain_section(before: RunData, after: RunData, after_map: CellMap, threshold: float,
                    summary: dict) -> str:
    """Before and after maps, the selected cells with their change, checks and criteria."""
    bmap = before.cell_map()
    maps = (f'<figure><figcaption>Before: {esc(before.meta.get("model_name", "?"))} '
            f'{esc(str(before.meta.get("model_hash") or "")[:12])}</figcaption>'
            f'{_map_svg(bmap, threshold, "before-map", "before")}</figure>'
            f'<figure><figcaption>After: {esc(after.meta.get("model_name", "?"))} '
            f'{esc(str(after.meta.get("model_hash") or "")[:12])}</figcaption>'
            f'{_map_svg(after_map, threshold, "after-map", "after")}</figure>'
            f"<figure>{legend_svg(threshold)}</figure>")
    rows = []
    cells = summary.get("blind_before", [])
    xs, ys = axis_texts(c["x"] for c in cells), axis_texts(c["y"] for c in cells)
    for c in cells:
        after_v = c.get("miou_after")
        fixed = after_v is not None and after_v >= threshold
        delta = "" if after_v is None else f"{after_v - c['miou_before']:+.3f}"
        rows.append(f"<tr><td>{esc(xs[c['x']])}</td><td>{esc(ys[c['y']])}</td>"
                    f"<td>{f3(c['miou_before'])}</td><td>{f3(after_v)}</td>"
                    f"<td>{delta}</td>"
                    f"<td>{'yes' if fixed else 'no'}</td></tr>")
    selected = ("<table id=\"selected-cells\"><thead><tr><th>x</th><th>y</th><th>mIoU before"
                "</th><th>after</th><th>change</th><th>at or above threshold</th></tr></thead>"
                f"<tbody>{''.join(rows)}</tbody></table>") if rows else \
        "<p class=\"note\">No cell was below the threshold before: nothing was selected.</p>"
    checks = []
    for c in summary.get("checks", []):
        change = c.get("change")
        delta = "" if change is None else f"{change:+.4f}"
        checks.append(f"<tr><td>{esc(c['name'])}</td><td>{int(c['scans'])}</td>"
                      f"<td>{f3(c.get('before'))}</td><td>{f3(c.get('after'))}</td>"
                      f"<td>{delta}</td>"
                      f"<td>{_yes(c.get('passed'))}</td><td>{esc(c.get('note', ''))}</td></tr>")
    crit = "".join(f"<li><code>{esc(k)}</code>: {_yes(v)}</li>"
                   for k, v in summary.get("criteria", {}).items())
    t = summary.get("training", {})
    loss = t.get("loss")
    loss = f"{loss:.4f}" if isinstance(loss, int | float) else esc(loss)
    training = (f"Fine-tuned from the model's weights on {esc(t.get('training_scans'))} training "
                f"scans plus {esc(t.get('selected_scans'))} selected scans repeated "
                f"{esc(t.get('oversample'))} times ({esc(t.get('scans_per_epoch'))} scans per "
                f"epoch), {esc(t.get('epochs'))} epoch(s) requested, stopped: "
                f"{esc(t.get('stopped'))}, final loss {loss}.") if t else ""
    return f"""
<section id="retrain-section">
<h2>Retraining experiment</h2>
<p class="note">The V cells below {threshold:.3f} before ({len(rows)} cells) chose the scans of R
added to the training set ({esc(summary.get("retraining_scans", 0))} scans). Mean cell mIoU over
V: {f3(summary.get("mean_before"))} before, {f3(summary.get("mean_after"))} after. {training}</p>
<div class="row">{maps}</div>
<h3>Selected cells</h3>
{scroll_open("Selected cells")}{selected}</div>
<h3>Regression checks (car IoU pooled over each set)</h3>
{scroll_open("Regression checks")}
<table id="checks"><thead><tr><th>set</th><th>scans</th><th>before</th>
<th>after</th><th>change</th><th>drop at most 0.01</th><th>note</th></tr></thead>
<tbody>{''.join(checks)}</tbody></table></div>
<h3>Criteria</h3>
<ul id="criteria">{crit}</ul>
</section>"""
