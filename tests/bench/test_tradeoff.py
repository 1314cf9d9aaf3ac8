"""`falsify tradeoff`: rows per knob, zero error at the reference, a self-contained page, exit 2 on
bad input with nothing written, and the map-comparison helpers on edge cases."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from falsify.bench.tradeoff import (
    BUDGET_FRACTIONS,
    BUDGET_SAMPLERS,
    CRF_ITERATIONS,
    KNOBS,
    LODS,
    PRECISIONS,
    RESOLUTIONS,
    STEPS,
)
from falsify.cli import main
from falsify.reports.tradeoff_page import pareto, plot
from falsify.results.miou_maps import CellMap, fill_nearest, jaccard, map_error

pytestmark = pytest.mark.slow   # the heavy tier: whole trade-off runs

CONFIG = """name = "tiny"
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.65
[dims.car_model]
values = ["sedan"]
[dims.x]
min = -2.0
max = -1.0
step = 1.0
[dims.y]
min = 9.0
max = 10.0
step = 1.0
[dims.background]
values = [0]
"""


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """A seeded random SqueezeSeg (CRF 3) as .onnx + .json, with its state dict as .pt."""
    torch = pytest.importorskip("torch")
    from falsify.models.export import export_onnx
    from falsify.models.squeezeseg import SqueezeSeg

    torch.manual_seed(0)
    net = SqueezeSeg().eval()
    d = tmp_path_factory.mktemp("model")
    path, _ = export_onnx(net, d / "rand.onnx")
    torch.save(net.state_dict(), d / "rand.pt")
    return path


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "tiny.toml"
    p.write_text(CONFIG)
    return p


@pytest.fixture(scope="module")
def run(model, config, tmp_path_factory) -> tuple[Path, dict]:
    """All knobs on the first 3 samples of the 2 × 2 grid (the step knob uses their extent)."""
    out = tmp_path_factory.mktemp("run") / "out"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("falsify.data.training.CALIBRATION_SCANS", 2)   # keep the test quick: a short
        mp.setattr("falsify.bench.tradeoff.TIMING_ROUNDS", 1)       # calibration, one timing round
        assert main(["tradeoff", str(config), "--out", str(out), "--model", str(model),
                     "--limit", "3"]) == 0
    return out, json.loads((out / "tradeoff.json").read_text())


def _names() -> dict[str, list[str]]:
    return {
        "resolution": [f"{r}x{c}" + (" (native)" if (r, c) == (64, 512) else "")
                       for r, c in RESOLUTIONS],
        "lod": [f"lod {k}" for k in LODS],
        "precision": list(PRECISIONS),
        "crf": [f"crf {k}" for k in CRF_ITERATIONS],
        "step": [f"{s:g} m" for s in STEPS],
        "budget": ["grid 100%"] + [f"{n} {f:.0%}" for n in BUDGET_SAMPLERS
                                   for f in BUDGET_FRACTIONS],
        "preset": ["exact", "balanced", "fast", "fastest"],
    }


def test_csv_rows_per_knob_and_setting(run):
    out, summary = run
    with open(out / "tradeoff.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    got: dict[str, list[str]] = {}
    for r in rows:
        got.setdefault(r["knob"], []).append(r["setting"])
    assert got == _names()
    assert list(rows[0])[:11] == ["knob", "setting", "is_reference", "time_per_sample_ms",
                                  "speedup", "map_mean_abs_error", "map_max_abs_error",
                                  "blind_spot_jaccard", "blind_spots", "samples", "notes"]
    assert summary["samples"] == 3 and len(summary["rows"]) == len(rows)
    assert not summary["notes"], summary["notes"]          # nothing skipped: torch is here
    assert sorted(p.name for p in (out / "models").glob("*.onnx")) == [
        "rand-crf0.onnx", "rand-crf1.onnx", "rand-crf2.onnx", "rand-fp16.onnx", "rand-int8.onnx"]


def test_reference_rows_have_zero_error_and_full_agreement(run):
    _, summary = run
    refs = [r for r in summary["rows"] if r["is_reference"]]
    assert {r["knob"] for r in refs} == set(KNOBS)
    # a model of your own runs as given in every preset: each is the reference setting
    assert {r["setting"] for r in refs} == {"64x512 (native)", "lod 2", "onnx fp32", "crf 3",
                                            "0.5 m", "grid 100%", "exact", "balanced", "fast",
                                            "fastest"}
    for r in refs:
        assert r["map_mean_abs_error"] == 0.0 and r["map_max_abs_error"] == 0.0, r
        assert r["blind_spot_jaccard"] == 1.0 and r["speedup"] == 1.0, r


def test_errors_finite_and_non_negative(run):
    _, summary = run
    for r in summary["rows"]:
        assert r["time_per_sample_ms"] > 0 and r["speedup"] > 0, r
        for key in ("map_mean_abs_error", "map_max_abs_error"):
            assert r[key] is not None and math.isfinite(r[key]) and r[key] >= 0, r
        assert r["map_mean_abs_error"] <= r["map_max_abs_error"] + 1e-12
        assert 0.0 <= r["blind_spot_jaccard"] <= 1.0
    step = {r["setting"]: r for r in summary["rows"] if r["knob"] == "step"}
    # 0.5 m over x -2..-1, y 9..10 is 3 × 3 cells; 1 m is 2 × 2; 2 m is 1 × 1.
    assert [step[f"{s:g} m"]["samples"] for s in STEPS] == [9, 4, 1]
    lod = {r["setting"]: r["notes"] for r in summary["rows"] if r["knob"] == "lod"}
    assert all(re.fullmatch(r"sedan \d+ triangles", n) for n in lod.values()), lod


def test_html_is_one_self_contained_file(run):
    out, _ = run
    text = (out / "tradeoff.html").read_text()
    assert "<svg" in text and "<table>" in text and "Pareto" in text
    assert not re.search(r"https?://", text)
    assert not re.search(r"<(script|link|img|iframe)\b", text)
    assert sorted(p.name for p in out.iterdir()) == ["models", "tradeoff.csv", "tradeoff.html",
                                                     "tradeoff.json"]


def test_unknown_knob_exits_2_and_writes_nothing(config, model, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["tradeoff", str(config), "--out", str(out), "--model", str(model),
                 "--knobs", "lod,colour"]) == 2
    err = capsys.readouterr().err
    assert "unknown knob 'colour'" in err and ", ".join(KNOBS) in err
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--limit", "0"], "--limit"),
    (["--model", "missing.onnx"], "missing.onnx"),
])
def test_bad_input_exits_2_and_writes_nothing(config, model, tmp_path, capsys, args, message):
    out = tmp_path / "out"
    argv = ["tradeoff", str(config), "--out", str(out), "--model", str(model), *args]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_listed_positions_need_a_range_only_for_the_knobs_that_resample_them(model, tmp_path,
                                                                           capsys):
    """x and y as `values`: the step and budget knobs, which resample them, name the dim and
    the knob; the lod knob runs (before: refused for every knob)."""
    config = tmp_path / "listed.toml"
    config.write_text(CONFIG.replace("min = -2.0\nmax = -1.0\nstep = 1.0", "values = [-2.0, 2.0]"))
    out = tmp_path / "out"
    assert main(["tradeoff", str(config), "--out", str(out), "--model", str(model),
                 "--knobs", "lod,step"]) == 2
    assert "dims.x must be a range (min, max, step) for the step knob;" in capsys.readouterr().err
    assert not out.exists()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("falsify.bench.tradeoff.TIMING_ROUNDS", 1)
        assert main(["tradeoff", str(config), "--out", str(out), "--model", str(model),
                     "--knobs", "lod", "--limit", "2"]) == 0
    assert (out / "tradeoff.html").is_file()


def test_a_failure_while_measuring_leaves_no_folder(config, model, tmp_path, monkeypatch):
    """The CRF variants are exported, then timing fails: OUT is not made (before: OUT/models/
    held the exported variants without any result beside them)."""
    def broken(*_a, **_k):
        raise RuntimeError("timing failed")

    monkeypatch.setattr("falsify.bench.tradeoff.SettingScorer.time", broken)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="timing failed"):
        main(["tradeoff", str(config), "--out", str(out), "--model", str(model),
              "--knobs", "crf", "--limit", "1"])
    assert not out.exists()


def test_jaccard_edge_cases():
    assert jaccard(set(), set()) == 1.0
    assert jaccard({(0, 0)}, set()) == 0.0
    assert jaccard({(0, 0), (1, 1)}, {(1, 1), (2, 2)}) == pytest.approx(1 / 3)


def _map(xs, ys, values) -> CellMap:
    m = np.asarray(values, float)
    z = np.zeros(m.shape, np.int64)
    return CellMap("x", "y", tuple(xs), tuple(ys), m, z, z, z)


def test_fill_nearest_and_compare():
    coarse = _map([0.0, 2.0], [0.0], [[0.5, np.nan]])
    filled = fill_nearest(coarse, [0.0, 1.0, 2.0], [0.0])
    assert filled.tolist() == [[0.5, 0.5, 0.5]]     # empty cell from the only sampled cell
    tie = fill_nearest(_map([0.0, 2.0], [0.0], [[0.1, 0.9]]), [1.0], [0.0])
    assert tie.tolist() == [[0.1]]                 # ties go to the lower coordinate
    assert np.isnan(fill_nearest(_map([0.0], [0.0], [[np.nan]]), [0.0], [0.0])).all()

    ref = _map([0.0, 1.0, 2.0], [0.0], [[0.9, 0.5, np.nan]])
    err = map_error(ref, np.array([[0.8, np.nan, 0.1]]), 0.65)
    assert err.mean_abs == pytest.approx(0.1) and err.max_abs == pytest.approx(0.1)
    assert err.lost_cells == 1 and err.blind_spots == 0 and err.jaccard == 0.0
    both_clear = map_error(ref, np.array([[0.9, 0.9, 0.9]]), 0.3)
    assert both_clear.jaccard == 1.0 and both_clear.blind_spots == 0


def test_pareto_front():
    assert pareto([(1.0, 0.5), (2.0, 0.1), (1.5, 0.6), (3.0, 0.0)]) == [
        (1.0, 0.5), (2.0, 0.1), (3.0, 0.0)]


def test_plot_with_every_error_under_a_hundredth():
    """A run whose settings all change the map by < 0.01 (e.g. --knobs lod) still gets its
    plot (before: TypeError from a float axis bound, after the csv and json were written)."""
    rows = [{"knob": "lod", "setting": f"lod {k}", "is_reference": k == 2, "map_time_s": 0.16,
             "map_mean_abs_error": err} for k, err in ((0, 0.001), (1, 0.0004), (2, 0.0))]
    svg = plot(rows, 2)
    assert svg.startswith("<svg") and "lod 0" in svg and "≤0.0001" in svg
