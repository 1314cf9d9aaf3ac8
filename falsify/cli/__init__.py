"""The `falsify` command line: one subcommand per job; user errors exit 2 with one clear line."""

# One module per command (falsify/cli/NAME.py): its `add_arguments(parser)`, its `run(args) ->
# exit code` and its text output. COMMANDS lists them, in the order `falsify --help` shows;
# common.py holds what several share, run.py what grid and search share.

from __future__ import annotations

import argparse
import errno
import os
import shlex
import sys
from types import ModuleType
from typing import NamedTuple

from falsify.cli import (
    adjust,
    agreement,
    bench,
    camera,
    dataset,
    explain,
    export,
    faithfulness,
    fit_returns,
    fit_rings,
    fit_world,
    gate,
    grid,
    holdout,
    predict,
    realism,
    report,
    retrain,
    robustness,
    scan,
    search,
    tradeoff,
    train,
    train_pointnet,
)
from falsify.cli.common import Parser
from falsify.cli.run import interrupted_text, lock_early, run_folder, with_resume
from falsify.cli.signals import stop_name, stop_signals
from falsify.errors import FalsifyError


class Command(NamedTuple):
    """A subcommand: its name, its line in `falsify --help`, the module that owns its options
    and its action, and the description its own --help opens with (None: none)."""

    name: str
    help: str
    module: ModuleType
    description: str | None = None


COMMANDS: tuple[Command, ...] = (
    Command("scan", "ray-cast one sample of a space into a labelled scan", scan),
    Command("dataset", "write training scans from random auto-driving scenes", dataset),
    Command("fit-world", "fit a world profile (the sensor's pitch and height over the road, cars "
            "in view, parked cars kept) on labelled real fit scans", fit_world),
    Command("fit-returns", "fit a sensor's return model (intensity, dropout, the ego body's "
            "shadow) on the points of KITTI object frames", fit_returns,
            "Fit the sensor's return model on the geometry and reflectance of KITTI's object "
            "frames."),
    Command("fit-rings", "fit the HDL-64E's ring elevations and origin heights on the points of "
            "KITTI object frames", fit_rings,
            "Fit the HDL-64E's ring geometry on the geometry of KITTI's object frames."),
    Command("holdout", "write a split manifest: scans that the fits and the trainers refuse "
            "(matched by content, wherever they are)", holdout),
    Command("predict", "run the network on scans; IoU, precision, recall per set and range band "
            "where labelled", predict),
    Command("faithfulness", "car IoU on each real KITTI object car against a synthetic car "
            "inserted in its place (the real car's points removed)", faithfulness),
    Command("realism", "compare synthetic scans with real KITTI scans: statistics, distances, "
            "encoder-feature Frechet distance; JSON + HTML", realism),
    Command("train", "train SqueezeSeg on a folder of .npy scans (resumable)", train,
            "Train SqueezeSeg on a directory of ``*.npy`` scans (H, W, 6), resumable exactly."),
    Command("train-pointnet", "train the reference PointNet plug-in on .npy scans with "
            "SemanticKITTI train ids (resumable)", train_pointnet,
            "Train the reference PointNet plug-in on .npy scans with SemanticKITTI train ids, "
            "resumable exactly."),
    Command("adjust", "logit adjustment: choose alpha on synthetic validation scans and write "
            "the adjusted SqueezeSeg weights", adjust,
            "`falsify adjust WEIGHTS.pt --val DIR --out ADJUSTED.pt`: choose alpha on "
            "synthetic validation scans and write the adjusted weights."),
    Command("export", "export trained SqueezeSeg weights to ONNX with their spec (and a static "
            "int8 copy)", export,
            "`falsify export WEIGHTS.pt --out MODEL.onnx`: export trained weights with their "
            "spec."),
    Command("grid", "evaluate the full factorial grid of a space", grid),
    Command("search", "search a space for low car IoU within a budget", search),
    Command("bench", "measure a fast path beside its naive path", bench),
    Command("report", "write a self-contained HTML report of a run", report),
    Command("gate", "fail (exit 1) when a run has too many blind spots, or new ones against a "
            "baseline", gate,
            "Count blind spots: (x, y) cells whose mIoU is below the threshold. Exit 0 within "
            "the limit, 1 over it, 2 on bad input."),
    Command("explain", "what a run's failing samples have in common: rules over the dims, each "
            "dim's share of the IoU variance, clusters", explain,
            "Read a run (read-only) and describe its samples below the threshold as readable "
            "rules, e.g. 'y >= 16 and |x| >= 3: 33 of 33 samples below 0.65'."),
    Command("tradeoff", "measure speed against mIoU-map error for each knob", tradeoff,
            "Evaluate one sample set under each setting of each knob against a reference "
            "setting; write tradeoff.csv, .json and .html."),
    Command("retrain", "the paper's experiment: blind spots on V, fine-tune on R's scans there, "
            "re-test V and held-out sets (resumable)", retrain),
    Command("agreement", "compare a run on our streets with a run of the same positions on real "
            "scans: how alike the network fails in both", agreement),
    Command("robustness", "per effect and severity the network's score, and mCE / mRR against a "
            "reference network (Robo3D's terms)", robustness),
    Command("calib", "check a LiDAR-camera calibration: KITTI object frames (points in 3D boxes "
            "inside 2D boxes) or our scenes (car points on car pixels)", camera),
)


def build_parser() -> argparse.ArgumentParser:
    from falsify import __version__

    p = Parser(prog="falsify", description=__doc__)
    p.add_argument("--version", action="version", version=f"falsify {__version__}",
                   help="print falsify's version and exit")
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        c = sub.add_parser(command.name, help=command.help, description=command.description)
        command.module.add_arguments(c)
        for action in c._actions:   # one wording for every command's --json
            if "--json" in action.option_strings and action.help is None:
                action.help = "print the summary as JSON on stdout, for scripts and CI"
        c.set_defaults(func=command.module.run)
    return p


def _lenient_output() -> None:
    """Let stdout and stderr print any path: one of non-UTF-8 bytes (argv holds those as
    surrogates) is escaped, not a UnicodeEncodeError after the job's work is done."""
    for stream in (sys.stdout, sys.stderr):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def expand_home(arg: str) -> str:
    """`--opt=~/x` with its `~` expanded, as the shell expands `--opt ~/x` but not this
    spelling (a folder named `~` was made in the working folder)."""
    name, eq, value = arg.partition("=")
    if arg.startswith("--") and eq and value.startswith("~"):
        return f"{name}={os.path.expanduser(value)}"
    return arg


def main(argv: list[str] | None = None) -> int:
    argv = [expand_home(a) for a in (sys.argv[1:] if argv is None else argv)]
    _lenient_output()
    is_run = argv[:1] in (["grid"], ["search"])
    resumable = is_run or argv[:1] in (["train"], ["retrain"], ["train-pointnet"])
    out = run_folder(argv)
    try:
        # every command: a SIGTERM (a cancelled CI job) runs its clean-up and says so, exit 143
        with stop_signals(), lock_early(out, argv):
            parser = build_parser()
            args = parser.parse_args(argv)
            args.argv = argv   # as typed: a stopped run's message repeats it to continue
            return int(args.func(args) or 0)
    except FalsifyError as exc:
        print(f"falsify: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:   # a reader that stopped early (`| head`): end as SIGPIPE would
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # nothing left to flush
        return 128 + 13
    except OSError as exc:   # a path the file system refuses to look up is bad input, not a bug
        if exc.errno != errno.ENAMETOOLONG:
            raise
        print(f"falsify: error: {exc.filename}: too long a path ({exc.strerror}); choose a "
              "shorter one", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        what, code = stop_name(exc)
        bar = "\n" if is_run and sys.stderr.isatty() else ""   # end the progress bar's line
        again = shlex.join(["falsify", *with_resume(argv)])
        print(f"{bar}falsify: {what}" + (f": {interrupted_text(argv, out)}" if out else
                                          f"; continue with: {again}" if resumable else ""),
              file=sys.stderr)
        return code


__all__ = ["COMMANDS", "Command", "build_parser", "main"]
