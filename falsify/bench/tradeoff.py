"""`falsify tradeoff`: what each speed knob costs in mIoU-map error, measured on one sample set.

Each knob (sensor resolution, car level of detail, inference precision and backend, CRF
iterations, grid step, sampler budget) is varied alone around one reference setting: the
network's own 64×512 scan, LOD 2, ONNX Runtime fp32, the model's CRF (3 iterations) and the
config's grid. A row says what one setting saves in time and what it changes in the x × y mIoU
map: mean and max absolute error per cell and agreement (Jaccard) of the blind-spot set.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from falsify.bench.knobs import KNOBS
from falsify.checks import MAX_SAMPLES, check_out_dir
from falsify.errors import FalsifyError
from falsify.models.spec import ModelSpec
from falsify.results.metrics import Status
from falsify.results.miou_maps import CellMap, MapError, fill_nearest, map_error, miou_map
from falsify.sensor.lidar import Sensor, SensorPose, load_sensor
from falsify.world.space import Categorical, Continuous, Sample, Space, load_space

if TYPE_CHECKING:   # kept out of the module's imports: trimesh
    from falsify.executors.evaluator import Evaluator

RESOLUTIONS = ((32, 256), (64, 512), (64, 1024), (128, 2048))
LODS = (0, 1, 2)
PRECISIONS = ("torch fp32", "onnx fp32", "onnx fp16", "onnx int8")
CRF_ITERATIONS = (0, 1, 2, 3)
STEPS = (0.5, 1.0, 2.0)
BUDGET_SAMPLERS = ("random", "sobol")
BUDGET_FRACTIONS = (0.10, 0.25, 0.50)
TIMING_SAMPLES = 40   # timed per setting and round, spread evenly over the sample set
TIMING_ROUNDS = 3     # interleaved over the settings; the fastest round counts
THREADS = 1           # inference threads: what each `--workers` process of a run uses
BATCH = 8


@dataclass(frozen=True)
class Setting:
    """How a sample is scanned and scored: car LOD, cast grid, model file and backend."""

    model: Path
    backend: str = "onnx"
    lod: int = 2
    resolution: tuple[int, int] | None = None   # cast grid; None = the network's own


@dataclass(frozen=True)
class Row:
    """One (knob, setting) measurement against the knob's reference setting."""

    knob: str
    setting: str
    is_reference: bool
    time_per_sample_ms: float | None
    speedup: float | None          # reference map time / this map time
    map_mean_abs_error: float | None
    map_max_abs_error: float | None
    blind_spot_jaccard: float | None
    blind_spots: int | None
    samples: int
    notes: str = ""
    map_time_s: float | None = None


@dataclass(frozen=True)
class Scored:
    """A sample's outcome under one setting."""

    status: str
    car_iou: float | None


class SettingScorer:
    """Scores samples under settings in this process (`threads` inference threads, 8 samples a
    call), caching results per (setting, sample), and times settings against each other."""

    def __init__(self, space: Space, threads: int = THREADS, batch: int = BATCH):
        self.space, self.threads, self.batch = space, threads, batch
        self.results: dict[tuple[Setting, Sample], Scored] = {}
        self.ms: dict[Setting, float] = {}
        self._evaluators: dict[Setting, Evaluator] = {}

    def evaluator(self, s: Setting) -> Evaluator:
        from falsify.executors.evaluator import EvalSettings, Evaluator

        if s not in self._evaluators:
            settings = EvalSettings(space=self.space, model=str(s.model), backend=s.backend,
                                    threads=self.threads, lod=s.lod)
            scanner = None if s.resolution is None else Resampling(
                load_sensor(self.space.sensor), s.resolution, self.space, s.lod)
            self._evaluators[s] = Evaluator(settings, scanner=scanner)
        return self._evaluators[s]

    def drop(self, s: Setting) -> None:
        self._evaluators.pop(s, None)

    def score(self, s: Setting, samples: Sequence[Sample]) -> pd.DataFrame:
        """The samples' rows (dims, status, car_iou), computing only those not cached."""
        todo = [x for x in dict.fromkeys(samples) if (s, x) not in self.results]
        if todo:
            self._run(s, todo)
        return pd.DataFrame([{**x.as_dict(), **dataclasses.asdict(self.results[(s, x)])}
                             for x in samples])

    def _run(self, s: Setting, samples: Sequence[Sample]) -> None:
        ev = self.evaluator(s)
        for i in range(0, len(samples), self.batch):
            for r in ev.score_batch(samples[i:i + self.batch]):
                iou = r.metrics.get("car_iou") if r.status == Status.OK else None
                self.results[(s, r.sample)] = Scored(r.status, iou)

    def time(self, settings: Sequence[Setting], samples: Sequence[Sample],
             rounds: int | None = None) -> None:
        """Wall time of scan + inference per sample for each setting: a fresh evaluator, warmed
        up (background hits cached, one batch run), then the samples in batches; rounds are
        interleaved over the settings and the fastest counts, so a busy moment of the machine
        does not land on one setting."""
        for _ in range(TIMING_ROUNDS if rounds is None else rounds):
            for s in settings:
                self.drop(s)
                ev = self.evaluator(s)
                for bg in sorted({x.background for x in samples}):
                    ev.sim.background_hits(bg, ev.sim.ego_pose(bg))
                ev.score_batch(samples[: self.batch])
                t0 = time.perf_counter()
                self._run(s, samples)   # the results are kept: scoring reuses them
                ms = (time.perf_counter() - t0) / len(samples) * 1e3
                self.ms[s] = min(ms, self.ms.get(s, math.inf))
                self.drop(s)


class Resampling:
    """A scanner for the evaluator in place of its Simulator: casts at another resolution over
    the same fields of view, then projects the labelled points into the network's grid (nearest
    point wins a pixel): holes when coarser, supersampling when finer."""

    def __init__(self, sensor: Sensor, shape: tuple[int, int], space: Space, lod: int):
        from falsify.sensor.simulator import Simulator

        self.sensor = sensor
        self.sim = Simulator(sensor.with_resolution(*shape), space.user_cars, lod=lod,
                             surfaces=space.surfaces, background_source=space.background_source())

    def background_hits(self, bg_id: int, pose: SensorPose):
        return self.sim.background_hits(bg_id, pose)

    def ego_pose(self, bg_id: int, pose: SensorPose = SensorPose()) -> SensorPose:
        return self.sim.ego_pose(bg_id, pose)

    def placed_pixels(self, scan) -> np.ndarray:
        return self.sim.placed_pixels(scan)

    def scan(self, sample: Sample, pose: SensorPose = SensorPose(),
             rng: np.random.Generator | None = None):
        from falsify.sensor.scan import image_from_points

        p = self.sim.scan(sample, pose, rng=rng).points
        return image_from_points(self.sensor, p[:, :3], p[:, 5].astype(np.uint8),
                                 p[:, 6].astype(np.int32), intensity=p[:, 3])


# -- spaces --------------------------------------------------------------------------------
def narrow(space: Space, samples: Sequence[Sample]) -> Space:
    """The space cut to what `samples` hold: ranges to their min..max, values to those seen."""
    dims = {}
    for name, dim in space.dims.items():
        seen = [x[name] for x in samples]
        if isinstance(dim, Continuous):
            dims[name] = dataclasses.replace(dim, lo=float(min(seen)), hi=float(max(seen)))
        else:
            dims[name] = Categorical(name, tuple(v for v in dim.values if v in set(seen)))
    return dataclasses.replace(space, dims=dims)


def with_step(space: Space, step: float) -> Space:
    """The same x/y extent at another grid step."""
    dims = dict(space.dims)
    for name in ("x", "y"):
        d = dims[name]
        assert isinstance(d, Continuous)
        dims[name] = dataclasses.replace(d, step=step)
    return dataclasses.replace(space, dims=dims)


# -- the measurement -----------------------------------------------------------------------
@dataclass(frozen=True)
class Variant:
    """One setting of an evaluation knob, or why it cannot run here (setting None)."""

    knob: str
    name: str
    setting: Setting | None
    notes: str = ""


@dataclass
class Context:
    """What every knob shares: the sample set, its map space, the scorer and the reference."""

    space: Space          # the config narrowed to the sample set
    samples: list[Sample]
    scorer: SettingScorer
    reference: Setting
    models: Path          # where variant models are written (moved to OUT/models/ at the end)
    ref_map: CellMap
    user_model: Path | None = None   # --model as given; None runs the bundled model

    @property
    def threshold(self) -> float:
        return self.space.threshold

    def map_of(self, s: Setting, samples: Sequence[Sample] | None = None,
               space: Space | None = None) -> CellMap:
        return miou_map(self.scorer.score(s, self.samples if samples is None else samples),
                        space or self.space, "x", "y")

    def row(self, v: Variant) -> Row:
        """A variant's row: its map on the whole sample set against the reference map."""
        if v.setting is None:
            return Row(v.knob, v.name, False, None, None, None, None, None, None, 0,
                       f"skipped: {v.notes}")
        err = map_error(self.ref_map, self.map_of(v.setting).miou, self.threshold)
        if v.setting != self.reference:
            self.scorer.drop(v.setting)   # its results are cached; free the session's memory
        n = len(self.samples)
        return make_row(v.knob, v.name, v.setting == self.reference, self.scorer.ms[v.setting],
                        self.scorer.ms[self.reference], n, n, err, v.notes)


def make_row(knob: str, name: str, is_ref: bool, ms: float, ref_ms: float, n: int, ref_n: int,
             err: MapError, notes: str = "") -> Row:
    if err.lost_cells:
        notes = "; ".join(filter(None, [notes, f"{err.lost_cells} cells lost their mIoU"]))
    return Row(knob, name, is_ref, round(ms, 2), round(ref_ms * ref_n / (ms * n), 3),
               _r(err.mean_abs), _r(err.max_abs), round(err.jaccard, 4), err.blind_spots, n,
               notes, round(ms * n / 1e3, 2))


def _r(v: float | None) -> float | None:
    return None if v is None else round(v, 4)


def _build(knob: str, name: str, make, notes: str = "") -> Variant:
    """A variant from `make()` (a Setting), or a skipped one saying what is missing."""
    try:
        return Variant(knob, name, make(), notes)
    except ImportError as exc:
        return Variant(knob, name, None, f"missing package {exc.name}")
    except Unavailable as exc:
        return Variant(knob, name, None, str(exc))


def knob_resolution(ctx: Context) -> list[Variant]:
    """Cast at other resolutions over the same FOV, projected into the network's 64×512."""
    net = ctx.scorer.evaluator(ctx.reference).sim.sensor.shape
    return [Variant("resolution", f"{r}x{c}" + (" (native)" if (r, c) == net else ""),
                    dataclasses.replace(ctx.reference, resolution=None if (r, c) == net
                                        else (r, c)))
            for r, c in RESOLUTIONS]


def knob_lod(ctx: Context) -> list[Variant]:
    """Car meshes at each level of detail; notes give the triangle counts."""
    from falsify.world.cars import BUILTIN_MODELS, car_mesh

    models = sorted({c.model for x in ctx.samples for c in x.cars} & set(BUILTIN_MODELS))
    return [Variant("lod", f"lod {lod}", dataclasses.replace(ctx.reference, lod=lod),
                    ", ".join(f"{m} {len(car_mesh(m, lod).faces)} triangles" for m in models))
            for lod in LODS]


def knob_precision(ctx: Context) -> list[Variant]:
    """torch fp32 on the .pt weights; ONNX Runtime fp32, fp16 and static int8 (variants
    written to DIR/models/)."""
    from falsify.data.training import calibration_scans
    from falsify.models.export import convert_fp16, quantize_int8

    ref, onnx, models = ctx.reference, ctx.reference.model, ctx.models
    return [
        _build("precision", "torch fp32", lambda: dataclasses.replace(
            ref, model=_torch_weights(onnx), backend="torch")),
        Variant("precision", "onnx fp32", ref),
        _build("precision", "onnx fp16", lambda: dataclasses.replace(ref, model=convert_fp16(
            onnx, models / f"{onnx.stem}-fp16.onnx"))),
        _build("precision", "onnx int8", lambda: dataclasses.replace(ref, model=quantize_int8(
            onnx, models / f"{onnx.stem}-int8.onnx",
            scans=calibration_scans(load_sensor(ctx.space.sensor)))),
            "static QDQ, calibrated on training-style synthetic scenes"),
    ]


def knob_crf(ctx: Context) -> list[Variant]:
    """The same weights with 0..3 CRF iterations (0 skips the CRF), exported and run in ORT."""
    from falsify.models.spec import load_paired_spec

    _, spec = load_paired_spec(ctx.reference.model, "onnx")
    out = []
    for k in CRF_ITERATIONS:
        if k == spec.crf_iterations:
            out.append(Variant("crf", f"crf {k}", ctx.reference))
        else:
            out.append(_build("crf", f"crf {k}", lambda k=k: dataclasses.replace(
                ctx.reference, model=export_crf(_torch_weights(ctx.reference.model), spec, k,
                                                ctx.models))))
    return out


def knob_step(ctx: Context) -> list[Row]:
    """Grid steps over the same x/y extent, each map upsampled (nearest cell) to the finest."""
    fine = with_step(ctx.space, min(STEPS))
    maps = {}
    for step in STEPS:
        sp = with_step(ctx.space, step)
        maps[step] = (ctx.map_of(ctx.reference, sp.grid(), sp), len(sp.grid()))
    ref_map, ref_n = maps[min(STEPS)]
    ms = ctx.scorer.ms[ctx.reference]
    own = {getattr(ctx.space.dims[d], "step", None) for d in ("x", "y")}
    rows = []
    for step, (m, n) in maps.items():
        err = map_error(ref_map, fill_nearest(m, fine.dims["x"].grid(), fine.dims["y"].grid()),
                      ctx.threshold)
        rows.append(make_row("step", f"{step:g} m", step == min(STEPS), ms, ms, n, ref_n, err,
                             "the config's step" if own == {step} else ""))
    return rows


def knob_budget(ctx: Context) -> list[Row]:
    """Random and Sobol samples (a fraction of the grid) snapped to the grid's cells; empty
    cells take the nearest sampled cell's mIoU."""
    from falsify.sampler import make_sampler

    ms, n = ctx.scorer.ms[ctx.reference], len(ctx.samples)
    xs, ys = ctx.space.dims["x"].grid(), ctx.space.dims["y"].grid()
    rows = [make_row("budget", "grid 100%", True, ms, ms, n, n,
                     map_error(ctx.ref_map, ctx.ref_map.miou, ctx.threshold))]
    for name in BUDGET_SAMPLERS:
        for frac in BUDGET_FRACTIONS:
            drawn: list[Sample] = []

            def evaluate(batch: Sequence[Sample], drawn=drawn) -> list[float | None]:
                drawn.extend(batch)
                f = ctx.scorer.score(ctx.reference, batch)
                return [None if v is None else float(v) for v in f["car_iou"]]

            make_sampler(name).run(ctx.space, evaluate, max(1, round(frac * n)), ctx.space.seed)
            err = map_error(ctx.ref_map, fill_nearest(ctx.map_of(ctx.reference, drawn), xs, ys),
                          ctx.threshold)
            rows.append(make_row("budget", f"{name} {frac:.0%}", False, ms, ms, len(drawn), n,
                                 err))
    return rows


def knob_preset(ctx: Context) -> list[Variant]:
    """The `--fidelity` presets as a run applies them: their LOD with the bundled model's
    variant, or with your own model as given (then only the LOD changes)."""
    from falsify.jobs.fidelity import PRESETS

    out = []
    for name, fid in PRESETS.items():
        model = fid.model(None if ctx.user_model is None else str(ctx.user_model))
        path = ctx.reference.model if model is None else Path(model).resolve()
        setting = dataclasses.replace(ctx.reference, model=path, lod=fid.lod)
        out.append(Variant("preset", name, setting, f"lod {fid.lod}, {path.name}"))
    return out


VARIANT_KNOBS = {"resolution": knob_resolution, "lod": knob_lod, "precision": knob_precision,
                 "crf": knob_crf, "preset": knob_preset}
MAP_KNOBS = {"step": knob_step, "budget": knob_budget}


class Unavailable(Exception):
    """A knob setting cannot be built here (e.g. no torch weights); its row says why."""


def _torch_weights(onnx: Path) -> Path:
    pt = onnx.with_suffix(".pt")
    if not pt.is_file():
        raise Unavailable(f"no torch weights {pt} beside the model")
    try:
        import torch  # noqa: F401
    except ImportError:
        raise Unavailable("torch is not installed") from None
    return pt


def export_crf(pt: Path, spec: ModelSpec, k: int, out: Path) -> Path:
    """The model's weights in SqueezeSeg(crf_iterations=k), exported to out/<stem>-crf<k>.onnx."""
    import torch

    from falsify.models.export import export_onnx
    from falsify.models.spec import check_exported_file, spec_path_for
    from falsify.models.squeezeseg import SqueezeSeg

    if spec.architecture != "squeezeseg":
        raise Unavailable(f"model architecture {spec.architecture!r} is not squeezeseg")
    check_exported_file(spec, spec_path_for(pt), pt, "pt")   # the .pt of the spec's export
    net = SqueezeSeg([c for c in spec.channels if c != "mask"], crf_iterations=k,
                     num_classes=spec.num_classes)
    net.load_state_dict(torch.load(str(pt), map_location="cpu", weights_only=True))
    path, _ = export_onnx(net.eval(), out / f"{pt.stem}-crf{k}.onnx", H=spec.height,
                          W=spec.width, name=f"{spec.name}-crf{k}")
    return path


# -- entry point ---------------------------------------------------------------------------
def parse_knobs(text: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(k.strip() for k in text.split(",") if k.strip()))
    bad = [k for k in names if k not in KNOBS]
    if bad or not names:
        what = f"unknown knob {bad[0]!r}" if bad else "no knob given"
        raise FalsifyError(f"--knobs: {what}; allowed: {', '.join(KNOBS)}")
    return names


def run_tradeoff(config: str | Path, out: str | Path, knobs: Sequence[str] = KNOBS,
                 model: str | Path | None = None, limit: int | None = None,
                 threads: int = THREADS) -> dict:
    """Measure every knob; write DIR/tradeoff.csv, .json and .html; return the JSON summary.

    Bad input raises FalsifyError before anything is written, and a failure while measuring
    leaves nothing: variant models are moved to DIR/models/ with the results."""
    from falsify.fileio import move_file, write_bytes, write_json, write_text
    from falsify.models.runners import BUNDLED_ONNX
    from falsify.reports.tradeoff_page import render

    knobs = parse_knobs(",".join(knobs))
    out = check_out_dir(out)
    if limit is not None and limit < 1:
        raise FalsifyError(f"--limit: {limit} must be >= 1")
    onnx = Path(model) if model else BUNDLED_ONNX
    if onnx.suffix != ".onnx" or not onnx.is_file():
        raise FalsifyError(f"--model {onnx}: not an existing .onnx file (with its .json spec "
                           "beside it); train one with `falsify train`")
    space = load_space(config)
    space.require_streets("tradeoff")
    ranged = [k for k in ("step", "budget") if k in knobs]   # the knobs that resample x, y
    for d in ("x", "y"):
        if ranged and not isinstance(space.dims[d], Continuous):
            raise FalsifyError(f"{config}: dims.{d} must be a range (min, max, step) for the "
                               f"{' and '.join(ranged)} knob{'s' if len(ranged) > 1 else ''}; "
                               "give one, or leave them out of --knobs")
    space.check_size(MAX_SAMPLES, "the trade-off's limit")
    samples = space.grid()[:limit]
    t_start = time.perf_counter()
    scorer = SettingScorer(narrow(space, samples), threads=threads)
    reference = Setting(model=onnx.resolve())
    # Loads and checks the model against the sensor: may raise, and nothing is written yet.
    ref_map = miou_map(scorer.score(reference, samples), scorer.space, "x", "y")
    with tempfile.TemporaryDirectory(prefix="falsify-tradeoff-") as scratch:
        summary, rows = _measure(Context(scorer.space, samples, scorer, reference, Path(scratch),
                                         ref_map, Path(model) if model else None),
                                 knobs, config, onnx, limit, t_start, out)
        frame = pd.DataFrame([dataclasses.asdict(r) for r in rows],
                             columns=list(Row.__annotations__))
        page = render(summary)   # before any file: a page that fails leaves no csv without it
        remove_outputs(out)   # a stop from here on leaves part of this run, none of the last
        variants = sorted(Path(scratch).iterdir())
        if variants:
            (out / "models").mkdir(parents=True, exist_ok=True)
        for f in variants:
            move_file(f, out / "models" / f.name)   # whole, across file systems too
        write_bytes(out / "tradeoff.csv", frame.to_csv(index=False).encode())
        write_text(out / "tradeoff.html", page)
        write_json(out / "tradeoff.json", summary)   # last: the run's files are all there
    return summary


# What a run writes into DIR/models/: `knob_precision`'s and `export_crf`'s variants, each an
# .onnx with its .json spec.
VARIANT_SUFFIXES = ("-fp16", "-int8", *(f"-crf{k}" for k in CRF_ITERATIONS))


def remove_outputs(out: Path) -> None:
    """Remove an earlier run's files from `out`: tradeoff.csv, .json and .html, and its variant
    models (named as `VARIANT_SUFFIXES` say) from out/models/, which goes if left empty; a run
    with fewer knobs kept the last one's models beside its results. Other files stay."""
    for k in ("json", "csv", "html"):   # the summary first: it says the files are one run
        (out / f"tradeoff.{k}").unlink(missing_ok=True)
    models = out / "models"
    if models.is_dir():
        for f in models.iterdir():
            p = Path(f.name)
            if p.suffix in (".onnx", ".json") and p.stem.endswith(VARIANT_SUFFIXES) \
                    and f.is_file():
                f.unlink()
        with contextlib.suppress(OSError):   # not empty: a file of the user's
            models.rmdir()


def _measure(ctx: Context, knobs: Sequence[str], config: str | Path, onnx: Path,
             limit: int | None, t_start: float, out: Path) -> tuple[dict, list[Row]]:
    """Time and score every knob's settings; the JSON summary and the rows."""
    from falsify.bench.machine import machine

    scorer, reference, space, samples = ctx.scorer, ctx.reference, ctx.space, ctx.samples
    variants = {k: VARIANT_KNOBS[k](ctx) for k in knobs if k in VARIANT_KNOBS}
    settings = [reference] + [v.setting for vs in variants.values() for v in vs
                              if v.setting is not None and v.setting != reference]
    every = max(1, len(samples) // TIMING_SAMPLES)
    scorer.time(list(dict.fromkeys(settings)), samples[::every][:TIMING_SAMPLES])
    rows: list[Row] = []
    for knob in knobs:
        rows.extend(map(ctx.row, variants[knob]) if knob in variants else MAP_KNOBS[knob](ctx))
    notes = [f"{r.knob} {r.setting}: {r.notes}" for r in rows if r.notes.startswith("skipped")]

    ref_eval = scorer.evaluator(reference)
    summary = {
        "command": "tradeoff", "config": str(config), "model": str(onnx),
        "model_hash": ref_eval.model_hash, "samples": len(samples), "limit": limit,
        "threshold": space.threshold, "knobs": list(knobs), "threads": scorer.threads,
        "batch": scorer.batch, "machine": machine(),
        "reference": {"resolution": "x".join(map(str, ref_eval.sim.sensor.shape)),
                      "lod": reference.lod,
                      "precision": "onnx fp32", "crf": ref_eval.model.spec.crf_iterations,
                      "grid": "the config's", "time_per_sample_ms": round(scorer.ms[reference], 2),
                      "blind_spots": len(ctx.ref_map.blind_spots(space.threshold)),
                      "lowest_cell_miou": _r(float(np.nanmin(ctx.ref_map.miou)))
                      if np.isfinite(ctx.ref_map.miou).any() else None},
        "rows": [dataclasses.asdict(r) for r in rows], "notes": notes,
        "timing": {"samples": len(samples[::every][:TIMING_SAMPLES]),
                   "rounds": TIMING_ROUNDS, "statistic": "fastest round"},
        "elapsed_s": round(time.perf_counter() - t_start, 1),
        "files": {k: str(out / f"tradeoff.{k}") for k in ("csv", "json", "html")},
    }
    return summary, rows


