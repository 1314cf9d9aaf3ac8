"""The `falsify tradeoff` page: a Pareto plot (time against mIoU-map error) and the table.

One self-contained HTML file: inline CSS and SVG, no script, a Content-Security-Policy that
forbids any fetch, every string escaped. Output bytes depend only on the measurement.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from falsify.fileio import write_text
from falsify.reports.page import esc, head, scroll_open

# Okabe-Ito: distinguishable with the common colour-vision deficiencies.
COLOURS = ("#0072b2", "#e69f00", "#009e73", "#cc79a7", "#d55e00", "#56b4e9", "#000000")
MARKERS = ("circle", "square", "diamond", "triangle", "circle", "square", "diamond")
CSP = "default-src 'none'; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"
CSS = """body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;
margin:2rem auto;max-width:1000px;padding:0 1rem;color:#222;overflow-wrap:break-word}
.scroll{overflow-x:auto;max-width:100%}svg{max-width:100%;height:auto}
table{border-collapse:collapse;margin:1rem 0;font-variant-numeric:tabular-nums}
th,td{border-bottom:1px solid #ddd;padding:.25rem .6rem;text-align:right}
th:nth-child(-n+2),td:nth-child(-n+2),th:last-child,td:last-child{text-align:left}
tr.ref td{font-weight:600;background:#f3f6fa}tr.skip td{color:#707070}
.note{color:#555;max-width:60rem}svg text{font:11px system-ui,sans-serif}"""
W, H = 760, 440
LEFT, RIGHT, TOP, BOTTOM = 70, 170, 20, 50
ERROR_FLOOR = 1e-4   # the log error axis starts here; zero-error points (references) sit on it


def fmt(value: object, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if isinstance(value, bool):
        return "yes" if value else ""
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _n(v: float) -> str:
    s = f"{v:.1f}"
    return s[:-2] if s.endswith(".0") else s


def grid_ms(row: dict, grid_samples: int) -> float:
    """Time of the row's whole map per sample of the config's grid (= time per sample for the
    knobs that score the same samples; fewer or more samples for step and budget)."""
    return row["map_time_s"] * 1e3 / grid_samples


def pareto(points: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """Points no other point beats in both time and error, fastest first."""
    front, best = [], math.inf
    for x, y in sorted(points):
        if y < best:
            front.append((x, y))
            best = y
    return front


def _marker(kind: str, x: float, y: float, colour: str, hollow: bool) -> str:
    fill = "#fff" if hollow else colour
    style = f'fill="{fill}" stroke="{colour}" stroke-width="1.5"'
    if kind == "square":
        return f'<rect x="{_n(x - 4)}" y="{_n(y - 4)}" width="8" height="8" {style}/>'
    if kind == "diamond":
        return (f'<polygon points="{_n(x)},{_n(y - 5)} {_n(x + 5)},{_n(y)} {_n(x)},{_n(y + 5)} '
                f'{_n(x - 5)},{_n(y)}" {style}/>')
    if kind == "triangle":
        return (f'<polygon points="{_n(x)},{_n(y - 5)} {_n(x + 5)},{_n(y + 4)} '
                f'{_n(x - 5)},{_n(y + 4)}" {style}/>')
    return f'<circle cx="{_n(x)}" cy="{_n(y)}" r="4.5" {style}/>'


def plot(rows: Sequence[dict], grid_samples: int) -> str:
    """Inline SVG: time per grid sample (x) against the map's mean absolute error (y), both
    log scale; each knob's settings joined in table order, the Pareto front dashed."""
    pts = [r for r in rows if r["map_time_s"] is not None and r["map_mean_abs_error"] is not None]
    if not pts:
        return "<p>No measured rows to plot.</p>"
    xs = [math.log10(max(grid_ms(r, grid_samples), 1e-6)) for r in pts]
    ys = [math.log10(max(r["map_mean_abs_error"], ERROR_FLOOR)) for r in pts]
    x0, x1 = min(xs) - 0.1, max(xs) + 0.1
    # y1 a whole decade, at least two above the floor (an int: errors all under 0.01 too)
    y0 = math.log10(ERROR_FLOOR)
    y1 = max(math.ceil(max(ys)), round(y0) + 2)
    pw, ph = W - LEFT - RIGHT, H - TOP - BOTTOM

    def px(lx: float) -> float:
        return LEFT + (lx - x0) / (x1 - x0) * pw

    def py(ly: float) -> float:
        return TOP + ph - (ly - y0) / (y1 - y0) * ph

    out = [f'<svg width="{W}" height="{H}" viewBox="0 0 {W} {H}" role="img" '
           'aria-label="time per sample against mIoU-map error, one series per knob">',
           f'<rect x="{LEFT}" y="{TOP}" width="{pw}" height="{ph}" fill="none" stroke="#999"/>']
    for e in range(math.floor(x0), math.ceil(x1) + 1):
        for m in (1, 2, 5):
            lx = e + math.log10(m)
            if x0 <= lx <= x1:
                out.append(f'<line x1="{_n(px(lx))}" x2="{_n(px(lx))}" y1="{TOP}" '
                           f'y2="{TOP + ph}" stroke="#eee"/><text x="{_n(px(lx))}" '
                           f'y="{TOP + ph + 15}" text-anchor="middle">{esc(f"{10 ** lx:g}")}'
                           '</text>')
    for e in range(round(y0), y1 + 1):
        label = f"≤{10.0 ** e:g}" if e == round(y0) else f"{10.0 ** e:g}"
        out.append(f'<line x1="{LEFT}" x2="{LEFT + pw}" y1="{_n(py(e))}" y2="{_n(py(e))}" '
                   f'stroke="#eee"/><text x="{LEFT - 6}" y="{_n(py(e) + 4)}" '
                   f'text-anchor="end">{esc(label)}</text>')
    out.append(f'<text x="{LEFT + pw / 2:.0f}" y="{H - 10}" text-anchor="middle">ms per grid '
               'sample (map time ÷ samples in the config grid; log scale)</text>')
    out.append(f'<text transform="translate(16 {TOP + ph / 2:.0f}) rotate(-90)" '
               'text-anchor="middle">mean |ΔmIoU| per cell vs reference (log)</text>')
    front = pareto(list(zip(xs, ys, strict=True)))
    if len(front) > 1:
        path = " ".join(f"{_n(px(x))},{_n(py(y))}" for x, y in front)
        out.append(f'<polyline points="{path}" fill="none" stroke="#888" '
                   'stroke-dasharray="4 3"/>')
    knobs = list(dict.fromkeys(r["knob"] for r in pts))
    for i, knob in enumerate(knobs):
        colour, kind = COLOURS[i % len(COLOURS)], MARKERS[i % len(MARKERS)]
        series = [(x, y, r) for x, y, r in zip(xs, ys, pts, strict=True) if r["knob"] == knob]
        line = " ".join(f"{_n(px(x))},{_n(py(y))}" for x, y, _ in series)
        out.append(f'<g><title>{esc(knob)}</title><polyline points="{line}" fill="none" '
                   f'stroke="{colour}" stroke-opacity=".5"/>')
        for x, y, r in series:
            out.append(f'<g><title>{esc(knob)} {esc(r["setting"])}: '
                       f'{grid_ms(r, grid_samples):.1f} ms, error '
                       f'{r["map_mean_abs_error"]:.4f}</title>'
                       + _marker(kind, px(x), py(y), colour, r["is_reference"])
                       + f'<text x="{_n(px(x) + 7)}" y="{_n(py(y) - 6)}" fill="#555" '
                       f'font-size="9">{esc(r["setting"])}</text></g>')
        ly = TOP + 10 + 18 * i
        out.append(_marker(kind, LEFT + pw + 18, ly, colour, False)
                   + f'<text x="{LEFT + pw + 30}" y="{ly + 4}">{esc(knob)}</text></g>')
    ly = TOP + 10 + 18 * len(knobs)
    out.append(_marker("circle", LEFT + pw + 18, ly, "#555", True)
               + f'<text x="{LEFT + pw + 30}" y="{ly + 4}">reference</text>'
               f'<line x1="{LEFT + pw + 10}" x2="{LEFT + pw + 26}" y1="{ly + 18}" '
               f'y2="{ly + 18}" stroke="#888" stroke-dasharray="4 3"/>'
               f'<text x="{LEFT + pw + 30}" y="{ly + 22}">Pareto front</text></svg>')
    return "\n".join(out)


COLUMNS = (("knob", "knob"), ("setting", "setting"), ("is_reference", "reference"),
           ("time_per_sample_ms", "ms / sample"), ("speedup", "speedup"),
           ("map_mean_abs_error", "mean |Δ|"), ("map_max_abs_error", "max |Δ|"),
           ("blind_spot_jaccard", "blind-spot Jaccard"), ("blind_spots", "blind spots"),
           ("samples", "samples"), ("notes", "notes"))


def table(rows: Sequence[dict]) -> str:
    head = "".join(f"<th>{esc(label)}</th>" for _, label in COLUMNS)
    body = []
    for r in rows:
        cls = "ref" if r["is_reference"] else "skip" if r["time_per_sample_ms"] is None else ""
        cells = "".join(f"<td>{esc(fmt(r[key], 1 if key == 'time_per_sample_ms' else 3))}</td>"
                        for key, _ in COLUMNS)
        body.append(f'<tr class="{cls}">{cells}</tr>')
    return (f'{scroll_open("Speed and map error per setting")}<table><thead><tr>{head}</tr></thead>'
            f"<tbody>{''.join(body)}</tbody></table></div>")


def render(summary: dict) -> str:
    """The page for a `falsify tradeoff` summary (its JSON)."""
    ref = summary["reference"]
    notes = "".join(f"<li>{esc(n)}</li>" for n in summary.get("notes", []))
    machine = summary.get("machine", {})
    return f"""{head(f"falsify tradeoff: {esc(summary['config'])}", CSP, CSS)}
<body><main>
<h1>Speed against mIoU-map error</h1>
<p class="note">Config {esc(summary["config"])}, {esc(summary["samples"])} samples
(limit {esc(fmt(summary.get("limit")))}), model {esc(Path(summary["model"]).name)}
({esc(summary["model_hash"][:12])}), blind-spot threshold {esc(summary["threshold"])}.
Reference: {esc(ref["resolution"])} native scan, LOD {esc(ref["lod"])}, {esc(ref["precision"])},
CRF {esc(ref["crf"])} iterations, {esc(ref["grid"])} grid: {esc(ref["time_per_sample_ms"])} ms
per sample, {esc(ref["blind_spots"])} blind spots (lowest cell mIoU
{esc(fmt(ref.get("lowest_cell_miou")))}). Times: scan + inference per sample in one
process, {esc(summary["threads"])} inference threads, {esc(summary["batch"])} samples per call (the
network takes them one frame at a time), after a warm-up, on {esc(machine.get("cpus", "?"))}
CPUs ({esc(machine.get("processor", ""))}).</p>
<p class="note">Each knob is varied alone. Errors are per (x, y) cell of the mIoU map against the
knob's reference (the grid-step knob: the 0.5 m grid, coarser maps upsampled by nearest cell;
the budget knob: the full grid, empty cells filled from the nearest sampled cell). The Jaccard
index compares the blind-spot sets (1 = the same cells, also when both are empty).</p>
{plot(summary["rows"], summary["samples"])}
{table(summary["rows"])}
{f"<ul class='note'>{notes}</ul>" if notes else ""}
</main></body>
</html>
"""


def write_page(summary: dict, path: str | Path) -> Path:
    """Write the page atomically; returns its path."""
    path = Path(path)
    write_text(path, render(summary))
    return path
