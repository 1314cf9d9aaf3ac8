"""The report's Explain section: the failing region as rules over the dims, each dim's share of
the IoU variance, and clusters of failing samples, as `falsify explain RUN` computes them."""

from __future__ import annotations

from falsify.reports.charts import f3
from falsify.reports.page import esc, scroll_open
from falsify.results.explain import Condition, Explanation, score_name
from falsify.results.store import RunData


def _value_text(data: RunData, dim: str, value: object) -> str:
    """A dim's value as escaped text (numbers as `falsify explain` writes them); a real
    background's index also gets the scan's name."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    text = esc(f"{float(value):g}" if number else value)  # type: ignore[arg-type]
    if number and dim == "background" and data.space.real_backgrounds:
        try:
            text += f" ({esc(data.space.background_name(int(value)))})"  # type: ignore
        except (IndexError, ValueError):
            pass
    return text


def _condition_html(data: RunData, c: Condition) -> str:
    """One condition as in `falsify explain` (e.g. `|x| >= 3`), every part escaped."""
    value = _value_text(data, c.dim, c.value)
    if c.op.startswith("|x|"):
        return f"|{esc(c.dim)}| {esc(c.op[3:])} {value}"
    return f"{esc(c.dim)} {esc(c.op)} {value}"


def _rules_html(data: RunData, e: Explanation) -> str:
    if not e.rules:
        return ('<p class="note">No rule covers the failing samples better than the run as a '
                "whole.</p>")
    rows = []
    for k, r in enumerate(e.rules, start=1):
        text = " and ".join(_condition_html(data, c) for c in r.conditions)
        rows.append(f'<tr><td class="num">{k}</td><td><code>{text}</code></td>'
                    f'<td class="num">{r.support}</td><td class="num">{r.failing}</td>'
                    f'<td class="num">{f3(r.precision)}</td>'
                    f'<td class="num">{f3(r.mean_iou)}</td></tr>')
    return (f'{scroll_open("Rules where samples fail")}'
            '<table class="small" id="explain-rules"><thead><tr><th>#</th>'
            "<th>rule</th><th>support</th><th>failing</th><th>precision</th><th>mean IoU</th>"
            f'</tr></thead><tbody>{"".join(rows)}</tbody></table></div>')


def _sensitivity_html(e: Explanation) -> str:
    if not e.sensitivity:
        return ""
    rows = []
    for dim, s in e.sensitivity.items():
        width = f"{min(max(s, 0.0), 1.0) * 100:.1f}"
        rows.append(f"<tr><td>{esc(dim)}</td><td class=\"num\">{f3(s)}</td>"
                    f'<td class="sbar"><span style="width:{width}%"></span></td></tr>')
    return ('<div><h3>Sensitivity</h3><p class="note">Share of the IoU variance each dim '
            "explains alone (first-order index).</p>"
            f'{scroll_open("Sensitivity")}<table class="small" id="explain-sensitivity">'
            '<thead><tr><th>dim</th><th>share</th><th><span class="vh">share, as a bar</span>'
            "</th></tr></thead>"
            f'<tbody>{"".join(rows)}</tbody></table></div></div>')


def _clusters_html(data: RunData, e: Explanation) -> str:
    if not e.clusters:
        return ""
    rows = []
    for k, c in enumerate(e.clusters, start=1):
        centre = ", ".join(f"{esc(d)} = {_value_text(data, d, v)}" for d, v in c.centre.items())
        rows.append(f'<tr><td class="num">{k}</td><td class="num">{c.size}</td>'
                    f'<td class="num">{f3(c.mean_iou)}</td><td>{centre}</td></tr>')
    return ('<div><h3>Clusters of failing samples</h3><p class="note">k-means over the failing '
            "samples' continuous dims; categorical dims show each cluster's most common value; "
            "a car's dims show only where most of the cluster's samples hold that car.</p>"
            f'{scroll_open("Clusters of failing samples")}'
            '<table class="small" id="explain-clusters"><thead><tr>'
            "<th>#</th><th>samples</th><th>mean IoU</th><th>centre</th></tr></thead>"
            f'<tbody>{"".join(rows)}</tbody></table></div></div>')


def explain_section(data: RunData, explanation: Explanation | str) -> str:
    """The section drawn from the explanation the report job computed, or its one-line reason
    why there is none (`explanation` as a string)."""
    if isinstance(explanation, str):
        body = f'<p class="note">{esc(explanation)}</p>'
    else:
        e = explanation
        body = (f'<p class="note">{e.failing} of {e.samples} valid samples have '
                f"{esc(score_name(e.score))} below "
                f"{e.threshold:.3f}. Each rule is a region of the dims where samples fail far "
                "more often than in the run as a whole (support: samples it covers; failing: "
                "those below the threshold; precision: their share), as <code>falsify explain"
                "</code> prints them; later rules explain failures the earlier ones left.</p>"
                f"{_rules_html(data, e)}"
                f'<div class="row">{_sensitivity_html(e)}{_clusters_html(data, e)}</div>')
    return f"""
<section id="explain">
<h2>What the failing samples have in common</h2>
{body}
</section>"""
