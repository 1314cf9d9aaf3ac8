"""The paper's retraining experiment as one resumable job: find blind spots, retrain, re-test.

Stages, each recorded in OUT/stages.json when it finishes (a killed run resumes at the stage it
was in; the grids and the fine-tuning resume inside their stage too):

  before    grid over the validation backgrounds V with the model
  rows      grid over the retraining backgrounds R with the model (the rows to re-cast)
  selected  the V cells below the threshold; the scans of R at those cells, re-cast from the
            rows by falsify.jobs.retraining_set.write_retraining_set (which replays them by
            falsify.results.replay).
            With selection "control", as many cells drawn at random (seeded) from V's cells at
            or above the threshold: the same amount of extra data, not aimed at the blind
            spots, so a run pair separates "the blind scans fixed it" from "more training did".
            With selection "rules", R's samples under the rules `falsify explain` finds on V's
            failing samples (their conditions on background dropped: V's streets are not R's);
            with "random", as many of R's valid samples drawn at random (seeded) from the whole
            space: the control of "rules". Both record V's samples under the rules (the region)
            so a pair compares the region's mean before and after
  finetune  falsify.models.train from the model's weights on the training data plus the
            selected scans, each repeated `oversample` times so a few dozen scans weigh against
            thousands
  after     grid over V with the fine-tuned model
  checks    pooled car IoU before and after (falsify.jobs.predict.evaluate) on held-out
            drive-style synthetic scans, the real KITTI sets and semantickitti-mini's
            evaluation split (evaluation only)
  report    maps as CSV, summary.json and the comparison page
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from falsify.checks import check_out_dir, check_range, check_seed, require_torch
from falsify.data.range_npy import npy_files
from falsify.errors import ConfigError
from falsify.executors.driver import ProgressListener
from falsify.fileio import write_text
from falsify.jobs.retrain_config import parse_ids, subset_config
from falsify.jobs.retrain_result import (
    Check,
    FinetuneRecord,
    GridRecord,
    RetrainResult,
    SelectedRecord,
    as_json,
    read_record,
    read_summary,
    result_of,
    result_text,
    rounded,
)
from falsify.jobs.retrain_selection import (
    SELECTIONS,
    control_cells,
    covered,
    random_rows,
    transferable,
)
from falsify.jobs.retraining_set import plain_value, write_retraining_set
from falsify.results.explain import Rule, explain
from falsify.results.store import open_run
from falsify.world.space import Space

STAGES = ("before", "rows", "selected", "finetune", "after", "checks", "report")
STAGE_FILE = "stages.json"
HELD_OUT_FIRST_BACKGROUND = 5000   # the drive-style held-out streets: 5000..5049, seed 2
HELD_OUT_BACKGROUNDS = 50
HELD_OUT_SEED = 2
# What must match for --resume to continue a run (the rest, e.g. workers, may change).
RESUME_KEYS = ("config_hash", "model_hash", "train_data", "validation", "retraining",
               "threshold", "epochs", "batch", "lr", "seed", "oversample", "train_scans",
               "held_out_scans", "precision", "selection")


@dataclass(frozen=True)
class RetrainRequest:
    """Everything that defines one retraining experiment."""

    config: Path
    model: Path                     # ONNX; the .pt beside it is where fine-tuning starts
    train_data: Path                # `falsify dataset` output the model was trained on
    out: Path
    validation: tuple[int, ...]     # background ids of V
    retraining: tuple[int, ...]     # background ids of R
    threshold: float | None = None  # default: the config's
    epochs: int = 1
    time_limit_min: float | None = None
    precision: str = "auto"
    batch: int = 8
    lr: float = 3e-4                # fine-tuning: a third of the from-scratch rate
    seed: int = 0
    oversample: int = 20
    train_scans: int | None = None  # use only the first N training scans (None: all)
    held_out_scans: int = 200
    kitti: Path | None = None       # a folder of real KITTI sets to check on (None: skipped)
    holdout: tuple[Path, ...] = ()  # split manifests: held-out scans are never trained on
    workers: int = 2
    resume: bool = False
    selection: str = "blind"        # or "control": random non-blind cells, as many; or
    #                                 "rules": R's samples under explain's rules on V; or
    #                                 "random": as many of R's samples as "rules" takes


@dataclass(frozen=True)
class RetrainContext:
    """What `RetrainJob.prepare` found, for every stage: the space, the request's resume key,
    the threshold and the training data (its scans and index.json, if any)."""

    space: Space
    key: dict
    threshold: float
    train_files: list[Path]
    train_index: dict | None


# -- the job ----------------------------------------------------------------------------------
class RetrainJob:
    """Runs the stages in order; `on_stage(name)` is called before a stage is computed (the
    seam tests use to simulate a kill); `on_progress` is handed to each grid run."""

    def __init__(self, req: RetrainRequest, on_stage: Callable[[str], None] | None = None,
                 on_progress: ProgressListener | None = None):
        self.req = req
        self.on_stage = on_stage
        self.on_progress = on_progress

    # checks before anything is written
    def prepare(self) -> RetrainContext:
        from falsify.data.holdout import check_not_held_out
        from falsify.models.runners import load_segmenter
        from falsify.models.train import list_scans
        from falsify.world.space import load_space

        req = self.req
        _check_numbers(req)
        space = load_space(req.config)
        used = {int(b) for b in space.dims["background"].grid()}
        _check_backgrounds(req, used)
        _check_settings(req)
        seg = load_segmenter(req.model, threads=1)
        train_files = list_scans(req.train_data, "--train-data")
        train_index = _read_index(req.train_data)
        check_not_held_out(train_files, req.holdout, "--train-data")
        if space.real_backgrounds:   # what R holds is trained on
            check_not_held_out([space.real_backgrounds[b].bin for b in req.retraining],
                               req.holdout, "--retraining-backgrounds")
        _check_train_index(req, train_index, used, bool(space.real_backgrounds))
        threshold = req.threshold if req.threshold is not None else space.threshold
        key = {"config_hash": space.config_hash, "model_hash": seg.model_hash,
               "train_data": str(req.train_data.resolve()), "validation": list(req.validation),
               "retraining": list(req.retraining), "threshold": threshold,
               "epochs": req.epochs, "batch": req.batch, "lr": req.lr, "seed": req.seed,
               "oversample": req.oversample, "train_scans": req.train_scans,
               "held_out_scans": req.held_out_scans, "precision": req.precision,
               "selection": req.selection}
        _check_out(req, key)
        return RetrainContext(space, key, threshold, train_files, train_index)

    def run(self) -> RetrainResult:
        ctx = self.prepare()
        require_torch("falsify retrain (its fine-tuning)")   # before the first stage's grid
        req = self.req
        req.out.mkdir(parents=True, exist_ok=True)
        state_path = req.out / STAGE_FILE
        if state_path.exists():
            state = json.loads(state_path.read_text(encoding="utf-8"))
        else:   # first, so that a kill from here on leaves a run that --resume continues
            state = {"request": ctx.key, "done": {}}
            _write_state(state_path, state)
        for name, ids in (("validation", req.validation), ("retraining", req.retraining)):
            path = req.out / f"config-{name}.toml"
            if not path.is_file():   # whole or absent: written atomically
                write_text(path, subset_config(req.config, ids, name,
                                               ctx.space.real_backgrounds))
        computed, reused = [], []
        for stage in STAGES:
            if stage in state["done"]:
                reused.append(stage)
                continue
            if state["done"].get("selected", {}).get("scans") == 0 and stage != "report":
                continue   # nothing below the threshold: nothing to retrain or re-test
            if self.on_stage is not None:
                self.on_stage(stage)
            state["done"][stage] = as_json(getattr(self, f"_{stage}")(ctx, state["done"]))
            _write_state(state_path, state)
            computed.append(stage)
        return self._result(ctx, state["done"], tuple(computed), tuple(reused))

    # -- stages ---------------------------------------------------------------------------
    def _grid(self, name: str, config: str, model: Path, threshold: float) -> GridRecord:
        from falsify.jobs.run import RunRequest, execute
        from falsify.results.store import STORE_NAME

        out = self.req.out / name
        s = execute(RunRequest(config=self.req.out / config, out=out, command="grid",
                               model=str(model), workers=self.req.workers,
                               resume=(out / STORE_NAME).exists(), threshold=threshold,
                               report=False), on_progress=self.on_progress)
        return GridRecord.of(s)

    def _before(self, ctx: RetrainContext, done: dict) -> GridRecord:
        return self._grid("before", "config-validation.toml", self.req.model, ctx.threshold)

    def _rows(self, ctx: RetrainContext, done: dict) -> GridRecord:
        return self._grid("rows", "config-retraining.toml", self.req.model, ctx.threshold)

    def _selected(self, ctx: RetrainContext, done: dict) -> SelectedRecord:
        v = open_run(self.req.out / "before")
        r = open_run(self.req.out / "rows")
        cmap = v.cell_map()
        blind = cmap.blind_spots(ctx.threshold)
        chosen = None    # the blind cells
        rules: tuple[Rule, ...] = ()
        select = None
        if self.req.selection == "control" and blind:
            chosen = control_cells(cmap, ctx.threshold, len(blind), self.req.seed)
        by_rules = self.req.selection in ("rules", "random")
        region = None
        if by_rules:
            rules = explain(v.frame, v.space, ctx.threshold, score=v.score_column).rules
            select = functools.partial(covered, rules, r.space)
            region = sorted(int(i) for i in v.ok["eval_index"][covered(rules, v.space, v.ok)])
        if self.req.selection == "random":
            select = functools.partial(random_rows, int(covered(rules, r.space, r.ok).sum()),
                                       r.ok["eval_index"], self.req.seed)
        # R's rows at the chosen cells of V (or under V's rules), into OUT/selected/retrain
        n = write_retraining_set(dataclasses.replace(r, path=self.req.out / "selected"), cmap,
                                 ctx.threshold, cells=chosen, select=select)
        return SelectedRecord(
            cells=[{"x": c.a, "y": c.b, "miou": round(c.miou, 4)} for c in blind],
            selection=self.req.selection,
            control_cells=None if chosen is None else [
                {"x": plain_value(a), "y": plain_value(b)} for a, b in chosen],
            rules=[transferable(rule).text() or "(a street of V only)" for rule in rules]
            if by_rules else None,
            region=region,
            scans=n, folder=str(self.req.out / "selected" / "retrain"))

    def _finetune(self, ctx: RetrainContext, done: dict) -> FinetuneRecord:
        from falsify.models.train import CHECKPOINT, TrainConfig, train

        req = self.req
        data = req.out / "finetune-data"
        if data.exists():
            shutil.rmtree(data)
        data.mkdir(parents=True)
        files = ctx.train_files[:req.train_scans] if req.train_scans else ctx.train_files
        for f in files:
            (data / f"t-{f.name}").symlink_to(f.resolve())
        selected = npy_files(req.out / "selected" / "retrain")
        for k in range(req.oversample):
            for f in selected:
                (data / f"s{k:03d}-{f.name}").symlink_to(f.resolve())
        out = req.out / "finetune"
        out.mkdir(parents=True, exist_ok=True)
        # models.train prints a line per epoch: it goes to a log file, not to our caller.
        with open(out / "train_stdout.log", "a", encoding="utf-8") as log, \
                contextlib.redirect_stdout(log):
            summary = train(TrainConfig(
                data=str(data), out=str(out), epochs=req.epochs, batch=req.batch,
                seed=req.seed, lr=req.lr, precision=req.precision,
                time_limit_min=req.time_limit_min, init=str(req.model.with_suffix(".pt")),
                resume=(out / CHECKPOINT).exists()))
        return FinetuneRecord(
            model=str(out / "squeezeseg.onnx"), training_scans=len(files),
            selected_scans=len(selected), oversample=req.oversample,
            scans_per_epoch=len(files) + req.oversample * len(selected),
            epochs=req.epochs, stopped=summary.get("stopped"),
            epoch_reached=summary.get("epoch"), loss=summary.get("loss"),
            log=str(out / "train_log.jsonl"))

    def _after(self, ctx: RetrainContext, done: dict) -> GridRecord:
        return self._grid("after", "config-validation.toml", _tuned(done), ctx.threshold)

    def _checks(self, ctx: RetrainContext, done: dict) -> dict:
        from falsify.data.scansets import ScanSet, read_set
        from falsify.jobs.predict import evaluate
        from falsify.models.runners import load_segmenter
        from falsify.sensor.lidar import load_sensor

        req = self.req
        sets: list[tuple[str, ScanSet | None, str]] = []
        if req.held_out_scans:
            sets.append(("held-out drive-style synthetic", self._held_out(ctx),
                         f"streets {HELD_OUT_FIRST_BACKGROUND}.."
                         f"{HELD_OUT_FIRST_BACKGROUND + HELD_OUT_BACKGROUNDS - 1}, seed "
                         f"{HELD_OUT_SEED}, drive traffic"))
        kitti = req.kitti
        sensor = load_sensor(ctx.space.sensor)
        sq = sorted((kitti / "squeezeseg").glob("*.npy")) if kitti else []
        sets.append(("real KITTI, SqueezeSeg layout",
                     read_set("squeezeseg", sq, sensor) if sq else None,
                     "kitti/squeezeseg/*.npy" if sq
                     else f"skipped: no scans in {kitti}/squeezeseg" if kitti
                     else "skipped: no --kitti"))
        bins = sorted((kitti / "semantickitti").glob("*.bin")) if kitti else []
        sets.append(("real SemanticKITTI seq. 00",
                     read_set("semantickitti", bins, sensor) if bins else None,
                     "kitti/semantickitti/*.bin projected with the config's sensor" if bins
                     else f"skipped: no scans in {kitti}/semantickitti" if kitti
                     else "skipped: no --kitti"))
        sets.append(evaluation_split(kitti, sensor, req.holdout))
        present = [s for _, s, _ in sets if s is not None]
        scores = {}
        for when, model in (("before", req.model), ("after", _tuned(done))):
            result = evaluate(load_segmenter(model, threads=2), present) if present else None
            scores[when] = [] if result is None else [e.pooled.car().iou for e in result.sets]
        checks, k = [], 0
        for name, scans, note in sets:
            if scans is None:
                checks.append(Check(name, 0, None, None, note))
                continue
            checks.append(Check(name, len(scans), rounded(scores["before"][k]),
                                rounded(scores["after"][k]), note))
            k += 1
        return {"checks": [asdict(c) for c in checks]}

    def _held_out(self, ctx: RetrainContext):
        """Drive-style held-out scans with the training set's sensor effects (written once)."""
        from falsify.data.scansets import read_set
        from falsify.data.training import TrafficOptions, write_dataset
        from falsify.sensor.lidar import load_sensor

        idx = ctx.train_index or {}
        effects = {k: float(idx[k]) for k in ("ray_drop", "range_noise") if k in idx}
        sensor = load_sensor(ctx.space.sensor, **effects)
        folder = self.req.out / "held-out"
        opts = TrafficOptions(first_background=HELD_OUT_FIRST_BACKGROUND,
                              backgrounds=HELD_OUT_BACKGROUNDS, traffic="drive")
        write_dataset(sensor, folder, self.req.held_out_scans, seed=HELD_OUT_SEED, opts=opts)
        return read_set("held-out", npy_files(folder), sensor)

    def _report(self, ctx: RetrainContext, done: dict) -> dict:
        from falsify.fileio import write_bytes, write_json

        out = self.req.out
        files = {}
        for name in ("before", "after"):
            src = out / name / "maps" / "miou_x_y.csv"
            if src.exists():
                dst = out / f"miou_{name}.csv"
                write_bytes(dst, src.read_bytes())
                files[f"map_{name}"] = str(dst)
        files["summary"] = str(out / "summary.json")
        # The summary is written with the page's path before the page: both then agree.
        if "after" in done:
            files["report"] = str(out / "comparison.html")
        result = self._result(ctx, {**done, "report": {"files": files}}, (), ())
        write_json(out / "summary.json", result.to_json())
        if "after" in done:
            from falsify.jobs.report import write_report
            # the page reads the summary as written, so `falsify report --retrain` rebuilds it
            write_report(out / "after", out / "comparison.html", compare=out / "before",
                         predict=False, retrain=read_summary(out / "summary.json", "summary"))
        return {"files": files}

    # -- result ---------------------------------------------------------------------------
    def _result(self, ctx: RetrainContext, done: dict, computed: tuple[str, ...],
                reused: tuple[str, ...]) -> RetrainResult:
        return result_of(self.req.out, self.req.selection, ctx.threshold, done, computed,
                         reused)


def _check_numbers(req: RetrainRequest) -> None:
    """The threshold, counts, seed and output folder's name, before the config is read."""
    from falsify.jobs.gate import check_threshold

    check_threshold(req.threshold)
    for option, value, lo in (("--epochs", req.epochs, 1), ("--oversample", req.oversample, 1),
                              ("--batch", req.batch, 1), ("--workers", req.workers, 1),
                              ("--held-out-scans", req.held_out_scans, 0),
                              ("--train-scans", req.train_scans, 1)):
        check_range(value, option, lo)
    check_seed(req.seed)
    check_out_dir(req.out)


def _check_backgrounds(req: RetrainRequest, used: set[int]) -> None:
    """V and R: given, among the config's backgrounds (`used`), and disjoint."""
    for option, ids in (("--validation-backgrounds", req.validation),
                        ("--retraining-backgrounds", req.retraining)):
        if not ids:
            raise ConfigError(f"{option}: no backgrounds given")
        outside = sorted(set(ids) - used)
        if outside:
            raise ConfigError(f"{option}: background {outside[0]} is not in "
                              f"{req.config}'s backgrounds {sorted(used)}")
    both = sorted(set(req.validation) & set(req.retraining))
    if both:
        raise ConfigError(f"--validation-backgrounds and --retraining-backgrounds share "
                          f"background {both[0]}; V and R must be disjoint")


def _check_settings(req: RetrainRequest) -> None:
    """Selection, precision, learning rate, time limit, and the model with its weights."""
    if req.selection not in SELECTIONS:
        raise ConfigError(f"--selection: {req.selection!r}; allowed: {', '.join(SELECTIONS)}")
    if req.precision not in ("auto", "bf16", "fp32"):
        raise ConfigError(f"--precision: {req.precision!r}; allowed: auto, bf16, fp32")
    if not req.lr > 0:
        raise ConfigError(f"--lr: {req.lr} must be > 0")
    if req.time_limit_min is not None and not req.time_limit_min > 0:
        raise ConfigError(f"--time-limit-min: {req.time_limit_min} must be > 0")
    if req.model.suffix != ".onnx" or not req.model.is_file():
        raise ConfigError(f"--model {req.model}: expected an existing .onnx file")
    weights = req.model.with_suffix(".pt")
    if not weights.is_file():
        raise ConfigError(f"--model {req.model}: fine-tuning starts from {weights}, "
                          "which does not exist")
    if req.kitti is not None:
        if not req.kitti.is_dir():
            raise ConfigError(f"--kitti {req.kitti}: no such folder")
        sets = ("squeezeseg", "semantickitti", "semantickitti-mini")
        if not any((req.kitti / s).is_dir() for s in sets):
            raise ConfigError(f"--kitti {req.kitti}: holds none of the real sets it checks on "
                              f"({', '.join(s + '/' for s in sets)}); leave --kitti out to "
                              "skip the checks")


def _check_train_index(req: RetrainRequest, train_index: dict | None, used: set[int],
                       real: bool) -> None:
    """Training streets (by the training set's index.json) apart from the held-out streets
    and, on our streets (not `real` scans), from the config's test backgrounds."""
    held = set(range(HELD_OUT_FIRST_BACKGROUND,
                     HELD_OUT_FIRST_BACKGROUND + HELD_OUT_BACKGROUNDS))
    if train_index is not None and req.held_out_scans:
        first = int(train_index.get("first_background", -1))
        span = set(range(first, first + int(train_index.get("backgrounds", 0))))
        if span & held:
            raise ConfigError(f"--train-data {req.train_data}: training backgrounds overlap "
                              f"the held-out streets {min(held)}..{max(held)}")
        if span & used and not real:
            raise ConfigError(f"--train-data {req.train_data}: training backgrounds overlap "
                              f"{req.config}'s test backgrounds")


def _check_out(req: RetrainRequest, key: dict) -> None:
    """--out new and empty, or (with --resume) a run of the same experiment (RESUME_KEYS)."""
    state_path = req.out / STAGE_FILE
    if state_path.exists():
        if not req.resume:
            raise ConfigError(f"--out {req.out} already holds a retraining run; pass "
                              "--resume to continue it or choose another --out")
        old = json.loads(state_path.read_text(encoding="utf-8"))["request"]
        for k in RESUME_KEYS:
            if old.get(k) != key[k]:
                raise ConfigError(f"--resume: {k} differs from the run in {req.out} "
                                  f"({old.get(k)!r} there, {key[k]!r} now)")
    elif req.resume:
        raise ConfigError(f"--resume: {req.out} holds no retraining run ({STAGE_FILE} "
                          "missing)")
    elif req.out.exists() and any(req.out.iterdir()):
        raise ConfigError(f"--out {req.out}: directory exists and is not empty")


def evaluation_split(kitti: Path | None, sensor, holdout: tuple[Path, ...] = ()) -> tuple:
    """The held-out scans of `kitti`/semantickitti-mini (by the split manifests, else its
    official split) as one check, only reported on; or the note saying why it was skipped."""
    from falsify.data.holdout import holdout_for
    from falsify.data.scansets import read_set
    from falsify.world.real_scans import sequence_dirs, sequence_files

    name = "real held-out split (semantickitti-mini)"
    root = kitti / "semantickitti-mini" if kitti else None
    found = sequence_dirs(root) if root is not None and root.is_dir() else None
    files = [f for d in (found or {}).values() for f in sequence_files(d)]
    held = holdout_for(files, holdout).held_out(files)
    if not held:
        return (name, None, f"skipped: no held-out scans in {root}" if root is not None
                else "skipped: no --kitti")
    return (name, read_set("evaluation split", held, sensor),
            f"{len(held)} scans, front 90 degrees, projected with the config's sensor; labels "
            "from labels/")


def _tuned(done: dict) -> Path:
    """The fine-tuned model of a finetune stage that is done."""
    return Path(read_record(FinetuneRecord, done["finetune"]).model)


def _read_index(folder: Path) -> dict | None:
    try:
        return json.loads((folder / "index.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _write_state(path: Path, state: dict) -> None:
    from falsify.fileio import write_json
    write_json(path, state)


__all__ = ["SELECTIONS", "control_cells", "RetrainRequest", "RetrainJob", "RetrainResult",
           "Check", "parse_ids", "read_summary", "result_text"]
