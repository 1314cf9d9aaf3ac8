"""An output file's name must end as what is written there: a slip of `--out` onto a run's
store or a scan is refused with exit 2, naming the endings allowed, and the file is left as it
was (`report --out RUN/results.sqlite` wrote the page over the run's store)."""

from __future__ import annotations

from pathlib import Path

import pytest

from falsify.cli import main

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("names") / "run"
    assert main(["grid", str(ROOT / "configs" / "smoke.toml"), "--out", str(out), "--quiet",
                 "--no-report"]) == 0
    return out


def test_a_report_onto_the_runs_store_is_refused_and_the_store_kept(run, capsys):
    store = run / "results.sqlite"
    before = store.read_bytes()
    assert main(["report", str(run), "--out", str(store)]) == 2
    assert f"--out {store}: must end in .html or .htm" in capsys.readouterr().err
    assert store.read_bytes() == before
    assert main(["report", str(run), "--out", str(run / "page.htm"), "--json"]) == 0


def test_junit_onto_a_runs_summary_is_refused_and_the_summary_kept(run, capsys):
    summary = run / "summary.json"
    before = summary.read_bytes()
    assert main(["gate", str(run), "--junit", str(summary)]) == 2
    assert f"--junit {summary}: must end in .xml" in capsys.readouterr().err
    assert summary.read_bytes() == before


@pytest.mark.parametrize("argv, endings", [
    (["holdout", "SCANS", "--out", "SCANS/000000.bin"], ".toml"),
    (["fit-returns", "SCANS", "--out", "SCANS/000000.label"], ".json"),
    (["fit-world", "SCANS", "--out", "profile.toml"], ".json"),
    (["faithfulness", "--out", "faithfulness.html"], ".json"),
    (["export", "SCANS/w.pt", "--out", "SCANS/w.pt"], ".onnx"),
])
def test_each_named_output_file_must_end_as_it_is_written(tmp_path, capsys, argv, endings):
    scans = tmp_path / "scans"
    scans.mkdir()
    kept = {scans / "000000.bin": b"\0" * 16, scans / "000000.label": b"\1" * 4,
            scans / "w.pt": b"weights"}
    for path, data in kept.items():
        path.write_bytes(data)
    argv = [a.replace("SCANS", str(scans)) for a in argv]
    assert main(argv) == 2
    out = argv[argv.index("--out") + 1]
    assert f"--out {out}: must end in {endings}" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in kept} == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scans"]
