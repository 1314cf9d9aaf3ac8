"""The report job: open a run (and the run it is compared with), replay its worst samples'
scans and predictions, and hand all of it to the HTML renderer, which only draws."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from falsify.errors import FalsifyError
from falsify.fileio import write_text
from falsify.jobs.explain import explain_data
from falsify.models.runners import Segmenter, load_segmenter
from falsify.reports.run import WORST, ReplayedScan, ReportInput, render
from falsify.results.explain import MIN_SUPPORT, Explanation, score_name
from falsify.results.replay import Replay
from falsify.results.store import Completeness, RunData, open_run


def open_model(meta: dict, predict: bool, model: Segmenter | None = None,
               device: str = "cpu") -> tuple[Segmenter | None, str]:
    """The run's model (the one given, else loaded from the run's metadata onto `device`) if
    `predict` and it loads; else None and a note saying why."""
    if not predict:
        return None, "Previews show labels only (--no-predict)."
    if model is None:
        try:
            model = load_segmenter(meta.get("model_path"), backend=meta.get("backend") or "onnx",
                                   device=device)
        except Exception as exc:  # any failure: the report is still useful without predictions
            return None, f"Model not loaded ({exc}); previews show labels only."
    note = ""
    have, want = model.model_hash, meta.get("model_hash")
    if have and want and have != want:
        note = (f"The model found now (hash {str(have)[:12]}) is not the run's "
                f"({str(want)[:12]}); predictions may differ from the scores.")
    return model, note


def run_lod(meta: dict) -> int:
    """The car level of detail a run scanned with: its meta's `lod`; for runs that predate it,
    its preset's (as presets are defined now); else the full mesh."""
    if isinstance(meta.get("lod"), int):
        return int(meta["lod"])
    from falsify.jobs.fidelity import PRESETS

    fid = PRESETS.get(str(meta.get("fidelity") or "exact"))
    return fid.lod if fid is not None else 2


def replay_worst(data: RunData, worst: int, predict: bool, model: Segmenter | None = None,
                 device: str = "cpu") -> tuple[dict[int, ReplayedScan], str]:
    """Re-cast the worst rows (grouped by background to reuse BVHs) and predict them."""
    rows = data.worst(worst)
    if not len(rows):
        return {}, ""
    seg, note = open_model(data.meta, predict, model, device)
    try:
        replay = Replay(data.space, lod=run_lod(data.meta))
    except Exception as exc:
        return {}, f"Scans could not be regenerated ({exc})."
    out: dict[int, ReplayedScan] = {}
    order = rows.sort_values(["background", "eval_index"], kind="stable") \
        if "background" in rows else rows
    for _, row in order.iterrows():
        ev = int(row["eval_index"])
        try:
            sample, scan = replay.scan(row)
        except Exception as exc:
            out[ev] = ReplayedScan(None, error=f"scan not regenerated: {exc}")
            continue
        car = (float(sample.cars[0].x), float(sample.cars[0].y))
        classes, error = None, ""
        if seg is not None:
            try:
                classes = seg.predict(scan.image[None]).classes[0]
            except Exception as exc:
                error = f"prediction failed: {exc}"
        out[ev] = ReplayedScan(scan.image, car, classes, error)
    return out, note


def explain_report(data: RunData) -> Explanation | str:
    """The run's explanation as `falsify explain RUN` computes it (its defaults, seed 0), with
    clusters for non-grid runs only (as its text does); else one line saying why there is none."""
    try:   # an incomplete run is explained too: the page says so
        result = explain_data(data, seed=0)
    except FalsifyError as exc:   # the report is still useful without it
        return f"The failing samples could not be explained ({exc})."
    e = result.explanation
    if e.samples < MIN_SUPPORT:
        return (f"Too few valid samples to explain ({e.samples}; a rule needs at least "
                f"{MIN_SUPPORT}).")
    if not e.failing:
        return (f"No valid sample has {score_name(e.score)} below the threshold "
                f"{e.threshold:.3f}: nothing to explain.")
    return e if result.algorithm != "grid" else dataclasses.replace(e, clusters=())


def space_differences(before: RunData, after: RunData) -> tuple[str, ...]:
    """What, besides the model and the x-y cells, differs between two runs' spaces, a line
    each: a comparison across them mixes the network's change with the scenes'."""
    out = []
    b, a = before.space, after.space

    def shown(values) -> str:
        vals = [str(v) for v in values]
        return ", ".join(vals[:6]) + (f", ... ({len(vals)} values)" if len(vals) > 6 else "")

    def backgrounds(data: RunData) -> list[str]:
        return [data.space.background_name(int(v)) for v in data.space.dims["background"].grid()]

    for name in sorted((set(b.dims) | set(a.dims)) - {"x", "y"}):
        if name not in a.dims or name not in b.dims:
            has, lacks = ("before", "after") if name in b.dims else ("after", "before")
            out.append(f"dim {name}: in the run {has} only, not {lacks}")
            continue
        bv, av = (backgrounds(d) for d in (before, after)) if name == "background" else (
            list(b.dims[name].grid()), list(a.dims[name].grid()))
        if bv != av:
            out.append(f"{name}: before {shown(bv)}; after {shown(av)}")
    if b.sensor != a.sensor:
        out.append(f"sensor: before {b.sensor}; after {a.sensor}")
    if before.score_column != after.score_column:
        out.append(f"objective: before {before.score_column}; after {after.score_column}")
    if before.threshold != after.threshold:
        out.append(f"threshold: before {before.threshold}; after {after.threshold}")
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class WrittenReport:
    """A report written: where, what differs from the run compared with, how complete the run
    is (what the command says beside the page)."""

    path: Path
    differences: tuple[str, ...]
    completeness: Completeness


def report_input(run: Path, compare: Path | None = None, predict: bool = True,
                 worst: int = WORST, model: Segmenter | None = None,
                 retrain: dict | None = None, device: str = "cpu") -> ReportInput:
    """Everything the report of `run` draws, each run opened once; `retrain` (a `falsify
    retrain` summary, with `compare`) adds the experiment's section; `device` is where the
    run's model predicts the previews when it is loaded here."""
    data = open_run(run)
    before = open_run(compare) if compare is not None else None
    scans, note = replay_worst(data, worst, predict, model, device)
    return ReportInput(data, before, scans, note, worst, retrain, explain_report(data),
                       () if before is None else space_differences(before, data))


def render_report(run: Path, compare: Path | None = None, predict: bool = True,
                  worst: int = WORST, model: Segmenter | None = None,
                  retrain: dict | None = None, device: str = "cpu") -> str:
    """The report of `run` as one self-contained HTML string (deterministic for its inputs)."""
    return render(report_input(run, compare, predict, worst, model, retrain, device))


def write_report_of(run: Path, out: Path | None = None, compare: Path | None = None,
                    predict: bool = True, model: Segmenter | None = None,
                    retrain: dict | None = None, device: str = "cpu") -> WrittenReport:
    """Render and write the report atomically (default RUN/report.html)."""
    report = report_input(Path(run), None if compare is None else Path(compare), predict,
                          model=model, retrain=retrain, device=device)
    path = Path(out) if out is not None else Path(run) / "report.html"
    if path.is_dir():
        raise FalsifyError(f"--out {path}: is a directory")
    try:
        write_text(path, render(report))
    except OSError as exc:
        raise FalsifyError(f"--out {path}: cannot write ({exc.strerror})") from None
    return WrittenReport(path, report.differences, report.run.completeness)


def write_report(run: Path, out: Path | None = None, compare: Path | None = None,
                 predict: bool = True, model: Segmenter | None = None,
                 retrain: dict | None = None, device: str = "cpu") -> Path:
    """write_report_of's path."""
    return write_report_of(run, out, compare, predict, model, retrain, device).path
