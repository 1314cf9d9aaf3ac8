"""Same config, seed and model give the same rows, maps, retraining set and report as the pinned
reference, tests/data/regression.json. Regenerate it
(`python tests/project/test_regression.py DIR`) only for a change meant to alter one of them, and
say in the commit which and why.

Timings, timestamps and the run's own path are left out; everything else is compared exactly,
the report by what it says (its headings and every table cell), not by its bytes, so that a
change of style or script alone does not move it,
but for the retraining scans' float channels: their labels and valid pixels are hashed, their
channel sums compared to 1e-6, since Embree's and numpy's kernels differ in the last bits between
CPUs (AVX-512 on a Xeon, AVX2 on an EPYC) while every score and map stays the same to the byte.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import sqlite3
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = Path(__file__).resolve().parents[1] / "data" / "regression.json"
RUNS = {   # name: the command line after `falsify`, with RUN for the output directory
    "grid": ["grid", "configs/smoke.toml", "--out", "RUN", "--threshold", "0.95", "--quiet"],
    "search": ["search", "configs/smoke.toml", "--algorithm", "random", "--budget", "6",
               "--out", "RUN", "--quiet"],
}
TIMING = ["t_scan", "t_infer", "t_total"]


def fingerprint(run: Path) -> dict:
    """What must not change in a run directory, as plain text and content hashes."""
    with sqlite3.connect(run / "results.sqlite") as db:
        frame = pd.read_sql_query("SELECT * FROM samples ORDER BY eval_index", db)
        meta = {k: json.loads(v) for k, v in db.execute("SELECT key, value FROM run")}
    rows = frame.drop(columns=TIMING).to_csv(index=False)
    # read as text, the file's own digits (pandas before 3 parsed floats one bit off)
    csv = pd.read_csv(run / "results.csv", dtype=str, keep_default_na=False).drop(
        columns=TIMING).to_csv(index=False)
    summary = json.loads((run / "summary.json").read_text())
    for key in ("elapsed_s", "run"):
        summary.pop(key)
    report = (run / "report.html").read_text(encoding="utf-8").replace(str(run), "RUN")
    retrain = run / "retrain"

    def scan(path: Path) -> dict:
        image = np.load(path)
        exact = np.ascontiguousarray(np.stack([image[..., 5], image[..., 4] > 0]).astype(np.int32))
        return {"labels_and_valid_sha256": hashlib.sha256(exact.tobytes()).hexdigest(),
                "channel_sums": [float(v) for v in image.astype(np.float64).sum(axis=(0, 1))]}
    return {
        "rows": rows, "csv": csv, "curve": meta["curve"], "summary": summary,
        "maps": {p.name: p.read_text() for p in sorted((run / "maps").glob("*.csv"))},
        "retrain": {p.name: (p.read_text() if p.suffix == ".csv" else scan(p))
                    for p in sorted(retrain.glob("*"))} if retrain.exists() else {},
        "report": report_content(report),
    }


class _Content(HTMLParser):
    """Collects a page's headings and table cells as text: what the report says."""

    def __init__(self) -> None:
        super().__init__()
        self.headings: list[str] = []
        self.cells: list[str] = []
        self._open: list[str] | None = None
        self._text: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag in ("h1", "h2", "h3", "td", "th"):
            self._open, self._text = [tag], []

    def handle_endtag(self, tag):
        if self._open and tag == self._open[0]:
            text = " ".join("".join(self._text).split())
            (self.headings if tag.startswith("h") else self.cells).append(text)
            self._open = None

    def handle_data(self, data):
        if self._open:
            self._text.append(data)


def report_content(html: str) -> dict:
    """The report's headings in order and a hash of its table cells (the run's time left out)."""
    html = re.sub(r"<dt>Time</dt><dd>.*?</dd>", "", html, flags=re.S)
    parsed = _Content()
    parsed.feed(html)
    cells = "\n".join(parsed.cells)
    return {"headings": parsed.headings, "cells": len(parsed.cells),
            "cells_sha256": hashlib.sha256(cells.encode()).hexdigest()}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_same_run_as_before_the_layout_change(name, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    run = tmp_path / name
    assert main([str(run) if a == "RUN" else a for a in RUNS[name]]) == 0
    want = json.loads(REFERENCE.read_text())[name]
    got = fingerprint(run)
    for key in want:
        if key == "retrain":
            assert same_retraining_set(got[key], want[key]), f"{name}: retrain differs"
            continue
        assert got[key] == want[key], f"{name}: {key} differs from the run made before"


def same_retraining_set(got: dict, want: dict) -> bool:
    """Equal files, index and labels; float channel sums equal to a relative 1e-6."""
    if set(got) != set(want):
        return False
    for name, g in got.items():
        w = want[name]
        if isinstance(w, str) or isinstance(g, str):
            if g != w:
                return False
        elif g["labels_and_valid_sha256"] != w["labels_and_valid_sha256"] or not all(
                math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-6)
                for a, b in zip(g["channel_sums"], w["channel_sums"], strict=True)):
            return False
    return True


# regenerate: python tests/project/test_regression.py DIR_WITH_grid_AND_search
if __name__ == "__main__":
    import sys

    base = Path(sys.argv[1])
    REFERENCE.write_text(json.dumps({n: fingerprint(base / n) for n in sorted(RUNS)},
                                    indent=1, sort_keys=True) + "\n")
