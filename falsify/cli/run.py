"""What grid and search share: their options, the run job's call and summary, what a stopped
run keeps, and the run folder's lock taken before the parser is built."""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import sys
from pathlib import Path

from falsify.checks import MAX_SAMPLES
from falsify.cli.common import (
    BACKEND_HELP,
    DEVICE_HELP,
    MODEL_HELP,
    camera_option,
    check_backend,
    emit,
)
from falsify.cli.progress import ProgressBar
from falsify.errors import FalsifyError


def run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--out", required=True, help="run directory (results.sqlite, maps, report)")
    p.add_argument("--model", default=None, help=MODEL_HELP)
    p.add_argument("--backend", choices=["onnx", "torch", "python"], default=None,
                   help=BACKEND_HELP)
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help=DEVICE_HELP)
    p.add_argument("--inference", choices=["auto", "worker", "shared"], default="auto",
                   help="where the network runs with several --workers: in each worker, or "
                   "in one shared process that batches all workers' scans (auto: shared on "
                   "cuda, else in each worker)")
    p.add_argument("--objective", default=None, metavar="CLASS",
                   help="what the samplers minimise and the maps show: a class the model "
                        "predicts (car, person, ... SemanticKITTI's names) or miou (default: "
                        "the placed actors' class)")
    p.add_argument("--workers", type=int, default=1,
                   help="local worker processes, or Ray actors with --executor ray")
    p.add_argument("--executor", choices=["process", "ray"], default="process",
                   help="process: worker processes on this machine; ray: warm actors on a Ray "
                   'cluster (pip install "falsify[ray]")')
    p.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="with --executor ray: the head of an existing Ray cluster (HOST:PORT, "
                   "ray://HOST:PORT or auto); default: start a local Ray instance")
    p.add_argument("--seed", type=int, default=None, help="default: the config's seed")
    p.add_argument("--resume", action="store_true", help="continue a killed run")
    p.add_argument("--threshold", type=float, default=None,
                   help="mIoU below which a cell is a blind spot (default: config, 0.65)")
    p.add_argument("--fidelity", default="exact",
                   choices=["fastest", "fast", "balanced", "exact"],
                   help="speed against accuracy, by the variant of the bundled network run: "
                   "exact (fp32, 3 CRF iterations; the default), balanced (int8, 3), fast "
                   "(int8, 1), fastest (int8, no CRF); not with --model or --backend torch")
    p.add_argument("--no-report", action="store_true",
                   help="write no report.html (the maps, tables and summary.json still)")
    p.add_argument("--no-retrain", action="store_true",
                   help="write no retraining set (the scans of the blind cells' samples, "
                   "0.75 MB each: 661 scans for the paper grid with 46 blind cells), as a CI "
                   "gate needs none; a retrain/ folder of an earlier finish is removed")
    p.add_argument("--max-samples", type=int, default=MAX_SAMPLES,
                   help=f"refuse a grid or budget larger than this (default {MAX_SAMPLES:,})")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    camera_option(p, "also store the camera images of the retraining set beside its scans")
    p.add_argument("--retrain-format", choices=["npy", "semantickitti"], default="npy",
                   help="the retraining set's layout: npy, SqueezeSeg's range images; "
                   "semantickitti, sequences/00/velodyne/*.bin and labels/*.label (raw ids), "
                   "what RangeNet++'s or SalsaNext's loaders read")
    p.add_argument("--json", action="store_true")


def summary_text(s) -> str:
    """A run's summary (RunSummary) in a few lines."""
    low = s.lowest
    what = "car IoU" if s.objective is None else (
        "mIoU" if s.objective == "miou" else f"{s.objective} IoU")
    key = next((k for k in low if k != "sample"), "car_iou") if low else "car_iou"
    where = "" if low is None else ", ".join(f"{k}={v}" for k, v in low["sample"].items()
                                             if k in ("x", "y", "yaw", "background",
                                                      "car_model", "actor"))
    mean = s.mean_car_iou if s.objective is None else s.mean_objective
    lines = [
        f"{s.samples} samples ({s.computed_this_time} computed now, {s.invalid} invalid, "
        f"{s.undefined} undefined) in {s.elapsed_s:.1f} s",
        f"blind spots: {s.blind_spots} of {s.cells} cells below mIoU {s.threshold}",
        f"lowest {what}: " + ("- (no valid sample)" if low is None else f"{low[key]} at {where}"),
        f"mean {what}: {'-' if mean is None else mean}",
        (f"retraining set: {s.retraining_samples} scans in {Path(s.run) / 'retrain'}"
         + (" (SemanticKITTI layout)" if s.retraining_format == "semantickitti" else "")
         if s.retraining_samples else
         "retraining set: not written (--no-retrain)" if s.retraining_skipped else
         "retraining set: none (no valid sample in a blind-spot cell), so no retrain/ folder"),
    ]
    if s.estimated:
        e = s.estimated
        lines.insert(2, f"estimated map (level-set): {e['scored']} of the grid's "
                     f"{e['grid_samples']} samples scored ({e['scored'] / e['grid_samples']:.0%});"
                     f" {e['undecided_cells']} cells undecided at {e['confidence']:.0%}")
    if s.unlabelled_backgrounds:
        u = s.unlabelled_backgrounds
        names = ", ".join(u[:3]) + (f", and {len(u) - 3} more" if len(u) > 3 else "")
        obj = "car" if s.objective in (None, "miou") else s.objective
        lines.append(f"real scans without labels: {len(u)} ({names}); their real_iou and "
                     f"real_recall are empty, and a {obj} predicted on one of their real "
                     f"{obj}s counts against the inserted {obj} (read inserted_recall)")
    if s.executors:
        lines.append(f"computed on executors {', then '.join(s.executors)} (resumed on another; "
                     "the rows do not depend on the executor)")
    if s.environment_changes:
        lines.append(f"computed under more than one environment "
                     f"({'; '.join(s.environment_changes)}): rows from each may differ in their "
                     "numbers (each is kept in the run's sessions)")
    if s.report:
        lines.append(f"report: {s.report}")
    return "\n".join(lines)


def _stopped_text(argv: list[str], out: Path, stored: int | None, advice: str = "") -> str:
    """What a stopped run keeps (`stored` samples; None: not counted) and the command that goes
    on: the same with --resume where a store is left, else the same again (a fresh run that
    stored nothing is removed); see `continue_command`."""
    from falsify.results.store import STORE_NAME
    then = f"{advice}, then " if advice else ""
    if not (out / STORE_NAME).exists():
        return (f"nothing was stored in {out}; {then}run it again with: "
                f"{continue_command(argv, out, resume=False)}")
    kept = "the finished samples are" if stored is None else f"{stored} samples are"
    return (f"{kept} stored safely in {out}; {then}continue with: "
            f"{continue_command(argv, out)}")


def interrupted_text(argv: list[str], out: Path) -> str:
    """`_stopped_text` of a run stopped by a signal, its rows counted in its store."""
    from falsify.results.store import stored_samples
    try:
        stored: int | None = stored_samples(out)
    except FalsifyError:
        stored = None
    return _stopped_text(argv, out, stored)


def _options_end(argv: list[str]) -> int:
    """Where the options of a command line end: at its `--` (after which every word is a
    positional argument, even one spelt like an option), else at its end."""
    return argv.index("--") if "--" in argv else len(argv)


def _is_resume(word: str) -> bool:
    """--resume, or an abbreviation argparse reads as it (--res)."""
    return len(word) >= 3 and "--resume".startswith(word)


def with_resume(argv: list[str]) -> list[str]:
    """The command line with --resume among its options: put before a `--`, where argparse
    still reads it as an option (after it, `--resume` is a stray positional argument)."""
    end = _options_end(argv)
    if any(_is_resume(a) for a in argv[:end]):
        return list(argv)
    return [*argv[:end], "--resume", *argv[end:]]


def without_resume(argv: list[str]) -> list[str]:
    """The command line with its --resume options dropped (not a positional after `--`)."""
    end = _options_end(argv)
    return [a for a in argv[:end] if not _is_resume(a)] + argv[end:]


def _names_local_path(word: str) -> bool:
    """Whether a word of a command line names an existing file or folder relative to the working
    folder: itself, or a plug-in's FILE.py before its :FACTORY."""
    for path in (word, word.rpartition(":")[0]):
        try:
            if path and not Path(path).is_absolute() and Path(path).exists():
                return True
        except (OSError, ValueError):   # too long a name, say: no file of the run's
            continue
    return False


def continue_command(argv: list[str], out: Path, resume: bool = True) -> str:
    """The command that goes on with a stopped grid or search, to paste in a shell anywhere:
    `argv` with --resume (or without it, `resume` False), after `cd DIR &&` where it names a
    path relative to the working folder DIR (its --out, config or model): pasted in another
    folder, those would name other files, or none."""
    words = ["falsify", *(with_resume(argv) if resume else without_resume(argv))]
    end = _options_end(argv)
    values = [w.partition("=")[2] if w.startswith("-") else w for w in argv[1:end]]
    if not out.is_absolute() or any(_names_local_path(v) for v in values + argv[end + 1:]):
        try:
            return f"cd {shlex.quote(os.getcwd())} && {shlex.join(words)}"
        except OSError:   # the working folder is gone: there is none to go back to
            pass
    return shlex.join(words)


def run_folder(argv: list[str]) -> Path | None:
    """The run folder of a grid or search command line, read before the parser is built: its
    --out (or --ou) given as `--out DIR` or `--out=DIR`, the last one given as argparse takes
    it, among the options (None for any other spelling, or command)."""
    if argv[:1] not in (["grid"], ["search"]):
        return None
    options = argv[1:_options_end(argv)]
    out = None
    for i, word in enumerate(options):
        name, eq, value = word.partition("=")
        if name in ("--out", "--ou"):
            out = value if eq else (options[i + 1] if i + 1 < len(options) else out)
    return Path(out) if out else None


def lock_early(out: Path | None, argv: list[str]) -> contextlib.AbstractContextManager:
    """Lock a run folder before the parser is built (its choices import the samplers: seconds),
    so that a second run on a busy folder is refused at once; the run job holds it too."""
    if out is None:
        return contextlib.nullcontext()
    from falsify.results.runlock import RunLock
    return RunLock(out, command=shlex.join(["falsify", *argv]))


def run_job(args, command: str, algorithm: str) -> int:
    from falsify.jobs.run import RunRequest, RunStopped, execute

    backend = check_backend(args.backend, args.model)
    req = RunRequest(
        config=Path(args.config), out=Path(args.out), command=command, algorithm=algorithm,
        budget=getattr(args, "budget", None), seed=args.seed, model=args.model,
        backend=backend, device=args.device, objective=args.objective,
        workers=args.workers, resume=args.resume,
        threshold=args.threshold, fidelity=args.fidelity, report=not args.no_report,
        retrain=not args.no_retrain,
        camera=args.camera, retrain_format=args.retrain_format,
        max_samples=args.max_samples, executor=args.executor,
        address=args.address, confidence=getattr(args, "confidence", None),
        inference=args.inference)
    try:
        summary = execute(req, on_progress=None if args.quiet else ProgressBar())
    except RunStopped as exc:
        argv = getattr(args, "argv", sys.argv[1:])
        raise FalsifyError(f"{exc.reason}: {_stopped_text(argv, req.out, exc.stored, exc.advice)}"
                           ) from None
    emit(args, summary.to_json(), summary_text(summary))
    return 0
