"""`falsify retrain`: stages recorded and resumed after a simulated kill without recomputing
finished ones, the comparison page in headless Chromium, the gate on the before/after pair, and
bad input exiting 2 with nothing written. Tiny: 2 cells, 1 background each for V and R, one
training step of 3 scans."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.data.training import TrafficOptions, write_dataset
from falsify.errors import FalsifyError
from falsify.jobs.retrain import STAGES, RetrainJob, RetrainRequest
from falsify.jobs.retrain_config import parse_ids, subset_config
from falsify.jobs.retrain_selection import control_cells
from falsify.models.runners import BUNDLED_ONNX
from falsify.results.miou_maps import CellMap
from falsify.results.samples import sample_seed
from falsify.sensor.lidar import load_sensor
from falsify.world.space import load_space
from tests.conftest import CONFIGS, HOLDOUT, KITTI, assert_offline

MODEL = BUNDLED_ONNX
TINY = """name = "tiny"
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.99
dims.car_model.values = ["sedan"]
dims.x.values = [-3.0, 1.0]
dims.y.values = [8.0]
dims.background.values = [0, 5]
"""


class Killed(Exception):
    """Stands for the process being killed at the start of a stage."""


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("retrain")
    (root / "tiny.toml").write_text(TINY)
    sensor = load_sensor("kitti-hdl64e-front", ray_drop=0.05, range_noise=0.02)
    write_dataset(sensor, root / "train", 2, seed=1,
                  opts=TrafficOptions(backgrounds=1, traffic="drive"))
    return {"root": root, "config": root / "tiny.toml", "train": root / "train"}


def request(inputs: dict, out: Path, **kw) -> RetrainRequest:
    args = dict(config=inputs["config"], model=MODEL, train_data=inputs["train"], out=out,
                validation=(0,), retraining=(5,), epochs=1, batch=8, oversample=1,
                train_scans=1, held_out_scans=2, kitti=KITTI if KITTI.is_dir() else None,
                workers=1)
    args.update(kw)
    return RetrainRequest(**args)


@pytest.fixture(scope="module")
def experiment(inputs) -> dict:
    """Run the experiment, killed when the 'after' grid starts, then resumed."""
    pytest.importorskip("torch")   # it fine-tunes
    out = inputs["root"] / "exp"

    def kill_at_after(stage: str) -> None:
        if stage == "after":
            raise Killed

    with pytest.raises(Killed):
        RetrainJob(request(inputs, out), on_stage=kill_at_after).run()
    state = json.loads((out / "stages.json").read_text())
    stamps = {p: (out / p).stat().st_mtime_ns for p in
              ("before/results.sqlite", "rows/results.sqlite", "finetune/squeezeseg.pt",
               "finetune/squeezeseg.onnx", "selected/retrain/index.csv")}
    result = RetrainJob(request(inputs, out, resume=True)).run()
    return {"out": out, "killed_state": state, "stamps": stamps, "result": result}


@pytest.mark.slow
def test_resume_after_kill_recomputes_nothing_finished(experiment) -> None:
    out, result = experiment["out"], experiment["result"]
    assert sorted(experiment["killed_state"]["done"]) == ["before", "finetune", "rows", "selected"]
    assert result.reused == ("before", "rows", "selected", "finetune")
    assert result.computed == ("after", "checks", "report")
    for p, stamp in experiment["stamps"].items():
        assert (out / p).stat().st_mtime_ns == stamp, p
    # one training run only: its log has one line
    assert len((out / "finetune" / "train_log.jsonl").read_text().splitlines()) == 1
    state = json.loads((out / "stages.json").read_text())
    assert sorted(state["done"]) == sorted(STAGES)
    # a second resume has nothing left to do and gives the same summary
    again = RetrainJob(request(_inputs_of(out), out, resume=True)).run()
    assert again.computed == () and again.reused == STAGES
    assert again.criteria == result.criteria


def _inputs_of(out: Path) -> dict:
    root = out.parent
    return {"config": root / "tiny.toml", "train": root / "train"}


@pytest.mark.slow
def test_result_and_files(experiment) -> None:
    out, r = experiment["out"], experiment["result"]
    assert r.cells == 2 and r.threshold == 0.99
    assert len(r.blind_before) >= 1 and r.retraining_scans == len(r.blind_before)
    assert r.fixed is not None and 0 <= r.fixed <= len(r.blind_before)
    assert r.mean_before is not None and r.mean_after is not None
    names = [c.name for c in r.checks]
    assert names[0] == "held-out drive-style synthetic" and r.checks[0].scans == 2
    assert r.checks[0].before is not None and r.checks[0].after is not None
    summary = json.loads((out / "summary.json").read_text())
    assert summary["blind_before"] == [c.to_json() for c in r.blind_before]
    assert summary["checks"][0]["change"] == round(r.checks[0].after - r.checks[0].before, 4)
    for name in ("miou_before.csv", "miou_after.csv", "comparison.html"):
        assert (out / name).is_file()
    # the selected scans are R's (background 5) at V's blind cells, re-cast from R's rows
    import csv
    with open(out / "selected" / "retrain" / "index.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == r.retraining_scans and {row["background"] for row in rows} == {"5"}
    blind = {(c.x, c.y) for c in r.blind_before}
    assert {(float(row["x"]), float(row["y"])) for row in rows} == blind


@pytest.mark.slow
def test_cli_json_and_gate_on_the_pair(experiment, capsys) -> None:
    out = experiment["out"]
    root = out.parent
    assert main(["retrain", str(root / "tiny.toml"), "--model", str(MODEL), "--train-data",
                 str(root / "train"), "--validation-backgrounds", "0",
                 "--retraining-backgrounds", "5", "--out", str(out), "--resume", "--epochs",
                 "1", "--oversample", "1", "--train-scans", "1", "--held-out-scans", "2",
                 "--workers", "1", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["computed"] == [] and shown["fixed"] == experiment["result"].fixed
    code = main(["gate", str(out / "after"), "--baseline", str(out / "before"), "--json"])
    verdict = json.loads(capsys.readouterr().out)
    assert verdict["baseline"] == str(out / "before")
    assert code == (1 if verdict["new_blind_spots"] else 0)


@pytest.mark.slow
def test_comparison_page_in_chromium(browser, experiment) -> None:
    from selenium.webdriver.common.by import By

    out, r = experiment["out"], experiment["result"]
    page = (out / "comparison.html").read_text()
    assert "sorted ascending" in page and 'id="retrain-section"' in page
    loss = json.loads((out / "summary.json").read_text())["training"]["loss"]
    assert f"final loss {loss:.4f}." in page   # rounded, not float repr
    browser.get((out / "comparison.html").as_uri())
    for ident in ("before-map", "after-map", "diffmap"):
        assert len(browser.find_elements(By.CSS_SELECTOR, f"#{ident} rect > title")) == 2
    rows = browser.find_elements(By.CSS_SELECTOR, "#selected-cells tbody tr")
    assert len(rows) == len(r.blind_before)
    checks = browser.find_elements(By.CSS_SELECTOR, "#checks tbody tr")
    assert len(checks) == len(r.checks)
    assert len(browser.find_elements(By.CSS_SELECTOR, "#improvement rect.bar")) == 2
    assert_offline(browser)


@pytest.mark.slow
def test_report_cli_rebuilds_the_page(experiment, tmp_path, capsys) -> None:
    out = experiment["out"]
    page = tmp_path / "page.html"
    assert main(["report", str(out / "after"), "--compare", str(out / "before"), "--retrain",
                 str(out / "summary.json"), "--no-predict", "--out", str(page)]) == 0
    assert page.read_bytes() == (out / "comparison.html").read_bytes()
    assert main(["report", str(out / "after"), "--retrain", str(out / "summary.json"),
                 "--out", str(tmp_path / "x.html")]) == 2
    assert "--retrain needs --compare" in capsys.readouterr().err


@pytest.mark.parametrize("change, message", [
    ({"--validation-backgrounds": "0,5"}, "share background 5"),
    ({"--retraining-backgrounds": "9"}, "background 9 is not in"),
    ({"--retraining-backgrounds": "x-y"}, "--retraining-backgrounds 'x-y'"),
    ({"--model": "MISSING_PT"}, "fine-tuning starts from"),
    ({"--train-data": "NOWHERE"}, "--train-data"),
    ({"--epochs": "0"}, "--epochs: 0"),
    ({"--resume": None}, "holds no retraining run"),
    ({"--kitti": "NOWHERE"}, "nowhere: no such folder"),
    ({"--kitti": "EMPTY"}, "holds none of the real sets it checks on (squeezeseg/,"),
])
def test_bad_input_exits_2_and_writes_nothing(inputs, tmp_path, capsys, change,
                                              message) -> None:
    out = tmp_path / "out"
    onnx = tmp_path / "m.onnx"
    onnx.write_bytes(MODEL.read_bytes())
    (tmp_path / "m.json").write_bytes(MODEL.with_suffix(".json").read_bytes())
    args = {"--model": str(MODEL), "--train-data": str(inputs["train"]),
            "--validation-backgrounds": "0", "--retraining-backgrounds": "5",
            "--out": str(out)}
    (tmp_path / "empty").mkdir()
    subs = {"MISSING_PT": str(onnx), "NOWHERE": str(tmp_path / "nowhere"),
            "EMPTY": str(tmp_path / "empty")}
    args.update({k: subs.get(v, v) for k, v in change.items()})
    argv = ["retrain", str(inputs["config"])]
    for k, v in args.items():
        argv += [k] if v is None else [k, v]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("falsify: error:") and message in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.slow
def test_existing_out_needs_resume(experiment, capsys) -> None:
    out = experiment["out"]
    root = out.parent
    assert main(["retrain", str(root / "tiny.toml"), "--model", str(MODEL), "--train-data",
                 str(root / "train"), "--validation-backgrounds", "0",
                 "--retraining-backgrounds", "5", "--out", str(out)]) == 2
    assert "pass --resume" in capsys.readouterr().err
    # resuming with a different experiment is refused, naming the key
    assert main(["retrain", str(root / "tiny.toml"), "--model", str(MODEL), "--train-data",
                 str(root / "train"), "--validation-backgrounds", "0",
                 "--retraining-backgrounds", "5", "--out", str(out), "--resume",
                 "--oversample", "3", "--train-scans", "1", "--held-out-scans", "2"]) == 2
    assert "--resume: oversample differs" in capsys.readouterr().err


def test_parse_ids_and_subset_config(tmp_path) -> None:
    assert parse_ids("0-3,9", "--v") == (0, 1, 2, 3, 9)
    assert parse_ids(" 7 - 8 ".replace(" ", ""), "--v") == (7, 8)
    text = subset_config(CONFIGS / "paper.toml", (0, 1, 2, 3, 4, 5, 6), "validation")
    (tmp_path / "v.toml").write_text(text)
    sub, full = load_space(tmp_path / "v.toml"), load_space(CONFIGS / "paper.toml")
    assert sub.dims["background"].grid() == tuple(range(7))
    assert sub.world == full.world == "semantickitti-places"   # the same streets
    raw, raw_full = tomllib.loads(text), tomllib.loads((CONFIGS / "paper.toml").read_text())
    assert raw["dims"]["x"] == raw_full["dims"]["x"] and raw["seed"] == raw_full["seed"]
    # the subset's samples are exactly the full grid's samples on those backgrounds
    wanted = [s for s in full.grid() if int(s["background"]) < 7]
    assert [sample_seed(sub, s) for s in sub.grid()] == [sample_seed(full, s) for s in wanted]


def test_control_cells_are_as_many_seeded_cells_that_are_not_blind() -> None:
    miou = np.array([[0.5, 0.9, 0.8, 0.7], [0.6, 0.95, np.nan, 0.66]])
    ones = np.ones(miou.shape, dtype=np.int64)
    cmap = CellMap("x", "y", (-3.0, -1.0, 1.0, 3.0), (5.0, 8.0), miou, ones, ones * 0, ones * 0)
    blind = {(c.a, c.b) for c in cmap.blind_spots(0.65)}
    assert blind == {(-3.0, 5.0), (-3.0, 8.0)}
    picks = [control_cells(cmap, 0.65, 2, seed) for seed in range(6)]
    assert picks[0] == control_cells(cmap, 0.65, 2, 0)          # seeded
    assert len({tuple(p) for p in picks}) > 1                   # and the seed matters
    for p in picks:
        assert len(p) == 2 and len(set(p)) == 2 and not set(p) & blind
        assert all(not np.isnan(miou[(5.0, 8.0).index(b), (-3.0, -1.0, 1.0, 3.0).index(a)])
                   for a, b in p)
    assert len(control_cells(cmap, 0.65, 10, 0)) == 5          # no more than there are
    assert control_cells(cmap, 0.99, 3, 0) == []               # every cell blind: none


def test_selection_is_checked_and_part_of_the_resume_key(inputs, tmp_path) -> None:
    with pytest.raises(FalsifyError, match="--selection: 'aimed'; allowed: blind, control"):
        RetrainJob(request(inputs, tmp_path / "x", selection="aimed")).prepare()
    assert not (tmp_path / "x").exists()
    key = RetrainJob(request(inputs, tmp_path / "y", selection="control")).prepare().key
    assert key["selection"] == "control"


def _load_compare_pairs():
    """research/paper-retraining/compare_pairs.py, the script the retraining write-up cites."""
    import importlib.util
    path = Path(__file__).resolve().parents[2] / "research/paper-retraining/compare_pairs.py"
    spec = importlib.util.spec_from_file_location("compare_pairs", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module, path.parent / "other-world"


def test_compare_pairs_read_out_on_crafted_maps(tmp_path, capsys):
    """A pair shows 'selection matters' only when the targeted run leads at >= 2/3 of the blind
    cells and by > 0.01; cells that were not blind do not count."""
    compare, _ = _load_compare_pairs()
    before = {(0.0, 5.0): 0.5, (1.0, 5.0): 0.6, (2.0, 5.0): 0.6, (3.0, 5.0): 0.9}
    targeted = {(0.0, 5.0): 0.80, (1.0, 5.0): 0.70, (2.0, 5.0): 0.60, (3.0, 5.0): 0.1}
    control = {(0.0, 5.0): 0.70, (1.0, 5.0): 0.69, (2.0, 5.0): 0.61, (3.0, 5.0): 0.9}

    def write(name: str, after: dict) -> None:
        (tmp_path / name).mkdir()
        for file, cells in (("miou_before.csv", before), ("miou_after.csv", after)):
            rows = "".join(f"{x},{y},{v},7,0,0\n" for (x, y), v in cells.items())
            (tmp_path / name / file).write_text("x,y,miou,samples,undefined,invalid\n" + rows)

    write("blind", targeted)
    write("control", control)
    compare.main(tmp_path)
    out = capsys.readouterr().out
    # ahead at 2 of 3 blind cells, mean lead (0.10 + 0.01 - 0.01) / 3 = 0.0333
    assert "seed 0: targeted ahead at 2 of 3 blind cells, mean lead +0.0333" in out
    assert "selection matters" in out
    (tmp_path / "blind" / "miou_after.csv").write_text(
        (tmp_path / "blind" / "miou_after.csv").read_text().replace("0.8,", "0.72,"))
    compare.main(tmp_path)
    out = capsys.readouterr().out
    assert "not shown" in out and "over 1 pairs: targeted wins 0, control wins 0" in out
    # a second pair the control wins by the mirror rule: the pool is then not resolved
    write("blind-seed1", control)
    write("control-seed1", targeted)
    compare.main(tmp_path)
    out = capsys.readouterr().out
    assert "seed 1: targeted ahead at 1 of 3 blind cells, mean lead -0.0333" in out
    assert "the control wins" in out and "not resolved with 2 pairs" in out


def test_compare_pairs_matches_the_published_runs(capsys):
    """The figures the retraining write-up quotes come from the maps shipped beside it."""
    compare, runs = _load_compare_pairs()
    compare.main(runs)
    out = capsys.readouterr().out
    assert "seed 0: targeted ahead at 0 of 86 blind cells, mean lead -0.0571" in out
    assert "seed 1: targeted ahead at 82 of 86 blind cells, mean lead +0.0118" in out
    assert "seed 2: targeted ahead at 86 of 86 blind cells, mean lead +0.0308" in out
    assert "seed 3: targeted ahead at 27 of 86 blind cells, mean lead -0.0027" in out
    assert "seed 4: targeted ahead at 0 of 86 blind cells, mean lead -0.0420" in out
    assert "seed 5: targeted ahead at 47 of 86 blind cells, mean lead +0.0003" in out
    assert "over 6 pairs: targeted wins 2, control wins 2, mean lead -0.0098: not resolved" in out


def test_rules_select_rs_samples_under_vs_rules_without_their_streets() -> None:
    from falsify.jobs.retrain_selection import covered, transferable
    from falsify.results.explain import Condition, Rule

    far = Rule((Condition("y", ">=", 16.0), Condition("background", "==", 5)), 10, 10, 1.0,
               0.5, 0.3, 0.1)
    street = Rule((Condition("background", "==", 2),), 10, 10, 1.0, 0.5, 0.3, 0.1)
    assert transferable(far).text() == "y >= 16" and transferable(street).text() == ""
    rows = pd.DataFrame({"x": [0.0, 1.0, 2.0, 3.0], "y": [5.0, 16.0, 19.0, 10.0],
                         "background": [7, 7, 8, 8]})
    space = load_space(CONFIGS / "smoke.toml")
    assert covered([far, street], space, rows).tolist() == [False, True, True, False]
    assert not covered([street], space, rows).any()


@pytest.mark.slow
def test_selection_rules_and_its_random_control_run_the_experiment(inputs, tmp_path) -> None:
    pytest.importorskip("torch")   # it fine-tunes
    results = {sel: RetrainJob(request(inputs, tmp_path / sel, selection=sel,
                                       held_out_scans=0)).run() for sel in ("rules", "random")}
    for sel, result in results.items():
        state = json.loads((tmp_path / sel / "stages.json").read_text())
        assert state["done"]["selected"]["selection"] == sel == result.selection
        assert isinstance(state["done"]["selected"]["rules"], list)
        assert result.region is not None and "mean_before" in result.region
    # the control takes as many scans as the rules did, and reports the same region
    assert results["random"].retraining_scans == results["rules"].retraining_scans
    assert results["random"].region["samples"] == results["rules"].region["samples"]
    assert results["random"].region["mean_before"] == results["rules"].region["mean_before"]


def test_random_rows_draw_as_many_seeded_samples_from_anywhere() -> None:
    from falsify.jobs.retrain_selection import random_rows

    pool = pd.Series(np.arange(100)[::-1])
    rows = pd.DataFrame({"eval_index": np.arange(120)})
    a = random_rows(10, pool, 3, rows)
    assert a.sum() == 10 and not a[100:].any()          # only the pool's rows
    assert (random_rows(10, pool, 3, rows) == a).all()  # seeded
    assert (random_rows(10, pool.sample(frac=1, random_state=1), 3, rows) == a).all()
    assert not (random_rows(10, pool, 4, rows) == a).all()
    assert random_rows(500, pool, 3, rows).sum() == 100  # never more than the pool


def test_region_figures_read_the_region_of_a_run() -> None:
    from types import SimpleNamespace

    from falsify.jobs.retrain_result import region_figures

    run = SimpleNamespace(score_column="car_iou", ok=pd.DataFrame(
        {"eval_index": [0, 1, 2, 3], "car_iou": [0.2, 0.6, 0.9, 0.1]}))
    assert region_figures(run, [0, 1, 2], 0.65) == {"mean": 0.5667, "below": 2}
    assert region_figures(run, [], 0.65) == {"mean": None, "below": 0}


def test_evaluation_split_check_or_a_named_skip(tmp_path) -> None:
    from falsify.jobs.retrain import evaluation_split

    sensor = load_sensor("kitti-hdl64e-front")
    name, scans, note = evaluation_split(tmp_path, sensor)
    assert scans is None and str(tmp_path / "semantickitti-mini") in note
    assert evaluation_split(None, sensor)[1] is None
    if not (KITTI / "semantickitti-mini").is_dir():
        pytest.skip(f"{KITTI / 'semantickitti-mini'} not found")
    name, scans, note = evaluation_split(KITTI, sensor, (HOLDOUT,))
    assert "held-out" in name and len(scans.sources) == 12 and "12 scans" in note
    assert {Path(src).parts[-3] for src in scans.sources} == {"00", "03", "06", "08"}
