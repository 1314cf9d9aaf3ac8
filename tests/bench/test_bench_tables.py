"""`falsify bench table`: saved benchmark results as one markdown table per CPU."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from falsify.bench.tables import BEGIN, END, load, processes, render, splice
from falsify.errors import FalsifyError

EPYC = {"cpu": "AMD EPYC (family 25, model 1)", "cpus": 2}
XEON = {"cpu": "Intel Xeon", "cpus": 4}


def scan(machine: dict, fast: float) -> dict:
    return {"benchmark": "scan", "config": "configs/bench.toml", "machine": machine,
            "samples": 1000,
            "fast_scans_per_s_1_process": fast / 2, "fast_scans_per_s_2_processes": fast,
            "naive_scans_per_s": 3.0, "speedup_1_process": fast / 6,
            "speedup_2_processes": fast / 3}


def test_a_scan_of_several_rounds_shows_its_median_range_and_command():
    doc = {**scan(EPYC, 600.0), "rounds": 3,
           "fast_scans_per_s_2_processes_rounds": [471.2, 600.0, 650.3]}
    text = render([doc])
    assert "600.0 scans/s on 2 processes (median of 3 rounds, 471.2-650.3), 300.0 on 1" in text
    assert "--samples 1000 --repeats 3 --json" in text
    assert "median of" not in render([scan(EPYC, 600.0)])   # one round: as before


def camera(machine: dict) -> dict:
    return {"benchmark": "camera", "config": "configs/paper.toml", "machine": machine,
            "image": "1242x375", "ms_per_image_cold": 245.0, "ms_per_image_warm": 30.1,
            "speedup_cold": 2.26, "speedup_warm": 18.4}


def test_one_table_per_cpu_with_figure_ratio_network_and_command():
    text = render([camera(EPYC), scan(XEON, 900.0), scan(EPYC, 600.0)])
    assert text.startswith(BEGIN) and text.endswith(END)
    assert text.index("### AMD EPYC (family 25, model 1), 2 cores") < text.index("### Intel Xeon")
    epyc = text.split("### Intel Xeon")[0]
    assert epyc.index("| scan |") < epyc.index("| camera |")   # rows in benchmark order
    assert "600.0 scans/s on 2 processes, 300.0 on 1" in epyc
    assert "200.0x the naive path" in epyc
    assert "`falsify bench scan --config configs/bench.toml --samples 1000 --json`" in epyc
    assert "900.0 scans/s" in text.split("### Intel Xeon")[1]


def test_splice_replaces_only_the_generated_section():
    doc = f"# Benchmarks\n\nprose\n\n{BEGIN}\nold\n{END}\n\nmore prose\n"
    new = splice(doc, render([scan(EPYC, 10.0)]))
    assert new.startswith("# Benchmarks\n\nprose\n\n") and new.endswith("\n\nmore prose\n")
    assert "old" not in new and new.count(BEGIN) == 1
    assert splice(new, render([scan(EPYC, 10.0)])) == new
    assert BEGIN in splice("# none yet\n", render([scan(EPYC, 10.0)]))


def test_a_file_that_is_not_a_result_is_named(tmp_path: Path):
    good = tmp_path / "scan.json"
    good.write_text(json.dumps(scan(EPYC, 10.0)))
    bad = tmp_path / "summary.json"
    bad.write_text(json.dumps({"benchmark": "search"}))
    assert load([good])[0]["benchmark"] == "scan"
    with pytest.raises(FalsifyError, match=r"summary\.json: benchmark 'search' has no table; "
                                           r"known: scan, scan effects, pipeline"):
        load([good, bad])
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(FalsifyError, match="broken.json: not a benchmark result"):
        load([broken])


def test_the_command_prints_or_splices_and_refuses_stray_files(tmp_path: Path, capsys):
    from falsify.cli import main

    result = tmp_path / "scan.json"
    result.write_text(json.dumps(scan(EPYC, 10.0)))
    assert main(["bench", "table", str(result)]) == 0
    tables = capsys.readouterr().out
    assert tables.startswith(BEGIN)
    assert main(["bench", "table", str(result), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["markdown"] + "\n" == tables and doc["benchmarks"] == ["scan"]
    binary = tmp_path / "model.onnx"
    binary.write_bytes(b"\x08\xe4\xff\x00")
    assert main(["bench", "table", str(binary)]) == 2
    assert "model.onnx: not a benchmark result" in capsys.readouterr().err
    doc = tmp_path / "benchmarks.md"
    doc.write_text("# Benchmarks\n")
    assert main(["bench", "table", str(result), "--write", str(doc)]) == 0
    assert "10.0 scans/s on 2 processes" in doc.read_text()
    assert main(["bench", "scan", str(result)]) == 2
    assert "RESULTS: only bench table takes result files" in capsys.readouterr().err
    assert main(["bench", "table"]) == 2
    assert main(["bench", "table", str(result), "--write", str(tmp_path / "none.md")]) == 2
    assert "--write:" in capsys.readouterr().err


def test_bench_effects_times_a_scan_with_and_without_its_effects(capsys):
    from falsify.cli import main

    assert main(["bench", "effects", "--samples", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["benchmark"] == "scan effects" and doc["samples"] == 2
    assert doc["ms_per_scan_clear"] > 0 and doc["ms_per_scan_all_effects"] > 0


def test_the_benchmarks_page_holds_the_tables_of_the_committed_results():
    """docs/benchmarks.md's figures are the committed JSON's, regenerated, not copied."""
    root = Path(__file__).resolve().parents[2]
    results = sorted((root / "research" / "benchmarks").glob("*/*.json"))
    assert results, "research/benchmarks/CPU/*.json: no committed results"
    page = (root / "docs" / "benchmarks.md").read_text()
    assert splice(page, render(load(results))) == page, (
        "docs/benchmarks.md is stale: falsify bench table research/benchmarks/*/*.json "
        "--write docs/benchmarks.md")


def test_a_gpu_pipeline_row_names_its_backend_device_and_ceilings():
    doc = {"benchmark": "pipeline-shared", "config": "configs/bench.toml", "samples": 450,
           "workers": 14, "device": "cuda", "gpu": "NVIDIA H200", "model": "squeezeseg",
           "backend": "torch", "e2e_samples_per_s": 164.97, "network_alone_frames_per_s": 214.64,
           "scan_only_samples_per_s": 1126.59, "e2e_over_lower_ceiling": 0.769, "goal": 0.8,
           "machine": XEON}
    row = render([doc]).splitlines()[-2]
    assert row == ("| pipeline, one inference process | 164.97 samples/s end to end on 14 "
                   "workers; the network alone 214.64 frames/s, the scans alone 1126.59 "
                   "samples/s | end to end / the lower 0.769 (goal 0.8) | squeezeseg (torch on "
                   "cuda, NVIDIA H200) | `falsify bench pipeline --inference shared --config "
                   "configs/bench.toml --samples 450 --workers 14 --device cuda --json` |")


def test_process_counts_read_as_english():
    assert (processes(1), processes(2)) == ("1 process", "2 processes")


def test_a_result_that_records_its_command_line_is_printed_with_it():
    """A result saved with its typed command (`measured_by`) shows that one: the rebuilt one
    drops what it does not know (here --naive-samples); older results keep the rebuilt one."""
    typed = "falsify bench scan --samples 40 --naive-samples 8 --json"
    text = render([{**scan(EPYC, 600.0), "measured_by": typed}])
    assert f"`{typed}`" in text and "--config configs/bench.toml" not in text
