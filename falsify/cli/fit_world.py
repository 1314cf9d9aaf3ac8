"""`falsify fit-world`: fit a world profile on labelled real fit scans."""

from __future__ import annotations

import argparse
from pathlib import Path

from falsify.checks import check_out_file
from falsify.cli.common import DEFAULT_CONFIG, UsageError, emit, holdout_option, predict_sequences


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="SemanticKITTI roots, sequence folders or .bin "
                   "scans with their .label (fit data only: held-out scans are refused)")
    holdout_option(p)
    p.add_argument("--sequences", default=None, metavar="SS,SS",
                   help="only these sequences of a SemanticKITTI root")
    p.add_argument("--out", required=True, help="the profile's JSON file")
    p.add_argument("--name", default="semantickitti-fit",
                   help="the profile's name (default semantickitti-fit, the shipped profile's: "
                   "name your own)")
    p.add_argument("--config", default=str(DEFAULT_CONFIG),
                   help="a space config whose sensor renders the world's own scenes")
    from falsify.jobs.fit_world import BASE_SCANS
    p.add_argument("--base-scans", type=int, default=BASE_SCANS,
                   help="training scenes of the world rendered to measure its own pose")
    from falsify.world.profile import PARKED_KEEP_GRID
    p.add_argument("--parked-keep", default=",".join(f"{k:g}" for k in PARKED_KEEP_GRID),
                   metavar="K,K", help="shares of the streets' parked cars to try; the one "
                   "whose cars in view and car share come nearest the fit scans' is kept")
    p.add_argument("--compare", action="append", metavar="PATH",
                   help="also describe this labelled set (a `dataset --format semantickitti` "
                   "folder, or real scans, per sequence) against the fit scans: reported only")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.fileio import write_json
    from falsify.jobs.fit_world import describe, distances, fit_world, summarise
    from falsify.sensor.lidar import load_sensor
    from falsify.world.space import load_space

    out = check_out_file(args.out, suffixes=(".json",))
    sequences = predict_sequences(args.sequences, args.scans)
    compare = {}
    for path in args.compare or []:
        if not Path(path).exists():
            raise UsageError(f"--compare {path}: no such file or folder")
    sensor = load_sensor(load_space(args.config).sensor)
    if not 1 <= args.base_scans <= 10_000:
        raise UsageError(f"--base-scans: {args.base_scans} must be in 1..10000")
    try:
        keeps = tuple(float(v) for v in args.parked_keep.split(","))
    except ValueError:
        keeps = ()
    if not keeps or not all(0.0 <= k <= 1.0 for k in keeps):
        raise UsageError(f"--parked-keep: {args.parked_keep!r} is not a comma list of shares "
                         "in 0..1")
    fit = fit_world(args.scans, sequences, sensor, name=args.name, base_scans=args.base_scans,
                    keep_grid=keeps, holdout=args.holdout or ())
    for path in args.compare or []:
        # A SemanticKITTI root is described per sequence, as predict reports it.
        from falsify.world.real_scans import available_sequences
        seqs = available_sequences([path]) or [None]
        for q in seqs:
            stats = describe([path], None if q is None else [q])
            key = path if q is None else f"{path}:{q}"
            compare[key] = {**summarise(stats), "distance_to_fit": distances(stats, fit.fit)}
    doc = {**fit.to_json(), "compare": compare, "out": str(out)}
    write_json(out, fit.profile.to_json())
    emit(args, doc, _fit_world_text(doc))
    return 0


def _fit_world_text(doc: dict) -> str:
    """Median (5-95 %) per statistic for the fit scans, the world and each compared set."""
    from falsify.jobs.fit_world import STAT_KEYS

    cols = [("fit", doc["fit"], None), ("world", doc["world"], doc["distance_world_to_fit"]),
            ("profiled world", doc["profiled_world"], doc["distance_profiled_to_fit"])]
    cols += [(k, v, v["distance_to_fit"]) for k, v in doc["compare"].items()]
    lines = [f"wrote {doc['out']}: world profile {doc['profile']['name']!r} from "
             f"{doc['fit']['scans']} fit scans (world base: {doc['world']['scans']} of its "
             "training scenes); median [5-95 %], and W1 to the fit scans",
             "parked cars kept: " + ", ".join(
                 f"{t['keep']:g} ({t['score']:.3f})" for t in doc["parked_keep_tries"])
             + f" -> {doc['profile']['parked_keep']:g}"]
    for name, summ, dist in cols:
        lines.append(f"{name} ({summ['scans']} scans)")
        for k in STAT_KEYS:
            s = summ[k]
            d = "" if dist is None else f"   W1 {dist[k]:.4f}"
            lines.append(f"  {k:12s} {s['p50']:8.3f} [{s['p5']:7.3f} .. {s['p95']:7.3f}]{d}")
    lines.append("places: share of front points per class group and range band, median "
                 "[10-90 %] over scans; W1 to the fit scans")
    lines.append(f"  {'group, band':24s} {'fit':>22s} {'world':>30s} {'profiled world':>30s}")
    fit, base, prof = doc["places_fit"], doc["places_world"], doc["places_profiled_world"]
    for key, f in fit.items():
        cells = [f"{f['p50']:.3f} [{f['p10']:.3f}..{f['p90']:.3f}]"]
        for side in (base[key], prof[key]):
            cells.append(f"{side['p50']:.3f} [{side['p10']:.3f}..{side['p90']:.3f}] "
                         f"W1 {side['w1']:.3f}")
        lines.append(f"  {key:24s} {cells[0]:>22s} {cells[1]:>30s} {cells[2]:>30s}")
    return "\n".join(lines)
