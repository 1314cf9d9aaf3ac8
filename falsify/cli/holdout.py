"""`falsify holdout`: write a split manifest of held-out scans."""

from __future__ import annotations

import argparse

from falsify.checks import check_out_file
from falsify.cli.common import emit, predict_sequences


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help=".bin or .npy scans, folders of them, SemanticKITTI "
                   "roots or sequence folders")
    p.add_argument("--sequences", default=None, metavar="SS,SS",
                   help="only these sequences of a SemanticKITTI root")
    p.add_argument("--out", required=True, help="the manifest (TOML), e.g. DATA/splits.toml")
    p.add_argument("--note", default=None, help="a comment line for the manifest's head")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.data.holdout import load_manifest, manifest_text, scans_under
    from falsify.fileio import write_text

    out = check_out_file(args.out, suffixes=(".toml",))
    sequences = predict_sequences(args.sequences, args.scans)
    scans = scans_under(args.scans, sequences)
    write_text(out, manifest_text(scans, args.note or ""))
    held = load_manifest(out)
    summary = {"manifest": str(out), "scans": len(held.scans),
               "bytes": sum(s.size for s in held.scans)}
    emit(args, summary, f"{out}: {len(held.scans)} held-out scans, matched by content; pass it "
         "as --holdout to the fits (fit-world, fit-returns, fit-rings) and the trainers, or name "
         "it in $FALSIFY_HOLDOUT")
    return 0
