"""`falsify retrain`: the paper's experiment (blind spots on V, fine-tune on R, re-test)."""

from __future__ import annotations

import argparse
from pathlib import Path

from falsify.cli.common import emit, holdout_option
from falsify.cli.progress import ProgressBar
from falsify.paths import config_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--model", required=True, help="an .onnx with its .pt beside it, or a "
                   "bundled name such as squeezeseg-drive")
    p.add_argument("--train-data", required=True, help="the model's training scans")
    p.add_argument("--validation-backgrounds", required=True, metavar="IDS", help="V, e.g. 0-6")
    p.add_argument("--retraining-backgrounds", required=True, metavar="IDS",
                   help="R, e.g. 7-14")
    p.add_argument("--out", required=True, help="the experiment's folder (its stages' runs)")
    p.add_argument("--resume", action="store_true", help="continue at the unfinished stage")
    p.add_argument("--threshold", type=float, default=None,
                   help="mIoU below which a cell is blind (default: the config's)")
    p.add_argument("--epochs", type=int, default=1, help="fine-tuning epochs (default 1)")
    p.add_argument("--time-limit-min", type=float, default=None,
                   help="stop fine-tuning after this many minutes (default: no limit)")
    p.add_argument("--precision", default="auto", choices=["auto", "bf16", "fp32"],
                   help="auto: bf16 where the CPU (or GPU) computes it natively, else fp32")
    p.add_argument("--batch", type=int, default=8, help="scans a step (default 8)")
    p.add_argument("--lr", type=float, default=3e-4, help="learning rate (default 3e-4)")
    p.add_argument("--seed", type=int, default=0, help="fine-tuning's seed (default 0)")
    p.add_argument("--oversample", type=int, default=20,
                   help="times each selected scan appears in the fine-tuning set")
    p.add_argument("--train-scans", type=int, default=None,
                   help="use only the first N training scans")
    p.add_argument("--held-out-scans", type=int, default=200,
                   help="synthetic drive-style scans of held-out streets to check on before "
                   "and after (0: none; default 200)")
    p.add_argument("--kitti", default=None, metavar="DIR",
                   help="a folder of real KITTI sets to check on before and after (squeezeseg/"
                   " .npy scans, semantickitti/ .bin scans, the held-out scans of "
                   "semantickitti-mini/); the checks are skipped without it")
    holdout_option(p)
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the grids on V (default 2)")
    p.add_argument("--selection", default="blind",
                   choices=["blind", "control", "rules", "random"],
                   help="blind: R's scans at V's blind cells (the paper); control: at as many "
                   "random cells that are not blind, to tell the blind scans' effect from "
                   "more training's; rules: R's samples under the rules explain finds on V; "
                   "random: as many of R's samples as rules takes, from anywhere (its control)")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.jobs.retrain import RetrainJob, RetrainRequest, parse_ids, result_text
    from falsify.models.runners import resolve_model

    model = resolve_model(args.model)   # a path, or a bundled name such as squeezeseg-drive
    req = RetrainRequest(
        config=config_path(args.config), model=model, train_data=Path(args.train_data),
        out=Path(args.out), validation=parse_ids(args.validation_backgrounds,
                                                 "--validation-backgrounds"),
        retraining=parse_ids(args.retraining_backgrounds, "--retraining-backgrounds"),
        threshold=args.threshold, epochs=args.epochs, time_limit_min=args.time_limit_min,
        precision=args.precision, batch=args.batch, lr=args.lr, seed=args.seed,
        oversample=args.oversample, train_scans=args.train_scans,
        held_out_scans=args.held_out_scans,
        kitti=Path(args.kitti) if args.kitti else None,
        holdout=tuple(Path(h) for h in args.holdout or ()),
        workers=args.workers, resume=args.resume, selection=args.selection)
    result = RetrainJob(req, on_progress=None if args.json else ProgressBar()).run()
    emit(args, result.to_json(), result_text(result))
    return 0
