"""Same config, seed and model give the same rows, maps, retraining set and report as the pinned
reference, tests/data/regression.json. Regenerate it (`python tests/test_regression.py DIR`) only
for a change meant to alter one of them, and say in the commit which and why.

Timings, timestamps and the run's own path are left out; everything else is compared exactly.
"""

from __future__ import annotations

import hashlib
import json
import re
import sqlite3
from pathlib import Path

import pandas as pd
import pytest

from falsify.cli import main

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = Path(__file__).resolve().parent / "data" / "regression.json"
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
    csv = pd.read_csv(run / "results.csv").drop(columns=TIMING).to_csv(index=False)
    summary = json.loads((run / "summary.json").read_text())
    for key in ("elapsed_s", "run"):
        summary.pop(key)
    report = (run / "report.html").read_text(encoding="utf-8").replace(str(run), "RUN")
    report = re.sub(r"<dt>Time</dt><dd>.*?</dd>", "<dt>Time</dt><dd></dd>", report,
                    flags=re.S)
    retrain = run / "retrain"
    return {
        "rows": rows, "csv": csv, "curve": meta["curve"], "summary": summary,
        "maps": {p.name: p.read_text() for p in sorted((run / "maps").glob("*.csv"))},
        "retrain": {p.name: (p.read_text() if p.suffix == ".csv" else
                             hashlib.sha256(p.read_bytes()).hexdigest())
                    for p in sorted(retrain.glob("*"))} if retrain.exists() else {},
        "report_sha256": hashlib.sha256(report.encode()).hexdigest(),
    }


@pytest.mark.parametrize("name", sorted(RUNS))
def test_same_run_as_before_the_layout_change(name, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    run = tmp_path / name
    assert main([str(run) if a == "RUN" else a for a in RUNS[name]]) == 0
    want = json.loads(REFERENCE.read_text())[name]
    got = fingerprint(run)
    for key in want:
        assert got[key] == want[key], f"{name}: {key} differs from the run made before"


if __name__ == "__main__":   # regenerate: python tests/test_regression.py DIR_WITH_grid_AND_search
    import sys

    base = Path(sys.argv[1])
    REFERENCE.write_text(json.dumps({n: fingerprint(base / n) for n in sorted(RUNS)},
                                    indent=1, sort_keys=True) + "\n")
