"""`falsify realism`: compare synthetic scans with real KITTI scans."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from falsify.checks import check_out_dir
from falsify.cli.common import UsageError, emit, predict_sequences
from falsify.cli.progress import ScanCounter

OUTPUTS = ("realism.json", "realism.html")   # what a run writes into --out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("synthetic", nargs="+",
                   help="`falsify dataset` folders of .npy scans (the first is the baseline "
                   "the others are compared with)")
    p.add_argument("--out", required=True, help="folder for realism.json and realism.html")
    p.add_argument("--real", nargs="+", required=True, metavar="PATH",
                   help="the real reference: scans as for predict (a SemanticKITTI root, "
                   "sequence folders, .bin or .npy scans), pooled")
    p.add_argument("--sequences", default=None, metavar="SS,SS",
                   help="only these sequences of --real's SemanticKITTI roots")
    p.add_argument("--evaluation", nargs="+", default=None, metavar="PATH",
                   help="held-out real scans: each synthetic set's distances to them, per "
                   "set, reported only, never pooled or compared")
    p.add_argument("--evaluation-sequences", default=None, metavar="SS,SS",
                   help="only these sequences of --evaluation's SemanticKITTI roots")
    p.add_argument("--scans", type=int, default=None,
                   help="use the first N scans of each synthetic folder")
    p.add_argument("--model", default=None,
                   help="SqueezeSeg ONNX model whose fire9 features are compared "
                   "(default: bundled)")
    p.add_argument("--sensor", default="kitti-hdl64e-front",
                   help="preset used to project real .bin scans")
    p.add_argument("--bootstrap", type=int, default=0, metavar="DRAWS",
                   help="also resample the scans DRAWS times (seeded): a 5-95 %% interval per "
                   "distance and, per later set, the share of draws in which it is closer "
                   "than the first (200 draws of two 200-scan sets: about a minute); it keeps "
                   "1 MB of feature moments a real scan, which are otherwise pooled as read")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.data.range_npy import npy_files
    from falsify.data.scansets import plan_sets
    from falsify.fileio import write_json, write_text
    from falsify.jobs.realism import EncoderFeatures, compare
    from falsify.reports.realism_page import render_realism
    from falsify.sensor.lidar import load_sensor

    check_out_dir(args.out)   # before the work: a minute or more of encoding
    if args.scans is not None and args.scans < 1:
        raise UsageError(f"--scans: {args.scans} must be >= 1")
    if args.bootstrap < 0:
        raise UsageError(f"--bootstrap: {args.bootstrap} must be >= 0 (0: no resampling)")
    synthetic: dict[str, list[Path]] = {}
    labels: dict[str, str] = {}
    for d in map(Path, args.synthetic):
        if not d.is_dir():
            raise UsageError(f"{d}: not a folder (expected a `falsify dataset` folder of .npy)")
        files = npy_files(d)[: args.scans]
        if not files:
            raise UsageError(f"{d}: no .npy scans in this folder")
        name = d.name if d.name not in synthetic and d.name else str(d)
        synthetic[name] = files
        # what the label channel holds, as index.json records it; our four classes without one
        try:
            index = json.loads((d / "index.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            index = None
        labels[name] = index.get("labels", "kitti4") if isinstance(index, dict) else "kitti4"
    sensor = load_sensor(args.sensor)
    # planned, not read: each set is read CHUNK scans at a time as its statistics are taken
    real = plan_sets(args.real, predict_sequences(args.sequences, args.real))
    reported = (plan_sets(args.evaluation,
                          predict_sequences(args.evaluation_sequences, args.evaluation))
                if args.evaluation else [])
    counter = ScanCounter("realism", sum(map(len, synthetic.values()))
                          + sum(len(p.files) for p in (*real, *reported)))
    try:
        result = compare(synthetic, real, EncoderFeatures(args.model),
                         bootstrap_draws=args.bootstrap, labels=labels, reported=reported,
                         sensor=sensor, on_scans=counter)
    finally:
        counter.close()
    doc = result.to_json()
    page = render_realism(doc)
    out = Path(args.out)
    for name in OUTPUTS:   # a stop between the two must not leave the last run's page
        (out / name).unlink(missing_ok=True)
    write_text(out / "realism.html", page)
    write_json(out / "realism.json", doc)
    summary = {**doc, "files": [str(out / "realism.json"), str(out / "realism.html")]}
    emit(args, summary, realism_text(doc, out))
    return 0


def realism_text(doc: dict, out: Path) -> str:
    """Distances to the pooled real scans, one line per statistic."""
    ref = doc["real_pooled"]
    names = [s["name"] for s in doc["synthetic"]]
    parts = [r["name"] for r in doc["real"] if r["name"] != ref]
    lines = [f"realism against {ref} ({', '.join(parts) or ref}), lower is "
             f"closer; wrote {out / 'realism.json'} and {out / 'realism.html'}"]
    for s in [*doc["real"][:len(parts) or 1], *doc.get("reported", [])]:
        if s["unlabelled"]:
            shown = ", ".join(s["unlabelled"][:3]) + (", ..." if len(s["unlabelled"]) > 3 else "")
            lines.append(f"{s['name']}: {len(s['unlabelled'])} of {s['scans']} scans without "
                         f"labels, left out of the class statistics ({shown})")
    lines.append(f"{'statistic':12s}" + "".join(f"{n[-24:]:>26s}" for n in names))
    for key in doc["statistics"]:
        lines.append(f"{key:12s}" + "".join(f"{doc['distances'][n][ref][key]:26.4f}"
                                            for n in names))
    floors = [s["frechet_floor"] for s in doc["synthetic"]]
    if all(floors):
        lines.append(f"{'(floor)':12s}" + "".join(f"{f['mean']:26.4f}" for f in floors)
                     + f"  frechet of {floors[0]['scans']} scans of the same set against the "
                     "rest (sampling alone)")
    for key in doc.get("reference_statistics", {}):
        lines.append(f"{key:12s}" + "".join(f"{doc['distances'][n][ref][key]:26.4f}"
                                            for n in names) + "  (reference, not compared)")
    for key in doc.get("diagnostic_statistics", {}):
        values = [doc["distances"][n][ref].get(key) for n in names]
        if any(v is not None for v in values):
            lines.append(f"{key:12s}" + "".join(
                f"{'—':>26s}" if v is None else f"{v:26.4f}" for v in values)
                + "  (SemanticKITTI's 19 classes: total variation; diagnostic, not compared)")
    for r in doc.get("reported", []):
        lines.append(f"{'reported':12s}" + "".join(
            f"{r['name'][-24:]:>26s}" for _ in names) + "  (evaluation data: never compared)")
        for key in doc["statistics"]:
            lines.append(f"{key:12s}" + "".join(f"{doc['distances'][n][r['name']][key]:26.4f}"
                                                for n in names))
    boot = doc.get("bootstrap")
    if boot:
        lo, hi = boot["levels"]
        lines.append(f"resampled {boot['draws']} times (seed {boot['seed']}): {lo:g}-{hi:g} % "
                     "of each distance")
        for key in doc["statistics"]:
            spans = (boot["intervals"][n][key] for n in names)
            lines.append(f"{key:12s}" + "".join(f"{f'{a:.4f}-{b:.4f}':>26s}" for a, b in spans))
    for name, cand in ((doc.get("comparison") or {}).get("candidates") or {}).items():
        k, n = sum(cand["closer"].values()), len(cand["closer"])
        lines.append(f"{name}: closer than {doc['comparison']['baseline']} on {k} of {n} "
                     f"statistics; on every one: {'yes' if k == n else 'no'}")
        if boot:
            share = boot["closer_share"][name]
            lines.append("  closer in this share of the resampled draws: " + ", ".join(
                f"{key} {share[key]:.2f}" for key in doc["statistics"]))
        on = cand["closer_on_real_scans"]
        lines.append(f"  closer against this many of the {cand['real_scans']} real scans, each "
                     "alone: " + ", ".join(f"{key} {v}" for key, v in on.items()))
    return "\n".join(lines)
