"""The `falsify realism` page: synthetic sets beside real scans, one self-contained HTML file.

Drawn from the realism JSON alone (so the page can be re-made from the JSON): a table of the
distances (lower is closer), the same against each real scan alone, the sets' summary figures,
per-class fractions over SemanticKITTI's classes where sets carry those labels, and inline SVG
charts of the per-row valid fraction and the range, height and intensity histograms. No
script, no fetch (a Content-Security-Policy forbids any), every user string escaped, fixed
number formats.
"""

from __future__ import annotations

from falsify.reports.charts import FONT
from falsify.reports.page import esc, head, scroll_open

# Nothing but inline styles and data: images; this page has no script at all.
CSP = ("default-src 'none'; img-src data:; style-src 'unsafe-inline'; base-uri 'none'; "
       "form-action 'none'")

# Okabe-Ito: colour-blind safe. Synthetic sets take the first colours, real sets the last.
SYN_COLOURS = ("#d55e00", "#0072b2", "#cc79a7", "#e69f00", "#56b4e9")
REAL_COLOURS = ("#009e73", "#000000", "#999999", "#f0e442")
W, H, PAD_L, PAD_B, PAD_T, PAD_R = 600, 260, 56, 40, 14, 12
PER_SCAN_ROWS = 50   # real scans listed one by one on the page (all of them in the JSON)


def _n(v: float) -> str:
    s = f"{v:.1f}"
    return s[:-2] if s.endswith(".0") else s


def _fmt(v: object, digits: int = 3) -> str:
    return "—" if v is None else f"{float(v):.{digits}f}"


def _series(doc: dict) -> list[tuple[str, dict, str, str]]:
    """(label, stats, colour, dash) for each set drawn: synthetic sets, then real sets."""
    out = [(f"synthetic: {s['name']}", s, SYN_COLOURS[i % len(SYN_COLOURS)], "")
           for i, s in enumerate(doc["synthetic"])]
    parts = " + ".join(r["name"] for r in doc["real"] if r["name"] != doc["real_pooled"])
    for i, s in enumerate(doc["real"]):
        pooled = s["name"] == doc["real_pooled"] and len(doc["real"]) > 1
        out.append((f"real: {s['name']}" + (f" ({parts})" if pooled else ""), s,
                    REAL_COLOURS[i % len(REAL_COLOURS)], "" if pooled else "5 3"))
    return out


def line_chart(ident: str, title: str, xs: list[float], lines: list[tuple[str, list[float],
               str, str]], xlabel: str, ylabel: str) -> str:
    """An SVG line chart; each line is (label, ys, colour, dash) with a <title> for hovering."""
    x0, x1 = min(xs), max(xs)
    top = max((max(ys) for _, ys, _, _ in lines), default=1.0) or 1.0
    pw, ph = W - PAD_L - PAD_R, H - PAD_T - PAD_B

    def px(x: float) -> float:
        return PAD_L + (x - x0) / ((x1 - x0) or 1.0) * pw

    def py(y: float) -> float:
        return PAD_T + ph - y / top * ph

    parts = [f'<svg id="{esc(ident)}" class="chart" viewBox="0 0 {W} {H}" width="{W}" '
             f'height="{H}" role="img" aria-label="{esc(title)}">',
             f'<rect x="{PAD_L}" y="{PAD_T}" width="{pw}" height="{ph}" class="plot"/>']
    for k in range(5):
        yv = top * k / 4
        parts.append(f'<line x1="{PAD_L}" x2="{PAD_L + pw}" y1="{_n(py(yv))}" '
                     f'y2="{_n(py(yv))}" class="grid"/>'
                     f'<text x="{PAD_L - 4}" y="{_n(py(yv) + 4)}" class="tick" '
                     f'text-anchor="end">{yv:.3g}</text>')
        xv = x0 + (x1 - x0) * k / 4
        parts.append(f'<text x="{_n(px(xv))}" y="{PAD_T + ph + 14}" class="tick" '
                     f'text-anchor="middle">{xv:.3g}</text>')
    parts.append(f'<text x="{PAD_L + pw / 2}" y="{H - 6}" class="axis" '
                 f'text-anchor="middle">{esc(xlabel)}</text>'
                 f'<text x="12" y="{PAD_T + ph / 2}" class="axis" text-anchor="middle" '
                 f'transform="rotate(-90 12 {PAD_T + ph / 2})">{esc(ylabel)}</text>')
    for label, ys, colour, dash in lines:
        pts = " ".join(f"{_n(px(x))},{_n(py(y))}" for x, y in zip(xs, ys, strict=True))
        dash_attr = f' stroke-dasharray="{dash}"' if dash else ""
        parts.append(f'<polyline class="series" points="{pts}" stroke="{colour}"{dash_attr}>'
                     f'<title>{esc(label)}</title></polyline>')
    parts.append("</svg>")
    return "".join(parts)


def legend(series: list[tuple[str, dict, str, str]]) -> str:
    items = "".join(
        f'<li><svg width="28" height="10" aria-hidden="true"><line x1="0" x2="28" y1="5" '
        f'y2="5" stroke="{c}" '
        f'stroke-width="2.5"{f" stroke-dasharray={chr(34)}{d}{chr(34)}" if d else ""}/></svg> '
        f'{esc(label)}</li>' for label, _, c, d in series)
    return f'<ul class="legend">{items}</ul>'


def distance_table(doc: dict) -> str:
    """Statistic rows; a column per (synthetic set, real set); ✓ where a later synthetic set is
    closer to the pooled real scans than the first."""
    pooled = doc["real_pooled"]
    reals = [pooled] + [r["name"] for r in doc["real"] if r["name"] != pooled]
    comp = doc.get("comparison") or {}
    boot = doc.get("bootstrap")
    head = "".join(f'<th>{esc(s["name"])}<br><span class="sub">vs {esc(r)}</span></th>'
                   for s in doc["synthetic"] for r in reals)
    rows = []
    for key, info in doc["statistics"].items():
        cells = []
        for s in doc["synthetic"]:
            for r in reals:
                value = doc["distances"][s["name"]][r][key]
                mark = ""
                cand = comp.get("candidates", {}).get(s["name"])
                if cand is not None and r == pooled:
                    mark = (' <span class="yes">✓ closer</span>' if cand["closer"][key]
                            else ' <span class="no">✗ not closer</span>')
                interval = ""
                if boot and r == pooled:
                    span = boot["intervals"][s["name"]][key]
                    interval = ('<br><span class="sub">no draw defined</span>' if span is None
                                else f'<br><span class="sub">{span[0]:.4f}-{span[1]:.4f}</span>')
                    share = boot["closer_share"].get(s["name"], {}).get(key)
                    if cand is not None and share is not None:
                        interval += (f'<br><span class="sub">closer in {share:.0%} of draws'
                                     '</span>')
                cells.append(f'<td class="num" data-stat="{esc(key)}">{value:.4f}{mark}'
                             f'{interval}</td>')
        rows.append(f'<tr><th scope="row">{esc(key)}<br><span class="sub">{esc(info["what"])} '
                    f'({esc(info["unit"])})</span></th>{"".join(cells)}</tr>')
    # each synthetic set's floor: the Fréchet estimator between two samples of itself
    if doc["synthetic"] and all(s.get("frechet_floor") for s in doc["synthetic"]):
        cells = []
        for s in doc["synthetic"]:
            f = s["frechet_floor"]
            cells.append(f'<td class="num" data-floor="{esc(s["name"])}">{f["mean"]:.4f}'
                         f'<br><span class="sub">max {f["max"]:.4f}</span></td>'
                         + '<td class="num">—</td>' * (len(reals) - 1))
        n = doc["synthetic"][0]["frechet_floor"]["scans"]
        rows.append(f'<tr><th scope="row">frechet floor<br><span class="sub">the same '
                    f'estimator between {n} random scans of the set and the rest (mean of '
                    f'{doc["synthetic"][0]["frechet_floor"]["draws"]} draws): what sampling '
                    f'alone gives</span></th>{"".join(cells)}</tr>')
    for key, info in doc.get("reference_statistics", {}).items():
        cells = [f'<td class="num" data-ref="{esc(key)}">'
                 f'{doc["distances"][s["name"]][r][key]:.4f}</td>'
                 for s in doc["synthetic"] for r in reals]
        rows.append(f'<tr><th scope="row">{esc(key)} (reference, not compared)<br>'
                    f'<span class="sub">{esc(info["what"])} ({esc(info["unit"])})</span></th>'
                    f'{"".join(cells)}</tr>')
    verdict = ""
    for name, cand in comp.get("candidates", {}).items():
        k, n = sum(cand["closer"].values()), len(cand["closer"])
        every = " (every one)" if cand["closer_on_every_statistic"] else ""
        verdict += (f'<p class="verdict">{esc(name)} is closer to the real scans than '
                    f'{esc(comp["baseline"])} on <b>{k} of {n}</b> statistics{every}.</p>')
    if boot:
        lo, hi = boot["levels"]
        verdict += (f'<p class="sub" id="bootstrap">Under each distance to the pooled real '
                    f'scans: its {lo:g}-{hi:g} % range over {boot["draws"]} resamples of the '
                    'scans (seeded; real scans drawn within each real set), and for a later '
                    'set the share of those draws in which it is closer than the first, both '
                    'against the same real draw.'
                    + "".join(f" {n} of the draws of {esc(name)} held only blank scans and "
                              "give no distance." for name, n in
                              boot.get("undefined_draws", {}).items() if n)
                    + '</p>')
    return (f'<section id="distances"><h2>Distances (lower is closer)</h2>{verdict}'
            f'{scroll_open("Distances")}<table><thead><tr><th>statistic</th>{head}</tr>'
            f'</thead><tbody>{"".join(rows)}</tbody></table></div></section>')


def per_scan_table(doc: dict) -> str:
    """A row per real scan, a column per synthetic set and statistic; for a later set ✓ where it
    is closer to that scan alone than the first set. Few real scans make a resample one of few
    combinations: this is where a candidate that is not closer in most draws is farther."""
    per = doc.get("per_real_scan")
    if not per or not per["scans"] or not doc["synthetic"]:
        return ""
    names = [s["name"] for s in doc["synthetic"]]
    stats = per["statistics"]
    base = names[0]
    shown = per["scans"][:PER_SCAN_ROWS]
    more = (f' The first {PER_SCAN_ROWS} of {len(per["scans"])} real scans are shown; the '
            'JSON holds all.' if len(per["scans"]) > PER_SCAN_ROWS else "")
    head = "".join(f'<th>{esc(n)}<br><span class="sub">{esc(k)}</span></th>'
                   for n in names for k in stats)
    rows = []
    for scan in shown:
        cells = []
        for n in names:
            for k in stats:
                v, b = scan["distances"][n][k], scan["distances"][base][k]
                mark = ""
                if n != base and v is not None and b is not None:   # None: a scan unlabelled
                    mark = (' <span class="yes">✓</span>' if v < b
                            else ' <span class="no">✗</span>')
                cells.append(f'<td class="num" data-scan-stat="{esc(k)}">{_fmt(v, 4)}{mark}'
                             '</td>')
        real_set = per["real_sets"][scan["real_set"]]
        rows.append(f'<tr><th scope="row">{esc(scan["source"])}<br><span class="sub">'
                    f'{esc(real_set)}</span></th>{"".join(cells)}</tr>')
    return (f'<section id="per-scan"><h2>Against each real scan alone</h2><p class="note">The '
            f'same distances against one real scan at a time (all but the feature distance, '
            f'whose estimator needs many scans). With few real scans a resample of them is one '
            f'of few combinations, so a set farther from one scan is farther on the draws that '
            f'scan dominates.{more}</p>{scroll_open("Distances against each real scan")}'
            f'<table><thead><tr><th>real scan</th>'
            f'{head}</tr></thead><tbody>{"".join(rows)}</tbody></table></div></section>')


def sets_table(doc: dict) -> str:
    classes = list(doc["synthetic"][0]["class_fraction"]) if doc["synthetic"] else []
    head = ("<th>set</th><th>scans</th><th>points</th><th>valid</th><th>mean range (m)</th>"
            "<th>mean z (m)</th><th>mean intensity</th>"
            + "".join(f"<th>{esc(c)}</th>" for c in classes)
            + "<th>feature samples (cells)</th><th>unlabelled scans</th>")
    rows = []
    for label, s, colour, _ in _series(doc):
        rows.append(
            f'<tr><th scope="row"><span class="swatch" style="background:{colour}"></span>'
            f'{esc(label)}</th><td class="num">{s["scans"]}</td><td class="num">{s["points"]}'
            f'</td><td class="num">{_fmt(s["valid_fraction"])}</td>'
            f'<td class="num">{_fmt(s["mean_range"], 2)}</td>'
            f'<td class="num">{_fmt(s["mean_height"], 2)}</td>'
            f'<td class="num">{_fmt(s["mean_intensity"])}</td>'
            + "".join(f'<td class="num">{_fmt(s["class_fraction"][c], 4)}</td>' for c in classes)
            + f'<td class="num">{s["feature_samples"]}</td>'
            f'<td class="num">{len(s.get("unlabelled", []))}</td></tr>')
    real = doc["real"][:-1] if len(doc["real"]) > 1 else doc["real"]   # not the pooled set
    missing = [(s["name"], name) for s in [*real, *doc.get("reported", [])]
               for name in s.get("unlabelled", [])]
    named = ("" if not missing else " Scans without labels: " + ", ".join(
        f"{esc(name)} ({esc(set_name)})" for set_name, name in missing[:PER_SCAN_ROWS])
        + (f" and {len(missing) - PER_SCAN_ROWS} more (the JSON lists all)"
           if len(missing) > PER_SCAN_ROWS else "") + ".")
    return (f'<section id="sets"><h2>Sets</h2><p class="note">Valid: fraction of pixels with a '
            f'return; class columns: fraction of valid points of the labelled scans; unlabelled: '
            f'scans whose labels were not found, counted in all but the class columns.{named}'
            f'</p>{scroll_open("Sets")}<table>'
            f'<thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table></div>'
            '</section>')


def semantic_table(doc: dict) -> str:
    """A row per SemanticKITTI class, a column per set: its fraction of the set's labelled
    points ("—" for a set without SemanticKITTI labels); then the unlabeled share and each
    synthetic set's total variation to the pooled real scans. Empty when no set has them."""
    series = _series(doc)
    if not any("semantic_fraction" in s for _, s, _, _ in series):
        return ""
    classes = next(list(s["semantic_fraction"]) for _, s, _, _ in series
                   if "semantic_fraction" in s)
    head = "".join(f'<th><span class="swatch" style="background:{colour}"></span>'
                   f'{esc(label)}</th>' for label, _, colour, _ in series)

    def row(title: str, attr: str, values: list[object], digits: int = 4) -> str:
        cells = "".join(f'<td class="num">{_fmt(v, digits)}</td>' for v in values)
        return f'<tr><th scope="row" {attr}>{title}</th>{cells}</tr>'

    rows = [row(esc(c), f'data-class="{esc(c)}"',
                [s.get("semantic_fraction", {}).get(c) for _, s, _, _ in series])
            for c in classes]
    rows.append(row('unlabeled<br><span class="sub">fraction of all valid points</span>',
                    'data-class="unlabeled"',
                    [s.get("unlabeled_fraction") for _, s, _, _ in series]))
    pooled = doc["real_pooled"]
    tv = [doc["distances"].get(s["name"], {}).get(pooled, {}).get("semantic_classes")
          if i < len(doc["synthetic"]) else None for i, (_, s, _, _) in enumerate(series)]
    if any(v is not None for v in tv):
        rows.append(row(f'total variation<br><span class="sub">against {esc(pooled)}; '
                        'diagnostic, not compared</span>', 'data-tv="semantic_classes"', tv))
    return (f'<section id="semantic"><h2>SemanticKITTI classes</h2><p class="note">Fraction '
            f'of labelled points per class ({len(classes)} classes; unlabeled points are left '
            f'out and their share of all valid points is given below). Synthetic sets written '
            f'with <code>--labels semantickitti</code>, real scans with .label files.</p>'
            f'{scroll_open("SemanticKITTI classes")}<table><thead><tr><th>class</th>{head}'
            f'</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table></div></section>')


def charts(doc: dict) -> str:
    series = _series(doc)
    bins = doc["bins"]

    def centres(edges: list[float]) -> list[float]:
        return [(a + b) / 2 for a, b in zip(edges[:-1], edges[1:], strict=True)]

    rows = list(range(len(doc["synthetic"][0]["row_valid"]))) if doc["synthetic"] else [0]
    specs = [
        ("row-valid", "Valid fraction per row (row 0 is the top beam)", rows, "row_valid",
         "row", "valid fraction"),
        ("range-hist", "Range of valid points", centres(bins["range"]), "range_hist",
         "range (m)", "fraction of points"),
        ("height-hist", "Height (sensor-frame z) of valid points", centres(bins["height"]),
         "height_hist", "z (m)", "fraction of points"),
        ("intensity-hist", "Intensity of valid points", centres(bins["intensity"]),
         "intensity_hist", "intensity", "fraction of points"),
    ]
    figs = []
    for ident, title, xs, key, xl, yl in specs:
        lines = [(label, s[key], c, d) for label, s, c, d in series]
        figs.append(f'<figure><figcaption>{esc(title)}</figcaption>'
                    f'{line_chart(ident, title, xs, lines, xl, yl)}</figure>')
    return f'<section id="charts"><h2>Statistics</h2>{legend(series)}{"".join(figs)}</section>'


CSS = f"""
body {{ font-family: {FONT}; margin: 24px; color: #222; background: #fff;
       overflow-wrap: break-word; }}
.scroll {{ overflow-x: auto; max-width: 100%; }}
figure {{ max-width: 100%; }} figure svg {{ max-width: 100%; height: auto; }}
h1 {{ font-size: 22px; margin: 0 0 4px; }} h2 {{ font-size: 17px; margin: 24px 0 8px; }}
.meta, .note, .sub {{ color: #555; font-size: 12px; }}
table {{ border-collapse: collapse; font-size: 13px; }}
th, td {{ border: 1px solid #ddd; padding: 4px 8px; text-align: left; vertical-align: top; }}
td.num {{ text-align: right; font-variant-numeric: tabular-nums; }}
.yes {{ color: #006d2c; font-weight: 600; }} .no {{ color: #b30000; font-weight: 600; }}
.swatch {{ display: inline-block; width: 10px; height: 10px; margin-right: 6px;
           print-color-adjust: exact; -webkit-print-color-adjust: exact; }}
figure {{ display: inline-block; margin: 8px 16px 8px 0; }}
figcaption {{ font-size: 13px; font-weight: 600; margin-bottom: 4px; }}
.chart .plot {{ fill: #fafafa; stroke: #bbb; }} .chart .grid {{ stroke: #e6e6e6; }}
.chart .tick {{ font-size: 10px; fill: #555; }} .chart .axis {{ font-size: 11px; fill: #333; }}
.chart .series {{ fill: none; stroke-width: 2; }}
.legend {{ list-style: none; padding: 0; font-size: 13px; }}
.legend li {{ display: inline-block; margin-right: 18px; }}
.verdict {{ font-size: 14px; }}
@media print {{ .scroll {{ overflow: visible; }} figure, tr {{ break-inside: avoid; }}
  h2 {{ break-after: avoid; }} }}
"""


def reported_table(doc: dict) -> str:
    """Distances to the real sets only reported on (the evaluation split): never pooled, never
    compared. Empty when there are none."""
    names = [r["name"] for r in doc.get("reported", [])]
    if not names:
        return ""
    head = "".join(f'<th>{esc(s["name"])}<br><span class="sub">vs {esc(r)}</span></th>'
                   for s in doc["synthetic"] for r in names)
    rows = "".join(
        f'<tr><th scope="row">{esc(key)}</th>' + "".join(
            f'<td class="num">{doc["distances"][s["name"]][r][key]:.4f}</td>'
            for s in doc["synthetic"] for r in names) + '</tr>'
        for key in doc["statistics"])
    return ('<section id="reported"><h2>Evaluation split (reported only)</h2><p class="note">'
            'The same distances to real places that are evaluation data: shown, never pooled '
            'into the reference and never used to compare or choose.</p>'
            f'{scroll_open("Evaluation split distances")}<table><thead><tr>'
            f'<th>statistic</th>{head}</tr></thead><tbody>{rows}</tbody></table></div></section>')


def render_realism(doc: dict) -> str:
    """The page for a realism JSON document (as `Realism.to_json()` makes it)."""
    feat = doc["feature"]
    meta = (f'model {esc(doc["model"])} ({esc(str(doc["model_hash"])[:12])}); features: '
            f'{esc(feat["tensor"])}, {esc(feat["estimator"])}: {esc(feat["samples"])} '
            f'({esc(feat["why"])}); frechet_tiles: {int(feat["tiles"][0])}×'
            f'{int(feat["tiles"][1])} tile means per scan')
    return (
        head("falsify realism: synthetic against real scans", CSP, CSS) + '<body><main>'
        '<h1>Realism: synthetic against real LiDAR scans</h1>'
        f'<p class="meta">{meta}</p>'
        f'{distance_table(doc)}{reported_table(doc)}{per_scan_table(doc)}{sets_table(doc)}'
        f'{semantic_table(doc)}'
        f'{charts(doc)}'
        '</main></body></html>\n')
