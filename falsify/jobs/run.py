"""A falsification run from start to summary: checks, store, sampler loop, maps, retraining set.

Everything a user can get wrong (config, model, sampler, run directory) is checked before the
run directory is written, so bad input leaves nothing half-written (the run lock, taken first so
that one process writes a run, removes the folders it made); what only the workers find (an
actor that cannot start) removes the run this invocation made while it holds no row. A full disk
ends the run as a FalsifyError saying how many samples are stored and that --resume continues.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import shutil
import sqlite3
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from falsify.checks import MAX_SAMPLES, check_out_dir, check_range, check_seed
from falsify.errors import ConfigError, FalsifyError
from falsify.executors.driver import Driver, Progress, ProgressListener
from falsify.executors.environment import session_changes
from falsify.executors.evaluator import EvalSettings
from falsify.fileio import read_text, write_bytes, write_json
from falsify.jobs.fidelity import preset
from falsify.jobs.retraining_set import (
    check_retrain_format,
    plain_value,
    write_retraining_set,
)
from falsify.models.runners import Segmenter, backend_for, load_segmenter
from falsify.paths import config_path
from falsify.results.metrics import Scoring, Status, column
from falsify.results.miou_maps import CellMap, miou_map
from falsify.results.runlock import LOCK_NAME, RunLock, remove_empty
from falsify.results.samples import CAR_SCORING
from falsify.results.store import (
    STORE_NAME,
    DiskFull,
    RunData,
    Store,
    disk_full,
    export,
    read_frame,
    read_meta,
    stored_samples,
)
from falsify.sampler import NLOPT_ALGORITHMS, make_sampler
from falsify.sampler.base import BATCH, Sampler, SearchResult
from falsify.sensor.lidar import load_sensor
from falsify.sensor.look import check_looks
from falsify.sensor.weather import check_beams
from falsify.world.actors import model_semantic
from falsify.world.cars import load_user_car
from falsify.world.space import Space, load_space

BATCHED = ("grid", "random", "sobol")   # samplers that take a batch_size
# What --resume must find unchanged. The executor, --workers and --address are not here: the rows
# do not depend on them (each sample's seed comes from the space and the sample alone), so a run
# may be continued on another; each invocation is kept in the meta's `sessions`.
RESUME_KEYS = ("config_hash", "model_hash", "algorithm", "seed", "budget", "fidelity",
               "sampler_options")
LEVEL_SET = "level-set"


@dataclass(frozen=True)
class RunRequest:
    """Everything that defines a run; equal requests give equal rows."""

    config: Path
    out: Path
    command: str                 # "grid" or "search"
    algorithm: str = "grid"
    budget: int | None = None
    seed: int | None = None
    model: str | None = None     # a model file, a bundled name, or a plug-in MODULE:FACTORY
    backend: str = "onnx"        # "python" is set for a plug-in
    device: str = "cpu"          # "cpu" or "cuda": where the network runs
    objective: str | None = None  # a class the model predicts, or "miou": what the sampler
    #                               minimises (None: the placed actors' class)
    workers: int = 1
    resume: bool = False
    threshold: float | None = None
    fidelity: str = "exact"
    report: bool = True
    retrain: bool = True         # write the retraining set (False: none, its folder removed)
    camera: str | None = None    # camera preset: render the retraining set's images too
    retrain_format: str = "npy"  # the retraining set's layout (retraining_set.RETRAIN_FORMATS)
    max_samples: int = MAX_SAMPLES   # a grid or budget larger than this is refused up front
    confidence: float | None = None  # level-set: the confidence a cell is decided at
    inference: str = "auto"      # "worker", "shared" (one process runs the network), "auto"
    executor: str = "process"    # "process": local worker processes; "ray": actors on Ray
    address: str | None = None   # the Ray head with executor "ray" (None: a local instance)


@dataclass(frozen=True)
class Prepared:
    """A checked request: what the run needs, with its model opened once for this process."""

    space: Space
    sampler: Sampler
    settings: EvalSettings
    seed: int
    meta: dict
    model: Segmenter


def prepare(req: RunRequest) -> Prepared:
    """Validate the request and open the model, without writing anything."""
    space = load_space(req.config)
    fid = preset(req.fidelity)
    _check_request(req, space)
    sampler, options = _sampler_of(req, space)
    if req.camera is not None and space.real_backgrounds:
        raise FalsifyError("--camera renders our streets; a space of real backgrounds has no "
                           "scene to render (drop --camera)")
    check_looks(space)   # stored in the results whether or not a camera renders them
    check_retrain_format(req.retrain_format)
    if not req.retrain and (req.camera is not None or req.retrain_format != "npy"):
        given = "--camera" if req.camera is not None else "--retrain-format"
        raise FalsifyError(f"{given} shapes the retraining set, which --no-retrain leaves "
                           f"unwritten: drop one of them")
    if req.camera is not None:
        from falsify.sensor.camera import camera_preset
        camera_preset(req.camera)
    if req.model is not None and req.fidelity != "exact" and not fid.is_variant(req.model):
        # a preset picks a variant of the bundled network; a user's model would run as given
        # while the run recorded the preset (its own variant, as resume commands name it, is fine)
        raise FalsifyError(f"--fidelity {req.fidelity} runs a variant of the bundled network "
                           f"({fid.bundled_model}); --model {req.model} is run as given: "
                           "leave out --model, or --fidelity (exact)")
    backend = backend_for(req.model, req.backend)
    if backend == "torch" and req.fidelity != "exact":
        raise FalsifyError(f"--fidelity {req.fidelity} runs an ONNX variant of the network; "
                           "use --backend onnx or --fidelity exact")
    model = fid.model(req.model)
    seed = space.seed if req.seed is None else req.seed
    threads = inference_threads(backend, req.device, req.workers)
    # Open the model once here: a missing, corrupt or mismatched model fails before any sample.
    seg = load_segmenter(model, backend=backend, threads=threads, device=req.device)
    scoring = _scoring_of(req, space, seg)
    _check_labels_scored(space, scoring, seg.spec.name)
    settings = EvalSettings(space=space, model=model, backend=backend, threads=threads,
                            lod=fid.lod, device=req.device, scoring=scoring)
    sensor = load_sensor(space.sensor)
    check_beams(space, sensor)
    seg.spec.check_fits(sensor, req.model or "bundled")
    for car in space.user_cars.values():   # a missing or broken mesh fails before the run dir
        load_user_car(car.file, car.scale, car.forward, car.up, car.key)
    meta = {
        "command": req.command, "config_path": str(req.config),
        "config_text": read_text(config_path(req.config), "config"),
        # where the config's relative paths (user meshes) resolve, from any later directory
        "config_dir": str(config_path(req.config).parent.resolve()),
        # where the paths as typed (config, model) resolve: the command that finishes the run
        "cwd": str(Path.cwd()),
        "config_hash": space.config_hash,
        "space_name": space.name, "sensor": sensor.name, "model_path": model,
        # which file (or preset) and grid: two sensor files may share a name
        "sensor_source": space.sensor, "sensor_shape": list(sensor.shape),
        "model_name": seg.spec.name, "model_hash": seg.model_hash, "backend": backend,
        "seed": seed, "algorithm": req.algorithm, "budget": req.budget,
        "threshold": req.threshold or space.threshold, "workers": req.workers,
        "fidelity": req.fidelity, "lod": fid.lod, "executor": req.executor,
    }
    if options is not None:
        meta["sampler_options"] = options
    if space.real_backgrounds:   # which scans, so a report or gate need not look again
        meta["real_backgrounds"] = [[r.name, str(r.bin), None if r.label is None else str(r.label),
                                     r.kind] for r in space.real_backgrounds]
    # Car-objective, four-class runs on our streets keep their meta as it was before streets
    # scored the placed objects apart.
    if (scoring if space.real_backgrounds else replace(scoring, parts=False)) != CAR_SCORING:
        meta.update(objective=scoring.objective, score_column=scoring.score_column,
                    scored_classes=list(scoring.scored))
    _check_run_dir(req, meta)
    return Prepared(space, sampler, settings, seed, meta, seg)


def _check_request(req: RunRequest, space: Space) -> None:
    """The request's numbers, run folder, executor and threshold, in the order they are told."""
    check_range(req.workers, "--workers", 1, 64)
    check_range(req.budget, "--budget", 1)
    check_seed(req.seed)
    check_range(req.max_samples, "--max-samples", 1)
    if req.budget is not None and req.budget > req.max_samples:
        raise FalsifyError(f"--budget: {req.budget:,} is more than --max-samples "
                           f"{req.max_samples:,}; raise --max-samples to run it")
    check_out_dir(req.out)
    if req.inference == "shared" and req.executor == "ray":   # wrong with or without ray
        raise FalsifyError("--inference shared runs one inference process beside local "
                           "workers; with --executor ray each actor runs the network")
    check_executor(req.executor, req.address)
    if req.algorithm == "grid" and req.budget is None:
        space.check_size(req.max_samples)
    elif req.algorithm == LEVEL_SET and req.budget is None and space.size() > req.max_samples:
        raise FalsifyError(f"--max-samples: level-set without --budget may score the whole grid, "
                           f"{space.size():,} samples, more than --max-samples "
                           f"{req.max_samples:,}; give --budget or raise --max-samples")
    if req.threshold is not None and not 0 < req.threshold <= 1:
        raise FalsifyError(f"--threshold: {req.threshold} must be in (0, 1]")


def _sampler_of(req: RunRequest, space: Space) -> tuple[Sampler, dict | None]:
    """The request's sampler and the options a resumed run must keep (None: it has none)."""
    # Batch samplers hand the driver whole batches; keep every worker busy with two chunks of
    # 8 each. NLopt asks for one point at a time per discrete combination: run as many
    # combinations at once as there are workers. Neither changes the samples or the rows.
    # Cross-entropy's round size is part of the algorithm, so it keeps its own.
    sizes = ({"batch_size": max(BATCH, 16 * req.workers)} if req.algorithm in BATCHED
             else {"concurrent": req.workers} if req.algorithm in NLOPT_ALGORITHMS else {})
    # The level-set sampler decides cells against the run's threshold: it and the confidence
    # choose its samples, so a resumed run must keep them.
    options: dict | None = None
    if req.confidence is not None and not 0.5 <= req.confidence < 1:
        raise FalsifyError(f"--confidence: {req.confidence} must be in [0.5, 1)")
    if req.algorithm == LEVEL_SET:
        options = {"threshold": req.threshold or space.threshold}
        if req.confidence is not None:
            options["confidence"] = req.confidence
    elif req.confidence is not None:
        raise FalsifyError(f"--confidence is an option of --algorithm {LEVEL_SET}")
    return make_sampler(req.algorithm, **sizes, **(options or {})), options


def _scoring_of(req: RunRequest, space: Space, seg: Segmenter) -> Scoring:
    """What the run scores: the objective asked for (else the placed actors' class), and the
    placed objects apart from the background's own (a real scan's, or a street's parked ones)."""
    semantics = [model_semantic(m, space.user_cars) for m in space.models()]
    objective = req.objective or Scoring.placed_class(list(seg.spec.classes), semantics)
    try:
        scoring = Scoring.of(list(seg.spec.classes), objective)
    except ConfigError as exc:
        if req.objective:
            raise
        raise ConfigError(f"{seg.spec.name} does not predict {objective!r}, the class of the "
                          f"placed objects, which a run scores by default; pass --objective "
                          f"(allowed: {str(exc).split('allowed: ', 1)[-1]}) or run a model "
                          "that predicts it") from None
    placed = [c for c in Scoring.placed_classes(list(seg.spec.classes), semantics)
              if c in scoring.scored and c not in ("unknown", "unlabeled")]
    return replace(scoring, parts=True, placed=tuple(placed) if len(placed) > 1 else ())


def _check_labels_scored(space: Space, scoring: Scoring, model: str) -> None:
    """ConfigError naming the real scans without labels when the model's classes are
    SemanticKITTI's: its scores read each scan's own SemanticKITTI labels (before any sample)."""
    bare = [r.name for r in space.real_backgrounds if r.kind == "none"]
    if scoring.semantic and bare:
        more = f", and {len(bare) - 3} more" if len(bare) > 3 else ""
        raise ConfigError(f"{space.source}: dims.background.real: {model} predicts "
                          "SemanticKITTI's classes and is scored on each scan's SemanticKITTI "
                          f"labels; {len(bare)} scan{'s' * (len(bare) != 1)} "
                          f"{'have' if len(bare) != 1 else 'has'} none ({', '.join(bare[:3])}"
                          f"{more}): name labelled scans, or run a four-class model")


def inference_threads(backend: str, device: str, workers: int) -> int:
    """A worker's inference threads. ONNX Runtime computes the same logits on 1 to 4 threads, so
    one worker takes both of a pair of cores; torch's oneDNN kernels (and a plug-in's) sum in
    another order on 1 and 2 threads (41 % of logits, up to 7.6e-6: a pixel's class flipped in
    1 of 128 rows), so on the CPU they take 1 whatever --workers is, and the rows do not depend
    on it."""
    if backend in ("torch", "python") and device == "cpu":
        return 1
    return 2 if workers == 1 else 1


def _check_run_dir(req: RunRequest, meta: dict) -> None:
    """A run folder that is new and empty, or (with --resume) holds a run of the same request."""
    if (req.out / STORE_NAME).exists():
        if not req.resume:
            raise FalsifyError(f"{req.out} already holds a run; pass --resume to continue it "
                               "or choose another --out")
        old = read_meta(req.out)
        for key in RESUME_KEYS + ("score_column",):
            if old.get(key) != meta.get(key):
                what = (config_difference(req.config, old.get("config_text"),
                                          meta.get("config_text"))
                        if key == "config_hash" else None)
                raise FalsifyError(f"--resume: {key} differs from the run in {req.out}" + (
                    f" ({old.get(key)!r} there, {meta.get(key)!r} now)" if what is None else
                    f": {what}; continue with the config it started with, or choose another "
                    "--out"))
    elif req.resume:
        raise FalsifyError(f"--resume: {req.out} holds no run to resume ({STORE_NAME} missing)")
    elif req.out.exists() and any(f.name != LOCK_NAME for f in req.out.iterdir()):
        raise FalsifyError(f"--out {req.out}: directory exists and is not empty")


def config_difference(config: Path, then: str | None, now: str | None) -> str | None:
    """What differs between the config a run started with (its recorded text) and the one
    given now: the keys whose values differ, or that only comments or layout do (the hash is
    of the bytes), or that the files it names do (sensor, meshes, profile, real scans); None
    where a text is not recorded or not readable."""
    from falsify.fileio import parse_toml

    if not isinstance(then, str) or not isinstance(now, str):
        return None
    if then == now:
        return (f"{config} is the config it started with, but a file it names (a sensor, a "
                "mesh, a world profile or a real scan) has changed since")
    try:
        before = parse_toml(then.encode(), "the run's config")
        after = parse_toml(now.encode(), str(config))
    except FalsifyError:
        return None
    if before == after:
        return (f"{config} differs from the config it started with only in comments or layout "
                "(the hash is of the file's bytes)")
    changes = config_changes(before, after)
    shown = "; ".join(changes[:3]) + (f"; and {len(changes) - 3} more" if len(changes) > 3
                                      else "")
    return f"{config} differs from the config it started with ({shown})"


def config_changes(then: dict, now: dict, prefix: str = "") -> list[str]:
    """Each dotted key whose value differs between two parsed configs, as 'KEY: OLD there, NEW
    now' ('-' where a side lacks it), in key order."""
    out = []
    for key in sorted(set(then) | set(now)):
        a, b = then.get(key), now.get(key)
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_changes(a, b, f"{name}.")
        elif a != b or (key in then) != (key in now):
            shown = ["-" if key not in side else repr(side[key]) for side in (then, now)]
            out.append(f"{name}: {shown[0]} there, {shown[1]} now")
    return out


def check_executor(executor: str, address: str | None) -> None:
    """A known executor; for ray, ray importable and the --address (if any) answering."""
    from falsify.executors import EXECUTORS
    from falsify.executors.ray import check_address, import_ray
    if executor not in EXECUTORS:
        raise FalsifyError(f"--executor {executor!r}; allowed: {', '.join(EXECUTORS)}")
    check_address(address, executor)
    if executor == "ray":
        import_ray()


@dataclass(frozen=True)
class RunSummary:
    """The outcome of a run (summary.json holds all but `report` and `search`)."""

    run: str
    command: str | None
    algorithm: str | None
    config: str | None
    model: str | None
    model_hash: str | None
    samples: int
    computed_this_time: int
    ok: int
    invalid: int
    undefined: int
    threshold: float
    cells: int
    blind_spots: int
    blind_spot_cells: list[dict]
    lowest: dict | None          # {"car_iou": ..., "sample": {dim: value}}
    elapsed_s: float | None
    retraining_samples: int
    mean_car_iou: float | None
    report: str | None = None
    retraining_camera: str | None = None   # the camera preset whose images sit beside the scans
    retraining_format: str | None = None   # set when not npy: the retraining set's layout
    retraining_skipped: bool | None = None  # set (True) when --no-retrain left it unwritten
    executors: list[str] | None = None     # set when resumed on another executor: all, in order
    # set when computed under environments that may give other numbers: what changed
    environment_changes: list[str] | None = None
    objective: str | None = None           # set when not car: the class (or miou) minimised
    mean_objective: float | None = None    # its mean over the valid samples
    estimated: dict | None = None          # level-set: the map is an estimate; how sure
    # real scans without labels (bare .bin files, or `labels = "optional"`): real_ columns empty
    unlabelled_backgrounds: list[str] | None = None
    search: SearchResult | None = field(default=None, repr=False)

    def to_json(self) -> dict:
        """Plain JSON data; `report`, `retraining_camera`, `retraining_format`,
        `retraining_skipped`, `executors`, `environment_changes` and the objective's fields
        only when set."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "search"}
        for optional in ("report", "retraining_camera", "retraining_format",
                         "retraining_skipped", "executors",
                         "environment_changes",
                         "objective", "mean_objective", "estimated", "unlabelled_backgrounds"):
            if out[optional] is None:
                del out[optional]
        return out


class RunStopped(FalsifyError):
    """A run that ended early with its finished rows kept: `stored` samples in `run` (None when
    they cannot be counted), which `--resume` continues once the `reason` is gone (`advice`)."""

    def __init__(self, run: Path, reason: str, stored: int | None, advice: str):
        self.run, self.reason, self.stored, self.advice = run, reason, stored, advice
        kept = "the finished samples are" if stored is None else f"{stored} samples are"
        super().__init__(f"{reason}: {kept} stored safely in {run}; {advice}, then continue "
                         "the run with --resume")


def execute(req: RunRequest, on_progress: ProgressListener | None = None,
            on_warning: Callable[[str], None] | None = None) -> RunSummary:
    """Run the sampler to the end, then write maps, retraining set, tables and report; the run
    folder is locked throughout. A full disk raises RunStopped. `on_warning` is told what the
    user should know but does not stop the run (a resume under other library versions); by
    default it goes to stderr."""
    with RunLock(req.out) as lock:
        try:
            return _execute(req, on_progress, lock.made, on_warning)
        except (sqlite3.Error, OSError, DiskFull) as exc:
            if not disk_full(exc, req.out):
                raise
            try:
                stored: int | None = stored_samples(req.out)
            except FalsifyError:
                stored = None
            raise RunStopped(req.out, "the disk is full", stored, "free some space") from None


def _execute(req: RunRequest, on_progress: ProgressListener | None, made: list[Path],
             on_warning: Callable[[str], None] | None = None) -> RunSummary:
    """`execute` under the run lock; `made` are the folders made for the run."""
    p = prepare(req)
    fresh = not (req.out / STORE_NAME).exists()
    try:
        store = Store(req.out / STORE_NAME, p.space, p.settings.scoring)
    except BaseException:
        if fresh:
            remove_run(req.out, made)
        raise
    old = store.meta()
    now = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    started = time.perf_counter()
    total = req.budget if req.budget is not None else (
        len(p.space.grid()) if req.algorithm == "grid" else None)
    progress = Progress(total, on_progress)
    try:
        # `planned` and `complete` (set when the sampler returns) tell readers whether the run
        # holds all it set out to; a run begun before they were kept gets them when resumed.
        if not old:
            store.set_meta(**p.meta, started=now, elapsed_s=0.0, curve=[],
                           planned=planned_samples(req, p.space), complete=False)
        elif "planned" not in old:
            store.set_meta(planned=planned_samples(req, p.space),
                           complete="computed_last" in old)   # its sampler has returned
        with Driver(p.settings, store, workers=req.workers, progress=progress,
                    model=p.model, executor=req.executor, address=req.address,
                    inference=req.inference) as driver:
            envs = driver.environments()
            this = session(req, now, envs, latest_environments(old))
            store.set_meta(sessions=[*sessions_of(old), this])
            if this.get("changed"):
                (on_warning or warn)(environment_warning(req, this["changed"], bool(old)))
            search = p.sampler.run(p.space, driver.evaluate, req.budget, p.seed)
            progress.tell(final=True)
            if (now_envs := driver.environments()) != envs:   # Ray actors started since
                store.set_meta(sessions=[*sessions_of(old), this | {"environments": now_envs}])
        # Rows of concurrent combinations arrive in an order that depends on timing (and a
        # resumed run may hold rows of a killed one): number them in the sampler's order.
        store.renumber(search.samples)
        elapsed = float(old.get("elapsed_s", 0.0)) + time.perf_counter() - started
        end: dict = {"elapsed_s": round(elapsed, 3), "curve": list(search.curve),
                     "computed_last": progress.computed}
        if search.cells:   # the level-set sampler's estimate of every cell
            end["cell_estimates"] = [c.as_list() for c in search.cells]
        store.set_meta(**end, complete=True)   # one transaction: complete with all it needs
    except BaseException:
        if not old and not len(store):   # this invocation's run, and it holds no row
            store.close()
            remove_run(req.out, made)
        raise
    finally:
        store.close()
    return finish(req.out, p.space, threshold=req.threshold, report=req.report,
                  lod=p.settings.lod, model=p.model, search=search,
                  camera=req.camera, retrain_format=req.retrain_format, retrain=req.retrain)


def planned_samples(req: RunRequest, space: Space) -> int:
    """The samples a run sets out to score: the grid (or its first `budget`); for level-set
    at most as many (it stops once every cell is decided); for other searches their budget, at
    most the grid of a space with no free continuous dim, which they score once (fewer rows
    where a sampler draws a sample twice or converges early)."""
    finite = not any(d.hi > d.lo for d in space.continuous())
    if req.algorithm in ("grid", LEVEL_SET) or finite:
        size = space.size()
        return size if req.budget is None else min(req.budget, size)
    return int(req.budget or 0)


def remove_run(out: Path, made: list[Path]) -> None:
    """Delete a run store that holds no row, its lock file, and the empty folders `made` for it:
    left behind, it would make the next invocation ask for --resume, then refuse a fixed model
    or config."""
    for suffix in ("", "-wal", "-shm", "-journal"):
        (out / f"{STORE_NAME}{suffix}").unlink(missing_ok=True)
    (out / LOCK_NAME).unlink(missing_ok=True)
    remove_empty(made)


def session(req: RunRequest, started: str, environments: list[dict] | None = None,
            previous: list[dict] | None = None) -> dict:
    """One invocation that computed on a run: when, on which executor and how many workers;
    the device only when not the CPU (runs on the CPU keep their bytes); the environments its
    samples are scored under, and what changed from the `previous` ones (or between its own)
    that may change the numbers (`changed`, only where something did)."""
    out: dict = {"started": started, "executor": req.executor, "workers": req.workers}
    if req.address is not None:
        out["address"] = req.address
    if req.device != "cpu":
        out["device"] = req.device
    if req.inference != "auto":
        out["inference"] = req.inference
    if environments:
        out["environments"] = environments
        if changed := session_changes(previous or [], environments):
            out["changed"] = changed
    return out


def latest_environments(meta: dict) -> list[dict]:
    """The environments of the run's latest session that recorded any (none: empty)."""
    return next((list(s["environments"]) for s in reversed(sessions_of(meta))
                 if s.get("environments")), [])


def environment_warning(req: RunRequest, changed: list[str], resumed: bool) -> str:
    """The one warning for a run computed under more than one environment: on --resume, what
    changed since it was last computed; else what differs between its Ray actors."""
    what = "; ".join(changed)
    if resumed:
        return (f"--resume: {req.out} goes on under another environment than its rows so far "
                f"were computed under: {what}; rows from before and after may differ in their "
                "numbers (each environment is kept in the run's sessions)")
    return (f"{req.out}: its workers run under different environments: {what}; their rows "
            "may differ in their numbers (each environment is kept in the run's sessions)")


def warn(message: str) -> None:
    """A run's warning on stderr, where no listener takes it."""
    print(f"falsify: warning: {message}", file=sys.stderr, flush=True)


def sessions_of(meta: dict) -> list[dict]:
    """The run's sessions so far; a run made before they were kept has its first one made up
    from its meta (executor, workers, started)."""
    if not meta:
        return []
    if "sessions" in meta:
        return list(meta["sessions"])
    return [{"started": meta.get("started"), "executor": meta.get("executor", "process"),
             "workers": meta.get("workers")}]


def executors_of(meta: dict) -> list[str]:
    """Every executor that has computed on the run, in the order first used."""
    names = [s.get("executor", "process") for s in sessions_of(meta)]
    return list(dict.fromkeys(names))


def finish(run: Path, space: Space, threshold: float | None = None, report: bool = True,
           lod: int = 2, model: Segmenter | None = None,
           search: SearchResult | None = None,
           camera: str | None = None, retrain_format: str = "npy",
           retrain: bool = True) -> RunSummary:
    """Maps, blind spots, retraining set (unless not `retrain`: any earlier one removed, as it
    was of other maps), CSV/Parquet, report and the summary of a run. The
    last outputs' summary and report go first and the summary is written last, so a kill in
    between (a --resume at another --threshold) leaves no summary beside other maps."""
    for name in ("summary.json", "report.html"):
        (run / name).unlink(missing_ok=True)
    data = RunData(run, read_meta(run), read_frame(run), space)
    meta, frame = data.meta, data.frame
    thr = threshold if threshold is not None else float(meta.get("threshold", space.threshold))
    col = data.score_column
    cmap = data.cell_map()
    blind = cmap.blind_spots(thr)
    maps_dir = run / "maps"
    write_bytes(maps_dir / "miou_x_y.csv", cmap.to_frame().to_csv(index=False).encode())
    for a, b in extra_map_pairs(space):
        write_bytes(maps_dir / f"miou_{a}_{b}.csv",
                    miou_map(frame, space, a, b, col).to_frame().to_csv(index=False).encode())
    for name in class_maps(meta):   # one (x, y) map per scored class beside the objective's
        c = f"{column(name)}_iou"
        write_bytes(maps_dir / f"iou_{column(name)}_x_y.csv",
                    miou_map(frame, space, "x", "y", c).to_frame().to_csv(index=False).encode())
    export(frame, run / "results")
    if retrain:
        scans = write_retraining_set(data, cmap, thr, lod, camera, fmt=retrain_format)
    else:
        shutil.rmtree(run / "retrain", ignore_errors=True)
        scans = 0
    ok = data.ok
    lowest = None
    if len(ok):
        row = ok.loc[ok[col].astype(float).idxmin()]
        lowest = {col: round(float(row[col]), 4),
                  "sample": {d: plain_value(row[d]) for d in space.dims}}
    summary = RunSummary(
        run=str(run), command=meta.get("command"), algorithm=meta.get("algorithm"),
        config=meta.get("config_path"), model=meta.get("model_name"),
        model_hash=meta.get("model_hash"), samples=int(len(frame)),
        computed_this_time=int(meta.get("computed_last", 0)),
        ok=int(len(ok)), invalid=int((frame["status"] == Status.INVALID).sum()),
        undefined=int((frame["status"] == Status.UNDEFINED).sum()),
        threshold=thr, cells=int(np.isfinite(cmap.miou).sum()),
        blind_spots=len(blind),
        blind_spot_cells=[{"x": c.a, "y": c.b, "miou": round(c.miou, 4), "samples": c.samples}
                          | ({} if c.lower is None else {"lower": round(c.lower, 4),
                                                         "upper": round(c.upper, 4)})
                          for c in blind],
        estimated=estimated_of(meta, cmap, thr),
        lowest=lowest, elapsed_s=meta.get("elapsed_s"), retraining_samples=scans,
        retraining_skipped=None if retrain else True,
        retraining_camera=camera,
        retraining_format=None if retrain_format == "npy" else retrain_format,
        executors=executors if len(executors := executors_of(meta)) > 1 else None,
        environment_changes=data.environment_changes or None,
        mean_car_iou=None if not len(ok) or "car_iou" not in ok else round(
            float(ok["car_iou"].astype(float).mean()), 4),
        objective=None if col == "car_iou" else data.objective,
        mean_objective=None if col == "car_iou" or not len(ok) else round(
            float(ok[col].astype(float).mean()), 4),
        unlabelled_backgrounds=[r.name for r in space.real_backgrounds if r.kind == "none"]
        or None,
        search=search)
    stored = summary.to_json()   # summary.json holds all but the report's path
    if report:
        from falsify.jobs.report import write_report
        summary = dataclasses.replace(summary, report=str(write_report(run, model=model)))
    write_json(run / "summary.json", stored)
    return summary


def estimated_of(meta: dict, cmap: CellMap, threshold: float) -> dict | None:
    """For a map a level-set run estimated: the grid's samples it stands for, how many were
    scored, and the cells the sampler had not decided when it stopped (its budget spent)."""
    estimates = meta.get("cell_estimates")
    if not estimates or not cmap.estimated:
        return None
    options = meta.get("sampler_options") or {}
    return {"grid_samples": int(sum(e[6] for e in estimates)),
            "scored": int(sum(e[5] for e in estimates)),
            "confidence": float(options.get("confidence", 0.95)),
            "undecided_cells": sum(1 for e in estimates if len(e) > 7 and not e[7])}


def class_maps(meta: dict) -> list[str]:
    """The classes whose own map a run draws: every scored class but unknown / unlabeled, for
    runs scored on more than car (none for a four-class car run: it keeps its files)."""
    if "scored_classes" not in meta:
        return []
    return [c for c in meta["scored_classes"] if c not in ("unknown", "unlabeled")]


def extra_map_pairs(space: Space) -> list[tuple[str, str]]:
    """Other dim pairs worth a map: every pair of dims that vary, besides (x, y)."""
    varying = [n for n, d in space.dims.items() if len(d.grid()) > 1 and n != "background"]
    pairs = []
    for i, a in enumerate(varying):
        for b in varying[i + 1:]:
            if (a, b) != ("x", "y"):
                pairs.append((a, b))
    return pairs
