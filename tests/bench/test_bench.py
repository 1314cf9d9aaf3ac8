"""`falsify bench`: each benchmark runs end to end on a tiny input and reports its fields.

Speed is never asserted here (timed tests flake on shared machines); the figures live in the
README with the commands that measured them.
"""

from __future__ import annotations

import importlib.util
import json
import os

import pytest

from falsify.bench.tables import render
from falsify.cli import build_parser, main
from falsify.cli.bench import pipeline_figures_text
from falsify.cli.common import given_options
from falsify.world.space import load_space
from tests.conftest import CONFIGS, ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
pytestmark = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")


def _json(capsys, argv: list[str]) -> dict:
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("ray") is not None,
                    reason="ray is installed: tests/executors/test_ray.py runs this benchmark "
                    "beside Ray actors and checks the same figures (one run of ~40 s, not two)")
def test_bench_pipeline_reports_both_paths(capsys):
    config = CONFIGS / "ci.toml"
    check_pipeline_figures(_json(capsys, ["bench", "pipeline", "--config", str(config),
                                          "--samples", "24", "--workers", "2", "--json"]),
                           config)


def check_pipeline_figures(r: dict, config) -> None:
    """The figures of `bench pipeline --samples 24 --workers 2 --json` on `config`: each there,
    and related to the others as they are defined, all from the one run."""
    one = r["one_process"]
    assert r["network_batch"] == 1 and r["samples_per_task"] == 8
    assert one["samples_per_s"] > 0 and one["inference_only_samples_per_s"] > 0
    assert one["overhead"] == pytest.approx(
        one["ms_per_sample"] / one["inference_ms_per_sample"] - 1, abs=2e-3)
    assert r["2_workers"]["samples"] == 24 - 2 * 8 and r["2_workers"]["samples_per_s"] > 0

    # From the same run: the machine, the network's FLOPs, the rates and the ratios between them.
    rates, mm, net, q = r["rates"], r["matmul"], r["network"], r["ratios"]
    assert rates["workers"] == mm["processes"] == q["workers"] == 2
    assert rates["e2e_n_workers"] == pytest.approx(r["2_workers"]["samples_per_s"], rel=1e-3)
    assert rates["e2e_samples_1"] == 24 - 8 and rates["frames_1"] == rates["frames_n"] == 24
    for key in ("inference_only_1_worker", "inference_only_n_workers", "e2e_1_worker"):
        assert rates[key] > 0, key
    assert mm["shape"] == "1024x1024x1024" and mm["library"].startswith("onnxruntime")
    assert mm["gflops_1_core"] > 0 and mm["gflops_per_core_all_at_once"] > 0
    assert mm["shapes"]["1024x1024x1024"]["gflops_1_core"] == mm["gflops_1_core"]
    assert net["flops_per_frame"] > 1e9 and net["unknown_nodes"] == []
    assert 0 < net["crf_share"] < 1
    achieved = net["flops_per_frame"] * rates["inference_only_1_worker"] / 1e9
    assert net["achieved_gflops_1_thread"] == pytest.approx(achieved, rel=2e-3)
    assert q["e2e_n_over_e2e_1"] == pytest.approx(
        rates["e2e_n_workers"] / rates["e2e_1_worker"], rel=2e-3)
    assert q["e2e_n_over_inference_only_n"] == pytest.approx(
        rates["e2e_n_workers"] / rates["inference_only_n_workers"], rel=2e-3)
    assert q["achieved_over_matmul_1_core"] == pytest.approx(
        net["achieved_gflops_1_thread"] / mm["gflops_1_core"], rel=2e-3)
    streets = r["streets"]   # built before the clock in every worker; their cost given apart
    assert streets["count"] == len({s.background for s in load_space(config).grid()})
    assert streets["build_ms_each"] > 0
    assert r["machine"]["cpus"] >= 1 and "cpu" in r["machine"]
    mem = r["memory"]
    if mem is not None:   # Linux
        assert mem["max_processes"] >= 3        # the driver and its two workers
        assert mem["peak_rss_mb"] >= mem["window_peak_rss_mb"] > 0
        assert mem["samples"] > 0
    text = pipeline_figures_text(r)   # what the command prints without --json
    for words in ("GFLOP/frame", "MatMul 1024x1024x1024", "ratios:", "memory of the 2-worker"):
        assert words in text, text


def test_bench_pipeline_refuses_repeats_the_store_would_answer(capsys):
    assert main(["bench", "pipeline", "--config", str(CONFIGS / "smoke.toml"),
                 "--samples", "24"]) == 2
    assert "more than the 8 samples" in capsys.readouterr().err


def test_bench_memory_runs_a_whole_grid(capsys):
    r = _json(capsys, ["bench", "memory", "--config", str(CONFIGS / "smoke.toml"),
                       "--workers", "2", "--json"])
    assert r["samples"] == 8 and r["command"].endswith("--workers 2")
    # the command as typed, which `bench table` prints for it (it rebuilt one from a few keys,
    # dropping options such as --naive-samples, --workers, --executor and --model)
    assert r["measured_by"] == (f"falsify bench memory --config {CONFIGS / 'smoke.toml'} "
                                "--workers 2 --json")
    assert f"`{r['measured_by']}`" in render([r])
    if r["memory"] is not None:
        assert r["memory"]["peak_rss_mb"] > 0 and r["memory"]["max_processes"] >= 3


@pytest.mark.slow
def test_bench_model_compares_variants_on_the_same_frames(capsys):
    pytest.importorskip("torch")
    r = _json(capsys, ["bench", "model", "--samples", "2", "--repeats", "1",
                       "--calibration-scans", "2", "--json"])
    rows = {v["variant"]: v for v in r["variants"]}
    assert set(rows) == {"onnx-fp32", "onnx-fp32-batch8", "torch-fp32", "torch-bf16",
                         "onnx-int8", "onnx-fp16"}, rows
    assert rows["onnx-fp32"]["batch"] == 1 and rows["onnx-fp32-batch8"]["batch"] == 8
    # batching changes speed, never the answer; torch agrees with ONNX Runtime
    for name in ("onnx-fp32-batch8", "torch-fp32"):
        assert rows[name]["pixel_agreement"] > 0.9999, rows[name]
    assert rows["torch-bf16"]["pixel_agreement"] > 0.99, rows["torch-bf16"]
    assert all(v["ms_per_frame"] > 0 and v["frames"] == 2 for v in rows.values())
    # the machine's own rates, and each variant as a share of its precision's rate
    rates = r["matrix_rates"]
    assert rates["fp32"]["gflops_1_core"] > 0 and rates["int8"]["gops_1_core"] > 0
    if rates["cpu_units"]["bf16"]:
        assert rates["bf16"]["gflops_1_core"] > 0
    else:
        assert rates["bf16"]["gflops_1_core"] is None and "no bf16 units" in rates["bf16"]["note"]
    for name, v in rows.items():
        assert v["achieved_gops_per_thread"] > 0
        if v["precision"] in ("fp32", "int8"):
            assert 0 < v["share_of_matrix_rate"] < 5, (name, v)
    assert rows["onnx-fp16"]["share_of_matrix_rate"] is None


def test_int8_matrix_rate_multiplies_integers_exactly():
    """The int8 product timed is a real u8 x s8 -> s32 product (checked against numpy), so its
    rate is of the integer path, not of a graph ONNX Runtime folded away."""
    import numpy as np
    import onnx

    from falsify.bench.machine import matmul_graph
    from falsify.models.runners import cpu_session

    model, a, b = matmul_graph(16, 32, 8, kind="int8")
    # the IR of opset 17, not onnx's newest: onnxruntime 1.19 (the oldest we take) reads <= 10
    assert onnx.load_from_string(model).ir_version == 8
    y = cpu_session(model, threads=1).run(None, {"A": a})[0]
    assert y.dtype == np.int32 and y.shape == (16, 8)
    assert (y == (a.astype(np.int32) - 128) @ b.astype(np.int32)).all()
    model, a, b = matmul_graph(16, 32, 8)
    y = cpu_session(model, threads=1).run(None, {"A": a})[0]
    np.testing.assert_allclose(y, a @ b, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("args, message", [
    (["bench", "model", "--threads", "0"], "--threads: 0: allowed 1..64"),
    (["bench", "pipeline", "--samples", "0"], "--samples"),
    (["bench", "memory", "--workers", "0"], "--workers"),
    (["bench", "memory", "--config", "no-such-config.toml"], "no-such-config.toml"),
    (["bench", "camera", "--camera-preset", "nope"], "--camera-preset: unknown camera 'nope'"),
    (["bench", "pipeline", "--backend", "torch", "--model", "m.py:f", "--device", "cuda"],
     "--backend torch: the plug-in model m.py:f runs on python"),
])
def test_bad_bench_options_exit_2(capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        code = main(args)
        raise SystemExit(code)
    assert exc.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("args, option", [
    (["bench", "scan", "--config", "no-such.toml", "--model", "x.onnx"], "--model"),
    (["bench", "model", "--config", "no-such.toml", "--scans", "no-such-dir"], "--config"),
    (["bench", "effects", "--config", "no-such.toml", "--workers", "1"], "--workers"),
    (["bench", "camera", "--config", "no-such.toml", "--thread=1"], "--threads"),
    (["bench", "memory", "--config", "no-such.toml", "--device", "cuda"], "--device"),
    (["bench", "scan", "--config", "no-such.toml", "--backend", "torch"], "--backend"),
])
def test_an_option_the_benchmark_does_not_read_exits_2(capsys, args, option):
    """An option a benchmark would ignore (bench scan --model, bench model --config) is refused
    by name with the ones it takes, before the config is read."""
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"{option}: bench {args[1]} does not take it; it takes" in err, err


@pytest.mark.parametrize("name, message", [
    ("nope.onnx", "model file nope.onnx not found"),
    ("x.pt", "--model x.pt: bench model takes an .onnx model"),
])
def test_bench_model_names_a_bad_model_before_timing_the_machine(capsys, monkeypatch, name,
                                                                 message):
    """A missing or non-ONNX --model is named before the matrix rates are timed (they took
    about 20 s, then the error came)."""
    def timed(*_a, **_k):
        raise AssertionError("the matrix rates were timed before the model was checked")

    monkeypatch.setattr("falsify.bench.model.model_bench_rates", timed)
    assert main(["bench", "model", "--model", name, "--samples", "1"]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("budgets", [",", " , ", "x"])
def test_bench_map_without_a_budget_exits_2(tmp_path, capsys, budgets):
    """`--budgets ,` names no share: refused (before: silently only the no-budget case)."""
    out = tmp_path / "m"
    assert main(["bench", "map", "--out", str(out), "--budgets", budgets]) == 2
    assert f"--budgets {budgets!r}: shares of the grid" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("what", ["scan", "pipeline", "camera"])
def test_bench_samples_given_are_honoured_and_defaults_are_each_benchmarks(what):
    """`--samples 1000` reaches the benchmark as 1000 (camera once read it as 10); left out,
    nothing is passed and the benchmark's own default stands."""
    parse = build_parser().parse_args
    given = given_options(parse(["bench", what, "--samples", "1000", "--naive-samples", "2"]),
                          "samples", "naive_samples")
    assert given == {"samples": 1000, "naive_samples": 2}
    assert given_options(parse(["bench", what]), "samples", "naive_samples") == {}


def test_default_runs_stay_small():
    """Each `falsify bench` subcommand's default run finishes within 2 minutes on a 2-core
    machine (docs/benchmarks.md, "Default runs"): few streets (each is built in every process
    before the clock), and default sample counts that the default space holds, so that the
    default run never refuses itself."""
    from inspect import signature

    from falsify.bench.nodes import bench_nodes
    from falsify.bench.pipeline import bench_pipeline
    from falsify.bench.scan import SIZE_SAMPLES, bench_scan
    from falsify.cli.bench import BENCH_CONFIGS, MODEL_BENCH_FRAMES

    parse = build_parser().parse_args
    assert parse(["bench", "scan"]).config is None   # each benchmark's own, resolved in bench.run

    def default(f, name: str):
        return signature(f).parameters[name].default

    grids = {what: load_space(CONFIGS / name).grid() for what, name in BENCH_CONFIGS.items()}
    for what in ("scan", "pipeline", "nodes", "memory"):
        assert len({s.background for s in grids[what]}) <= 3, what
    assert len(grids["memory"]) <= 100          # bench memory runs the whole grid
    assert default(bench_scan, "samples") == 1000 and default(bench_scan, "naive_samples") == 5
    assert default(bench_scan, "size_samples") == SIZE_SAMPLES <= 150
    for what, f in (("pipeline", bench_pipeline), ("nodes", bench_nodes)):
        assert default(f, "samples") <= len(grids[what]), what
    nodes = parse(["bench", "nodes"]).nodes
    assert nodes == default(bench_nodes, "nodes") == 2
    assert default(bench_nodes, "samples") > nodes * default(bench_nodes, "batch")
    assert default(bench_pipeline, "samples") > 2 * default(bench_pipeline, "batch")
    assert MODEL_BENCH_FRAMES == 8 and parse(["bench", "model"]).repeats == 1  # one batch of 8


def test_bench_scan_rounds_report_their_median_and_every_round(monkeypatch):
    """`--repeats` rounds of the 1- and N-process runs, interleaved: each round's rate is kept,
    and the headline is their median (a shared machine swings by a third between runs). The
    scene-size part (seconds of 16x BVHs) is timed by its own test below; here it is recorded."""
    import numpy as np

    from falsify.bench import scan

    asked = []
    monkeypatch.setattr(scan, "scene_size_effect",
                        lambda space, samples: asked.append(samples) or {"samples": len(samples)})
    r = scan.bench_scan(CONFIGS / "smoke.toml", samples=8, naive_samples=1, workers=2,
                        size_samples=1, repeats=2).to_json()
    assert [len(a) for a in asked] == [1] and r["scene_size"] == {"samples": 1}
    assert r["rounds"] == 2
    one, two = r["fast_scans_per_s_1_process_rounds"], r["fast_scans_per_s_2_processes_rounds"]
    assert len(one) == len(two) == 2 and min(one + two) > 0
    assert r["fast_scans_per_s_1_process"] == pytest.approx(np.median(one), abs=0.1)
    assert r["fast_scans_per_s_2_processes"] == pytest.approx(np.median(two), abs=0.1)
    # each figure is rounded (rates to 0.1, the naive rate to 0.001, the ratio to 0.1)
    assert r["speedup_2_processes"] == pytest.approx(
        r["fast_scans_per_s_2_processes"] / r["naive_scans_per_s"], rel=5e-3, abs=0.2)


def test_bench_scan_text_names_its_rounds(monkeypatch, capsys):
    from falsify.bench import scan

    def fake(config, workers, repeats, **_):
        return scan.ScanBench(str(config), "kitti-hdl64e-front", 8, workers, {}, 300.0, 500.0,
                              1.0, 1, {}, None, (280.0, 300.0, 310.0), (450.0, 500.0, 610.0))

    monkeypatch.setattr(scan, "bench_scan", fake)
    assert main(["bench", "scan", "--repeats", "3"]) == 0
    assert capsys.readouterr().out.strip() == (
        "scan: 500.0 scans/s on 2 processes (300.0 on 1), naive 1.0 scans/s: 500.0x, median of "
        "3 rounds (450.0-610.0 on 2, 280.0-310.0 on 1)")
    assert main(["bench", "scan", "--repeats", "0"]) == 2
    assert "--repeats" in capsys.readouterr().err


def test_scene_size_builds_each_scene_once(monkeypatch):
    """`bench scan`'s scene-size part builds each of its four scenes once per street (a 16x
    street's BVH takes seconds) and times them in interleaved passes; on a tiny street here."""
    import numpy as np

    from falsify.bench.scan import scene_size_effect
    from falsify.world import streets

    built = []

    def tiny(bg_id):
        built.append(bg_id)
        v = np.array([[-80, -80, 0], [80, -80, 0], [80, 80, 0], [-80, 80, 0],
                      [30, -5, 0], [30, 5, 0], [30, 5, 6], [30, -5, 6]], float)
        f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
        return streets.Background(bg_id, v, f, np.zeros(4, np.uint8), np.zeros(4, np.int32),
                                  (), 5.0)

    monkeypatch.setattr(streets, "build_background", tiny)
    space = load_space(CONFIGS / "smoke.toml")
    samples = [s for s in space.grid() if s.background == 0]
    r = scene_size_effect(space, samples)
    assert built == [0] * 4        # as built, 16x, 10x beyond range, image-only dims varied
    assert r["samples"] == len(samples) and r["streets"] == 1
    assert r["triangles_16x"] == 16 * r["triangles"] and r["triangles_10x"] == 10 * r["triangles"]
    for key in ("ratio_16x_triangles", "ratio_10x_objects", "ratio_image_dims"):
        assert r[key] > 0, key



def test_bench_search_times_fresh_runs_and_not_resumed_ones(tmp_path):
    """Every algorithm (NLopt on the given workers too) reports its seconds per evaluation and
    the ratio to random's; asked again, the runs resume from the directory and are not timed."""
    from falsify.bench.search import bench_search
    from falsify.results.store import read_meta

    out = tmp_path / "b"
    r = bench_search(CONFIGS / "smoke.toml", out, algorithms=("random", "LN_BOBYQA"), seeds=1,
                     fraction=1.0, workers=2)
    rows = {a["algorithm"]: a for a in r["algorithms"]}
    assert r["workers"] == 2 and read_meta(out / "LN_BOBYQA")["workers"] == 2
    for a in rows.values():
        assert a["timed"] and a["evaluations"] == 8 and a["wall_s"] > 0
        assert a["s_per_evaluation"] == pytest.approx(a["wall_s"] / 8, rel=1e-3)
    assert rows["random"]["s_per_evaluation_vs_random"] == 1.0
    nl = rows["LN_BOBYQA"]
    assert nl["s_per_evaluation_vs_random"] == pytest.approx(
        nl["s_per_evaluation"] / rows["random"]["s_per_evaluation"], rel=1e-2)
    assert isinstance(nl["within_goal"], bool) and "within_goal" not in rows["random"]
    again = bench_search(CONFIGS / "smoke.toml", out, algorithms=("random", "LN_BOBYQA"), seeds=1,
                         fraction=1.0, workers=2)
    for a in again["algorithms"]:
        assert not a["timed"] and a["wall_s"] is None and a["s_per_evaluation"] is None
        assert a["s_per_evaluation_vs_random"] is None and a["lowest"] == rows[
            a["algorithm"]]["lowest"]
    assert "resumed" in again["timing"]


def test_bench_search_text_says_never_for_a_target_not_reached(tmp_path, monkeypatch, capsys):
    """An algorithm that never comes within 0.02 of the grid's lowest reads "never", not
    "after None"."""
    import falsify.bench.search as search

    row = {"algorithm": "random", "lowest": 0.9, "evaluations": 4, "evaluations_to_target": None,
           "reached": False, "wall_s": 1.0, "s_per_evaluation": 0.25,
           "s_per_evaluation_vs_random": 1.0}
    monkeypatch.setattr(search, "bench_search", lambda *a, **k: {
        "algorithms": [row], "grid_lowest": 0.84, "per_evaluation_goal": "goal"})
    monkeypatch.setattr(search, "over_seeds_text", lambda result: "seeds")
    assert main(["bench", "search", "--out", str(tmp_path / "b")]) == 0
    out = capsys.readouterr().out
    assert "of the grid's 0.84 never;" in out and "None" not in out, out


def test_bench_camera_runs_the_samples_given(capsys):
    r = _json(capsys, ["bench", "camera", "--config", str(CONFIGS / "smoke.toml"),
                       "--samples", "2", "--naive-samples", "1", "--json"])
    assert r["samples"] == 2 and r["naive_samples"] == 1
    assert r["ms_per_image_cold"] > 0 and r["naive_ms_per_image"] > 0


def test_bench_nodes_reads_each_cluster_against_one_node():
    from falsify.bench.nodes import NodeRate, NodesBench

    r = NodesBench("c.toml", 8, {"cpus": 2}, (NodeRate(1, 100, 10.0, 5.0),
                                              NodeRate(2, 90, 4.5, 6.0),
                                              NodeRate(3, 80, 4.0, 7.0))).to_json()
    got = [(n["nodes"], n["samples_per_s"], n["over_1_node"]) for n in r["nodes"]]
    assert got == [(1, 10.0, 1.0), (2, 20.0, 2.0), (3, 20.0, 2.0)]
    cores = os.cpu_count() or 1
    assert [n["ideal_on_this_machine"] for n in r["nodes"]] == [min(k, cores) for k in (1, 2, 3)]


@pytest.mark.parametrize("args, message", [
    (["--nodes", "0"], "--nodes"),
    (["--nodes", "3", "--samples", "24"], "--samples: 24 must be more than"),
    (["--samples", "100000"], "--samples"),
])
def test_bad_bench_nodes_options_exit_2_before_a_cluster_starts(capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        raise SystemExit(main(["bench", "nodes", "--config", str(CONFIGS / "ci.toml"), *args]))
    assert exc.value.code == 2 and message in capsys.readouterr().err
