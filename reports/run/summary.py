"""The run report's summary cards: model, config, sensor, sample counts, blind spots, the
worst cell and sample, and the run's time."""

from __future__ import annotations

import re
from collections import Counter

import numpy as np

from falsify.reports.charts import f3
from falsify.reports.page import esc
from falsify.reports.run.common import bg_text, dim_text
from falsify.results.metrics import Status
from falsify.results.miou_maps import CellMap, axis_texts
from falsify.results.store import RunData


def sensor_text(meta: dict, fallback: str) -> str:
    """The sensor's name, then its grid and the preset or file it came from (runs that
    recorded them): two sensor files may share a name."""
    name = esc(meta.get("sensor", fallback))
    shape, source = meta.get("sensor_shape"), meta.get("sensor_source")
    if not shape or source is None:
        return name
    where = "a bundled preset" if source == meta.get("sensor") else esc(source)
    return f'{name}<br><span class="note">{int(shape[0])} x {int(shape[1])} · {where}</span>'


def samples_text(data: RunData) -> str:
    """Rows and valid rows; for a run that may not have ended, of how many it planned."""
    done = data.completeness
    text = f"{done.samples} ({len(data.ok)} valid)"
    if done.complete is True or done.planned is None:
        return text
    text = f"{done.samples} of {done.planned} planned ({len(data.ok)} valid)"
    state = '<span class="bad">incomplete</span>' if done.complete is False else \
        '<span class="note">not known whether it ended</span>'
    return f"{text}<br>{state}"


def invalid_text(data: RunData, most: int = 3) -> str:
    """The invalid count and its commonest reasons, numbers folded ("car # (sedan) intersects the
    background's pole #"), so a run of mostly invalid samples says why on its first screen."""
    frame = data.frame
    bad = frame.loc[frame["status"] == Status.INVALID, "reason"]
    if not len(bad):
        return "0"
    kinds = Counter(re.sub(r"\d+", "#", str(r)) for r in bad.fillna("no reason recorded"))
    top = " · ".join(f"{n} {esc(k)}" for k, n in
                     sorted(kinds.items(), key=lambda kn: (-kn[1], kn[0]))[:most])
    more = f" · {len(kinds) - most} more kinds" if len(kinds) > most else ""
    return f'{len(bad)}<br><span class="note">{top}{more}</span>'


LIBRARIES = ("falsify", "python", "onnxruntime", "torch", "numpy", "embree", "trimesh", "pandas",
             "ray")


def environment_text(data: RunData) -> str:
    """What the run's rows were computed under (its latest environment): CPU, backend, device,
    inference threads, library versions; a run computed under several that may differ in its
    numbers says what changed."""
    env = data.environments[-1]
    threads = env.get("inference_threads")
    libs = " · ".join(f"{k} {esc(env[k])}" for k in LIBRARIES if env.get(k))
    text = (f"{esc(env.get('cpu') or 'unknown CPU')}<br><span class=\"note\">"
            f"{esc(env.get('backend'))} on {esc(env.get('device'))}"
            + ("" if threads is None else
               f", {esc(threads)} inference thread{'s' * (threads != 1)}")
            + f"<br>{libs}</span>")
    if changes := data.environment_changes:
        text += (f'<br><span class="bad">its rows mix environments that may differ in their '
                 f"numbers: {esc('; '.join(changes))}</span>")
    return text


def summary_section(data: RunData, cmap: CellMap, threshold: float) -> str:
    meta, frame = data.meta, data.frame
    status = frame["status"]
    ok = data.ok
    blind = cmap.blind_spots(threshold)
    scored = int((~np.isnan(cmap.miou)).sum())
    if len(ok):
        low = data.worst(1).iloc[0]
        lowest = (f"{f3(low[data.score_column])} at x = {dim_text(low, 'x')}, "
                  f"y = {dim_text(low, 'y')}"
                  f", background {esc(bg_text(data, low))} (eval {int(low['eval_index'])})")
    else:
        lowest = "—"
    scored_cells = sorted((c for c in cmap.cells() if c.miou is not None),
                          key=lambda c: (c.miou, str(c.a), str(c.b)))
    worst_cell = "—"
    if scored_cells:
        w = scored_cells[0]
        worst_cell = (f"{w.miou:.3f} at x = {axis_texts(cmap.a_values)[w.a]}, "
                      f"y = {axis_texts(cmap.b_values)[w.b]}")
    elapsed = meta.get("elapsed_s")
    took = []
    if isinstance(elapsed, int | float):
        took.append(f"{float(elapsed):.1f} s")
    if meta.get("workers"):
        took.append(f"{esc(meta['workers'])} worker{'s' * (meta['workers'] != 1)}")
    started = str(meta.get("started") or "—").replace("T", " ")
    timing = (f"{esc(started)}<br><span class=\"note\">"
              f"{' on '.join(took) or 'duration unknown'}</span>")
    model = f"{esc(meta.get('model_name', '—'))} <code>{esc(str(meta.get('model_hash') or '')[:12])}</code>"  # noqa: E501
    model_path = meta.get("model_path")
    search = str(meta.get("command", "")) or "—"
    if meta.get("algorithm") and meta["algorithm"] != meta.get("command"):   # not "grid · grid"
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
        ("Sensor", sensor_text(meta, data.space.sensor)),
        ("Run", esc(search)),
        ("Samples", samples_text(data)),
        ("Invalid samples", invalid_text(data)),
        ("Undefined samples", str(int((status == Status.UNDEFINED).sum()))),
        ("Blind spots", f'<span class="{"bad" if blind else ""}">{len(blind)}</span> of '
         f"{scored} cells (mIoU &lt; {threshold:.3f})"),
        ("Worst cell", worst_cell),
        ("Lowest IoU", lowest),
        ("Time", timing),
    ]
    if data.environments:
        items.append(("Computed on", environment_text(data)))
    cards = "".join(f"<div><dt>{k}</dt><dd>{v}</dd></div>" for k, v in items)
    return f'<section id="summary"><dl class="summary">{cards}</dl></section>'
