"""`falsify fit-returns`: fit the sensor's return model on KITTI's object frames, or per class on
labelled fit scans (falsify.jobs.fit_returns says what is fitted)."""

from __future__ import annotations

import argparse
import json

from falsify.checks import check_out_file
from falsify.cli.common import emit, holdout_option, predict_sequences


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="KITTI .bin frames or folders of them (an object "
                   "directory's velodyne/); with "
                   "--labelled, SemanticKITTI roots, sequence folders or .bin scans with their "
                   ".label (fit data only: held-out scans are refused)")
    p.add_argument("--out", required=True, help="the return model's JSON file")
    p.add_argument("--labelled", action="store_true",
                   help="fit on labelled scans, with a reflectivity distribution and a return "
                   "probability per SemanticKITTI class")
    p.add_argument("--sequences", default=None, metavar="SS,SS",
                   help="with --labelled: only these sequences of a SemanticKITTI root")
    p.add_argument("--dropout-from", default=None, metavar="MODEL",
                   help="with --labelled: drop returns as this model does (a name in "
                   "configs/returns/ or a .json file) and fit only the intensity")
    p.add_argument("--name", default=None, help="the model's name (default: --out's stem)")
    holdout_option(p)
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    """Fit, write the return model to --out and print its main parameters."""
    from falsify.cli.common import UsageError
    from falsify.fileio import write_text

    out = check_out_file(args.out, suffixes=(".json",))
    name = args.name or out.stem
    if args.labelled:
        from falsify.jobs.fit_returns import fit_labelled, labelled_frames

        sequences = predict_sequences(args.sequences, args.scans)
        dropout_from = None
        if args.dropout_from is not None:
            from falsify.errors import ConfigError
            from falsify.jobs.fit_returns import DROPOUT_KEYS
            from falsify.sensor.returns import load_return_model

            try:
                other = load_return_model(args.dropout_from)
            except ConfigError as exc:
                raise UsageError(f"--dropout-from: {exc}") from None
            dropout_from = {k: _plain(getattr(other, k)) for k in DROPOUT_KEYS}
        frames = labelled_frames(args.scans, sequences, args.holdout or ())
        doc = fit_labelled(frames, name, _command(args), dropout_from)
    else:
        for opt, v in (("--sequences", args.sequences), ("--dropout-from", args.dropout_from)):
            if v:
                raise UsageError(f"{opt}: only with --labelled")
        from falsify.data.velodyne import fit_frames
        from falsify.jobs.fit_returns import fit

        doc = fit(fit_frames(args.scans, args.holdout or (), "fit-returns' frames"), _command(args))
        doc["name"] = name
    write_text(out, json.dumps(doc, indent=1) + "\n")
    p = doc["params"]
    summary = {k: p[k] for k in ("reflectivity", "cos_exp", "atten_m", "p_min", "p_max", "i0",
                                 "k")}
    if "classes" in p:
        c = p["classes"]
        summary["classes"] = {n: {"median": c["reflectivity"][i][len(c["z"]) // 2],
                                  "instance_share": c["instance_share"][i],
                                  "p_return": c["p_return"][i], "points": c["points"][i]}
                              for i, n in enumerate(c["names"]) if c["points"][i]}
    summary["out"] = str(out)
    emit(args, summary, _text(summary))
    return 0


def _command(args) -> str:
    """The command as run, recorded in the model; a path under $SEMANTICKITTI, $KITTI_OBJECT or
    $KITTI is written with the variable, so the record holds no folder of this machine's."""
    import os
    import shlex

    roots = [(v, os.environ[v].rstrip("/")) for v in ("SEMANTICKITTI", "KITTI_OBJECT", "KITTI")
             if os.environ.get(v, "").strip("/")]

    def portable(arg: str) -> str:
        for var, root in roots:
            if arg == root or arg.startswith(root + "/"):
                return f"${var}{arg[len(root):]}"
        return shlex.quote(arg)

    parts = ["falsify", "fit-returns", *(["--labelled"] if args.labelled else []),
             *map(portable, args.scans)]
    for opt, v in (("--sequences", args.sequences), ("--dropout-from", args.dropout_from),
                   ("--name", args.name)):
        if v:
            parts += [opt, portable(v)]
    for h in args.holdout or ():
        parts += ["--holdout", portable(h)]
    return " ".join([*parts, "--out", portable(args.out)])


def _plain(v):
    """Tuples (of tuples) as the lists a JSON document holds."""
    return [_plain(x) for x in v] if isinstance(v, tuple) else v


def _text(s: dict) -> str:
    """The fitted gains, and per class the median reflectivity, spread and P(return)."""
    lines = [f"wrote {s['out']}: cos_exp {s['cos_exp']:.3f}, atten_m {s['atten_m']:.0f}, "
             "levels " + ", ".join(f"{k} {v:.3f}" for k, v in s["reflectivity"].items())]
    if "classes" in s:
        lines.append(f"{'class':<14} {'points':>8} {'median':>7} {'between':>8} {'P(return)':>9}")
        for n, c in s["classes"].items():
            lines.append(f"{n:<14} {c['points']:>8} {c['median']:>7.3f} "
                         f"{c['instance_share']:>8.2f} {c['p_return']:>9.3f}")
    return "\n".join(lines)
