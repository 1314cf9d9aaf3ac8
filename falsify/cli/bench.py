"""`falsify bench`: measure a fast path beside its naive path, one benchmark per WHAT."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from falsify.checks import MAX_SAMPLES, check_out_dir, check_range
from falsify.cli.common import (
    DEFAULT_CONFIG,
    UsageError,
    check_backend,
    emit,
    given_options,
    int_in,
)
from falsify.paths import CONFIGS

# Held-out frames `bench model` compares the variants on unless --samples says otherwise (each
# variant is timed on the first TIMED_FRAMES of them). Each is on a street of its own, built
# first (about 1 s a street): 1,000 frames spent some 12 minutes there alone. 8 frames are one
# batch of onnx-fp32-batch8. Every variant runs a warm-up frame, --repeats timed runs of them
# (default 1) and one for agreement: 17 frames, where torch-bf16 on a CPU without bf16 units is
# emulated at 1.5-3 s a frame on a 2-core EPYC.
MODEL_BENCH_FRAMES = 8
# Each benchmark's space without --config: default runs finish within 2 minutes on a 2-core
# machine (research/benchmarks-history.md, "Default runs"); give --config configs/paper.toml
# for the paper's whole space. `bench model` measures held-out frames, not a space.
BENCH_CONFIGS = {"scan": "bench.toml", "pipeline": "bench.toml", "nodes": "bench.toml",
                 "memory": "ci.toml", "search": "yaw.toml", "camera": "paper.toml",
                 "map": "weather.toml", "effects": "weather.toml", "cells": "paper.toml"}
# The options each benchmark reads (every one takes --json); one given to a benchmark that does
# not read it is refused, not silently ignored.
BENCH_OPTIONS = {
    "scan": ("--config", "--samples", "--naive-samples", "--workers", "--repeats"),
    "model": ("--samples", "--model", "--scans", "--repeats", "--calibration-scans",
              "--threads"),
    "pipeline": ("--config", "--samples", "--workers", "--executor", "--device", "--inference",
                 "--model", "--backend"),
    "memory": ("--config", "--workers", "--model"),
    "nodes": ("--config", "--samples", "--nodes", "--model"),
    "search": ("--config", "--out", "--workers", "--model", "--fraction", "--seeds"),
    "map": ("--config", "--out", "--workers", "--model", "--budgets", "--threshold",
            "--confidence", "--timed", "--seeds"),
    "camera": ("--config", "--samples", "--naive-samples", "--camera-preset"),
    "effects": ("--config", "--samples"),
    "cells": ("--config", "--samples"),
    "table": ("--write",),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=["scan", "model", "pipeline", "search", "map", "camera",
                                     "memory", "nodes", "effects", "cells", "table"],
                   help="memory: peak memory of a whole `falsify grid --config ... --workers N` "
                   "run, all processes together; nodes: Ray on local clusters of 1..--nodes "
                   "one-CPU nodes; map: the level-set sampler's map against the full grid's "
                   "at each --budgets; effects: a scan with its weather and sensor effects "
                   "against the same scan clear; cells: a run's cell maps of --samples drawn "
                   "rows (default 50,000) against one pandas group per cell; table: saved "
                   "--json results (RESULTS) as one markdown table per CPU")
    p.add_argument("results", nargs="*", metavar="RESULTS",
                   help="bench table: the JSON files `falsify bench WHAT --json` wrote")
    p.add_argument("--write", default=None, metavar="DOC",
                   help="bench table: replace the generated section of this markdown file "
                   "(appended when it has none) instead of printing the tables")
    p.add_argument("--config", default=None,
                   help="the space (default: each benchmark's own: configs/bench.toml for scan, "
                   "pipeline and nodes, configs/ci.toml for memory, configs/yaw.toml for "
                   "search, configs/weather.toml for map and effects, configs/paper.toml for "
                   "camera and cells)")
    p.add_argument("--samples", type=int, default=None,
                   help="how many samples (default: each benchmark's own)")
    p.add_argument("--naive-samples", type=int, default=None,
                   help="samples through the naive path (default: each benchmark's own)")
    p.add_argument("--workers", type=int, default=2,
                   help="bench scan, pipeline, memory, search, map: worker processes (default 2)")
    p.add_argument("--executor", choices=["process", "ray"], default="process",
                   help="bench pipeline: also measure Ray actors against the processes")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="bench pipeline: where the network runs (cuda: one shared inference "
                   "process on the GPU, against the network alone there and the workers' "
                   "scan rate)")
    p.add_argument("--inference", choices=["auto", "shared"], default="auto",
                   help="bench pipeline: shared measures one inference process fed by the "
                   "workers (the default on cuda)")
    p.add_argument("--backend", choices=["onnx", "torch", "python"], default=None,
                   help="bench pipeline: onnx or torch for a model file (torch on cuda needs no "
                   "onnxruntime-gpu); python (set by itself) for a plug-in (default: onnx)")
    p.add_argument("--model", default=None,
                   help="bench model: an ONNX model; pipeline, memory, nodes, search, map: any "
                   "model a run takes (default bundled)")
    p.add_argument("--scans", default=None,
                   help="bench model: a folder of labelled .npy scans (default: generated)")
    p.add_argument("--repeats", type=int, default=1,
                   help="bench model: timed runs of each variant over its frames, the best kept; "
                   "bench scan: interleaved rounds of the 1- and N-process runs, the median "
                   "reported with every round (default 1)")
    p.add_argument("--calibration-scans", type=int_in(1, 1024), default=None,
                   metavar="N", help="bench model: synthetic scenes to calibrate int8 on "
                   "(default: the export's 64; the bundled network's shipped int8 copy is "
                   "measured unless this is given)")
    p.add_argument("--threads", type=int_in(1, 64), default=2, metavar="N",
                   help="bench model: inference threads (default 2; a grid worker uses 1)")
    p.add_argument("--out", default=None, help="bench search, map: where their runs go")
    p.add_argument("--budgets", default=None, metavar="F,F,...",
                   help="bench map: budgets as shares of the grid's evaluations (default "
                   "0.1,0.2,0.3; a run without a budget is always added)")
    p.add_argument("--threshold", type=float, default=None, metavar="T",
                   help="bench map: the blind-cell threshold (default the config's)")
    p.add_argument("--confidence", type=float, default=None, metavar="P",
                   help="bench map: the level-set sampler's confidence (default 0.95)")
    p.add_argument("--timed", action="store_true",
                   help="bench map: also run the level-set search for real and time it "
                   "against the grid")
    p.add_argument("--fraction", type=float, default=0.2,
                   help="bench search: budget as a fraction of the dense grid")
    p.add_argument("--seeds", type=int, default=3,
                   help="bench search, map: runs of each algorithm, from the config's seed on")
    p.add_argument("--nodes", type=int_in(1, 16), default=2, metavar="N",
                   help="bench nodes: the largest local cluster, in one-CPU worker nodes "
                   "(default 2)")
    p.add_argument("--camera-preset", default="kitti-centre",
                   help="bench camera: the camera preset")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    _check_options(args)
    if args.what == "table":
        return _table(args)
    if args.config is None:
        args.config = str(CONFIGS / BENCH_CONFIGS.get(args.what, DEFAULT_CONFIG.name))
    result, text = _benchmark(args)(args)
    if getattr(args, "argv", None) is not None:   # as typed, for `bench table` to print
        result["measured_by"] = measured_by(args.argv)
    emit(args, result, text)
    return 0


def measured_by(argv: list[str]) -> str:
    """The command line that measured a result, with --json (the saved results are its)."""
    import shlex

    words = ["falsify", *argv]
    return shlex.join(words if "--json" in argv else [*words, "--json"])


def _check_options(args) -> None:
    """The option values every benchmark refuses, before any work."""
    _check_given(args.what, getattr(args, "argv", None))
    check_range(args.samples, "--samples", 1, MAX_SAMPLES)
    check_range(args.workers, "--workers", 1, 64)
    check_range(args.naive_samples, "--naive-samples", 1)
    check_range(args.repeats, "--repeats", 1)
    if (args.what == "table") != bool(args.results):
        raise UsageError("RESULTS: only bench table takes result files, and it needs at least "
                         "one" if args.results else "bench table: give the JSON result files")
    if args.write and args.what != "table":
        raise UsageError("--write: only bench table writes a document")
    if not 0 < args.fraction <= 1:
        raise UsageError(f"--fraction: {args.fraction} must be in (0, 1]")
    if args.out:
        check_out_dir(args.out)


def _check_given(what: str, argv: list[str] | None) -> None:
    """UsageError for an option typed in `argv` (as argparse took it: `--opt=v` and unique
    prefixes too) that bench `what` does not read; None (no command line): nothing to check."""
    if argv is None:
        return
    every = sorted({o for opts in BENCH_OPTIONS.values() for o in opts})
    allowed = BENCH_OPTIONS[what]
    for token in argv:
        if token == "--":
            break
        typed = token.split("=", 1)[0]
        names = [o for o in every if o.startswith(typed)] if typed.startswith("--") else []
        if len(names) == 1 and names[0] not in allowed:
            raise UsageError(f"{names[0]}: bench {what} does not take it; it takes "
                             f"{', '.join(allowed)} and --json")


def _benchmark(args):
    """The function that runs `bench WHAT` and returns its result and its text."""
    if args.what == "pipeline" and (args.device == "cuda" or args.inference == "shared"):
        return _bench_shared
    bench = BENCHMARKS.get(args.what)
    if bench is None:
        raise UsageError(f"bench {args.what}: not available")
    return bench


def _bench_model(args) -> tuple[dict, str]:
    import numpy as np

    from falsify.bench.machine import machine
    from falsify.bench.model import add_shares, model_bench_rates
    from falsify.data.range_npy import npy_files
    from falsify.data.scansets import read_set
    from falsify.data.training import calibration_scans, held_out_scans
    from falsify.models.flops import count_flops
    from falsify.models.runners import BUNDLED_ONNX, WEIGHTS_DIR
    from falsify.models.runners.base import open_model
    from falsify.models.variants import bench_models
    from falsify.sensor.lidar import load_sensor
    sensor = load_sensor("kitti-hdl64e-front")
    progress = (lambda line: None) if args.json else _stderr

    frames = MODEL_BENCH_FRAMES if args.samples is None else args.samples
    files = npy_files(Path(args.scans))[:frames] if args.scans else []
    if args.scans and not files:
        raise UsageError(f"--scans {args.scans}: no .npy scans there")
    scans = (read_set(args.scans, files, sensor).images if files
             else held_out_scans(sensor, frames))
    onnx = Path(args.model) if args.model else BUNDLED_ONNX
    if onnx.suffix != ".onnx":
        raise UsageError(f"--model {onnx}: bench model takes an .onnx model (with its .json "
                         "spec beside it)")
    open_model(onnx, None, "onnx")   # a missing or mismatched model or spec, before the rates
    rates = model_bench_rates(progress)
    # the bundled network's int8 is its shipped copy (calibrating one anew takes minutes)
    shipped = (onnx.resolve() == BUNDLED_ONNX.resolve()
               and args.calibration_scans is None)
    rows = bench_models(np.asarray(scans), onnx, repeats=args.repeats,
                        threads=args.threads, on_progress=progress,
                        calibration=None if shipped else calibration_scans(
                            sensor, args.calibration_scans),
                        int8_path=WEIGHTS_DIR / "squeezeseg-int8.onnx" if shipped else None)
    add_shares(rows, count_flops(onnx).total, rates)
    result = {"benchmark": "model", "model": str(onnx), "frames": len(scans),
              "repeats": args.repeats, "machine": machine(), "matrix_rates": rates,
              "variants": rows}
    text = "\n".join([model_rates_text(rates), *(
        f"{r['variant']:16s} {r['ms_per_frame']:8.1f} ms/frame {r['fps']:6.1f} fps  car "
        f"IoU diff {r['car_iou_diff']:+.4f}" + ("" if r.get("share_of_matrix_rate") is None
                                               else f"  {r['share_of_matrix_rate']:.0%} of "
                                               f"the {r['precision']} matrix rate")
        if "error" not in r else f"{r['variant']:16s} did not run: {r['error']}"
        for r in rows)])
    return result, text


def _bench_shared(args) -> tuple[dict, str]:
    """`bench pipeline` with --device cuda or --inference shared."""
    from falsify.bench.shared import bench_shared
    if args.executor == "ray":
        raise UsageError("--inference shared runs beside local workers, not on Ray")
    result = bench_shared(args.config, workers=args.workers, model=args.model,
                          backend=check_backend(args.backend, args.model), device=args.device,
                          **given_options(args, "samples"))
    text = (f"shared inference on {args.device}: {result['e2e_samples_per_s']} samples/s "
            f"end to end on {args.workers} workers; the network alone "
            f"{result['network_alone_frames_per_s']} frames/s, the workers' scans alone "
            f"{result['scan_only_samples_per_s']} samples/s: "
            f"{result['e2e_over_lower_ceiling']:.2f} of the lower (goal {result['goal']})")
    return result, text


def _bench_pipeline(args) -> tuple[dict, str]:
    from falsify.bench.pipeline import bench_pipeline

    if args.executor == "ray":
        from falsify.executors.ray import import_ray
        import_ray()
    pipe = bench_pipeline(args.config, workers=args.workers, model=args.model,
                          backend=check_backend(args.backend, args.model),
                          executor=args.executor, **given_options(args, "samples"))
    result = pipe.to_json()
    one = result["one_process"]
    text = (f"pipeline: {pipe.samples_per_s} samples/s on {pipe.workers} workers; one "
            f"process {one['samples_per_s']} samples/s against "
            f"{one['inference_only_samples_per_s']} for inference alone (overhead "
            f"{pipe.overhead:.1%}); store {result['driver_store_rows_per_s']} rows/s")
    if result["network"] is not None:   # a plug-in has no ONNX graph to rate
        text += "\n" + pipeline_figures_text(result)
    else:
        text += (f"\nend to end {result['rates']['e2e_1_worker']} samples/s on 1 worker, "
                 f"{result['rates']['e2e_n_workers']} on {pipe.workers}")
    if pipe.ray is not None:
        r = pipe.ray
        text += (f"\nray: {r['samples_per_s']} samples/s on {r['actors']} actors "
                 f"({r['against_processes']:.2f}x the processes); per task "
                 f"{r['task_round_trip_ms']} ms round trip, {r['driver_ms_per_task']} ms "
                 "pipelined")
    return result, text


def _bench_memory(args) -> tuple[dict, str]:
    from falsify.bench.memory import bench_memory

    if args.samples is not None:
        raise UsageError("--samples: bench memory runs the config's whole grid, as "
                         "`falsify grid` does")
    result = bench_memory(args.config, workers=args.workers, model=args.model).to_json()
    m = result["memory"]
    text = (f"{result['command']}: {result['samples']} samples in {result['seconds']} s; "
            + f"all processes together: {_memory_text(m)}")
    return result, text


def _bench_nodes(args) -> tuple[dict, str]:
    from falsify.bench.nodes import bench_nodes

    result = bench_nodes(args.config, nodes=args.nodes, model=args.model,
                         on_progress=None if args.json else _stderr,
                         **given_options(args, "samples")).to_json()
    text = "\n".join(f"{r['nodes']} node(s): {r['samples_per_s']} samples/s, "
                     f"{r['over_1_node']}x one node (ideal here {r['ideal_on_this_machine']})"
                     for r in result["nodes"]) + "\n" + result["note"]
    return result, text


def _bench_search(args) -> tuple[dict, str]:
    from falsify.bench.search import bench_search, over_seeds_text

    if not args.out:
        raise UsageError("bench search needs --out DIR (its runs are resumable there)")
    result = bench_search(args.config, args.out, workers=args.workers,
                          model=args.model, fraction=args.fraction, seeds=args.seeds)
    text = "\n".join(
        f"{r['algorithm']:12s} lowest {r['lowest']} after {r['evaluations']} evaluations; "
        f"within 0.02 of the grid's {result['grid_lowest']} "
        + (f"after {r['evaluations_to_target']}" if r["reached"] else "never")
        + f"; {_search_timing(r)}" for r in result["algorithms"])
    text += f"\n{result['per_evaluation_goal']}; on {args.workers} workers"
    text += "\n" + over_seeds_text(result)
    return result, text


def _bench_map(args) -> tuple[dict, str]:
    from falsify.bench.map import BUDGETS, bench_map, map_text
    if not args.out:
        raise UsageError("bench map needs --out DIR (its grid run is resumable there)")
    try:
        budgets = BUDGETS if args.budgets is None else tuple(
            float(b) for b in args.budgets.split(",") if b.strip())
    except ValueError:
        budgets = ()
    if not budgets:
        raise UsageError(f"--budgets {args.budgets!r}: shares of the grid such as "
                         "0.1,0.2,0.3")
    result = bench_map(args.config, args.out, budgets, seeds=args.seeds, model=args.model,
                       threshold=args.threshold, confidence=args.confidence,
                       workers=args.workers, timed=args.timed)
    text = map_text(result)
    return result, text


def _bench_scan(args) -> tuple[dict, str]:
    from falsify.bench.scan import bench_scan
    from falsify.bench.tables import processes

    sb = bench_scan(args.config, workers=args.workers, repeats=args.repeats,
                    **given_options(args, "samples", "naive_samples"))
    result = sb.to_json()
    rounds = ("" if len(sb.rounds_n) < 2 else
              f", median of {len(sb.rounds_n)} rounds ({_span(sb.rounds_n)} on {sb.workers}, "
              f"{_span(sb.rounds_1)} on 1)")
    text = (f"scan: {round(sb.fast_n, 1)} scans/s on {processes(sb.workers)} "
            f"({round(sb.fast_1, 1)} on 1), naive {round(sb.naive, 3)} scans/s: "
            f"{round(sb.fast_n / sb.naive, 1)}x{rounds}")
    return result, text


def _span(values) -> str:
    return f"{min(values):.1f}-{max(values):.1f}"


def _bench_camera(args) -> tuple[dict, str]:
    from falsify.cli.camera import bench_camera_text
    from falsify.sensor.camera import CAMERA_PRESETS
    if args.camera_preset not in CAMERA_PRESETS:
        raise UsageError(f"--camera-preset: unknown camera {args.camera_preset!r}; allowed: "
                         f"{', '.join(CAMERA_PRESETS)}")
    result, text = bench_camera_text(args.config, args.camera_preset,
                                     **given_options(args, "samples", "naive_samples"))
    return result, text


def _bench_effects(args) -> tuple[dict, str]:
    from falsify.bench.scan import bench_effects

    result = bench_effects(args.config, **given_options(args, "samples")).to_json()
    text = (f"effects: {result['ms_per_scan_clear']} ms a scan clear, "
            f"{result['ms_per_scan_effects']} with its effects, "
            f"{result['ms_per_scan_all_effects']} with every effect at once "
            f"({result['samples_with_effects']} of {result['samples']} samples have effects)")
    return result, text


def _bench_cells(args) -> tuple[dict, str]:
    from falsify.bench.cells import bench_cells

    result = bench_cells(args.config, **given_options(args, "samples")).to_json()
    n = len(result['maps'])
    text = (f"cells: {n} map{'s' * (n != 1)}, {result['cells']:,} cells of "
            f"{result['samples']:,} rows: {result['s_arrays']} s in arrays, "
            f"{result['s_per_group']} s one pandas group per cell ({result['speedup']}x); "
            f"the same bytes: {'yes' if result['identical'] else 'NO'}")
    return result, text


def _table(args) -> int:
    """`bench table`: the saved results as tables, printed or spliced into --write."""
    from falsify.bench.tables import load, render, splice

    results = load(Path(f) for f in args.results)
    tables = render(results)
    if args.write is None:
        cpus = sorted({d["machine"]["cpu"] for d in results})
        emit(args, {"files": sorted(args.results), "cpus": cpus,
                    "benchmarks": [d["benchmark"] for d in results], "markdown": tables}, tables)
        return 0
    doc = Path(args.write)
    if not doc.is_file():
        raise UsageError(f"--write: {doc} is not a file")
    from falsify.fileio import write_text

    write_text(doc, splice(doc.read_text(), tables))
    return 0


BENCHMARKS = {"model": _bench_model, "pipeline": _bench_pipeline, "memory": _bench_memory,
              "nodes": _bench_nodes, "search": _bench_search, "map": _bench_map,
              "scan": _bench_scan, "camera": _bench_camera, "effects": _bench_effects,
              "cells": _bench_cells}


def pipeline_figures_text(r: dict) -> str:
    """The machine-relative lines of `bench pipeline`: rates, MatMul, FLOPs, ratios, memory."""
    w, rates, mm, net, q = r["rates"]["workers"], r["rates"], r["matmul"], r["network"], r["ratios"]
    crf = "" if net["crf_share"] is None else f" (CRF {net['crf_share']:.1%})"
    mem = r["memory"]
    return "\n".join([
        f"1 thread a worker: inference alone {rates['inference_only_1_worker']} samples/s on 1 "
        f"worker, {rates['inference_only_n_workers']} on {w} at once; end to end "
        f"{rates['e2e_1_worker']} on 1, {rates['e2e_n_workers']} on {w}",
        f"machine: fp32 MatMul {mm['shape']} ({mm['library']}, 1 thread) "
        f"{mm['gflops_1_core']} GFLOP/s on 1 core, {mm['gflops_per_core_all_at_once']} per "
        f"core with {mm['processes']} at once",
        f"network: {net['gflop_per_frame']} GFLOP/frame{crf}, {net['achieved_gflops_1_thread']} "
        f"GFLOP/s on 1 thread",
        f"ratios: end to end {w}/1 workers {q['e2e_n_over_e2e_1']} (goal >= 1.8 for 2), end "
        f"to end / inference alone on {w} {q['e2e_n_over_inference_only_n']} (goal >= 0.9), "
        f"network / MatMul {q['achieved_over_matmul_1_core']} (goal >= 0.5)",
        f"memory of the {w}-worker run, all processes: {_memory_text(mem)}",
        f"streets: {r['streets']['count']}, built in every worker before the clock starts "
        f"(the steady state); each costs a worker {r['streets']['build_ms_each']} ms once",
    ])


def _memory_text(m: dict | None) -> str:
    """Peak RSS (and PSS) of a process tree, and its early and late means when measured."""
    if m is None:
        return "not measured (no /proc)"
    pss = "" if m["peak_pss_mb"] is None else f" ({m['peak_pss_mb']} MB PSS)"
    if m["early_rss_mb"] is None:
        return f"peak {m['peak_rss_mb']} MB RSS{pss}; too short for early and late means"
    return (f"peak {m['peak_rss_mb']} MB RSS{pss}; mean early {m['early_rss_mb']} MB, late "
            f"{m['late_rss_mb']} MB")


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def model_rates_text(rates: dict) -> str:
    bf16 = rates["bf16"]
    return (f"machine, 1 thread: fp32 {rates['fp32']['gflops_1_core']} GFLOP/s, int8 "
            f"{rates['int8']['gops_1_core']} GOP/s (units: "
            f"{', '.join(rates['cpu_units']['int8']) or 'none'}), bf16 "
            + (f"{bf16['gflops_1_core']} GFLOP/s" if bf16["gflops_1_core"] is not None
               else bf16["note"]))


def _search_timing(r: dict) -> str:
    """A `bench search` row's time: wall seconds, per evaluation, against random's."""
    if r["s_per_evaluation"] is None:
        return "not timed (resumed from an earlier invocation)"
    vs = r["s_per_evaluation_vs_random"]
    return (f"{r['wall_s']:.1f} s, {r['s_per_evaluation'] * 1e3:.1f} ms/evaluation"
            + ("" if vs is None else f" ({vs:.2f}x random)"))
