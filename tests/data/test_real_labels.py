"""Real scans without labels: a SemanticKITTI sequence's scan whose .label is missing is a config
error naming it, `labels = "optional"` lets unlabelled scans in (SemanticKITTI's test sequences)
with their real_ columns empty and said in the summary, and `per_sequence` never asks a sequence
for more scans than it holds."""

from __future__ import annotations

import json
import shutil
import sqlite3
import tomllib
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.jobs.retrain_config import subset_config
from falsify.results.metrics import Scoring
from falsify.world.space import load_space
from tests.conftest import MINI, ROOT, one_car_config
from tests.data.test_real_backgrounds import space_toml, street_cloud

SK20 = ROOT / "models" / "weights" / "squeezeseg20.onnx"


def sequence(root: Path, sid: str, scans: int, labels: bool = True,
             missing: tuple[int, ...] = ()) -> list[Path]:
    """A SemanticKITTI sequence root/sequences/SID of `scans` small scans; its labels/ folder
    only when `labels`, without the .label of the scans in `missing`."""
    velodyne = root / "sequences" / sid / "velodyne"
    velodyne.mkdir(parents=True, exist_ok=True)
    if labels:
        (velodyne.parent / "labels").mkdir(exist_ok=True)
    out = []
    for i in range(scans):
        pts = np.random.default_rng(i).normal(size=(20 + i, 4)).astype(np.float32)
        pts.tofile(velodyne / f"{i:06d}.bin")
        if labels and i not in missing:
            np.full(len(pts), 40, np.uint32).tofile(velodyne.parent / "labels" / f"{i:06d}.label")
        out.append(velodyne / f"{i:06d}.bin")
    return out



def refused(tmp_path: Path, capsys, background: str, *args: str) -> str:
    """The error of a grid on this background, which must exit 2 and create no run folder."""
    run = tmp_path / "run"
    assert main(["grid", str(one_car_config(tmp_path, background)), "--out", str(run), "--quiet",
                 *args]) == 2
    assert not run.exists()
    return capsys.readouterr().err


def test_a_scan_whose_label_is_missing_exits_2_naming_the_file(tmp_path, capsys):
    sequence(tmp_path / "sk", "01", 3, missing=(1,))
    err = refused(tmp_path, capsys, f'real = ["{tmp_path / "sk"}"]\nsequences = ["01"]\n'
                  'per_sequence = 3\n')
    assert "c.toml: dims.background.real: 1 of 3 scans has no labels" in err
    assert f"missing {tmp_path / 'sk' / 'sequences' / '01' / 'labels' / '000001.label'}." in err
    assert 'set labels = "optional" in [dims.background]' in err
    # The same scan named as its folder, or alone, is refused too.
    velodyne = tmp_path / "sk" / "sequences" / "01" / "velodyne"
    for real in (velodyne, velodyne / "000001.bin"):
        assert "000001.label" in refused(tmp_path, capsys, f'real = ["{real}"]\n')


def test_a_sequence_without_labels_is_named_once_with_its_scans_counted(tmp_path, capsys):
    sequence(tmp_path / "sk", "01", 2)
    sequence(tmp_path / "sk", "02", 2, labels=False)
    err = refused(tmp_path, capsys, f'real = ["{tmp_path / "sk"}"]\n')
    labels = tmp_path / "sk" / "sequences" / "02" / "labels"
    assert f"2 of 4 scans have no labels, so the cars in them would be scored as background: " \
           f"missing {labels}/ (no such folder: 2 scans)." in err
    assert "SemanticKITTI's test sequences 11-21" in err


def test_many_missing_labels_name_the_first_three_and_count_the_rest(tmp_path, capsys):
    sequence(tmp_path / "sk", "05", 6, missing=(0, 1, 2, 3, 4))
    err = refused(tmp_path, capsys, f'real = ["{tmp_path / "sk"}"]\n')
    assert "5 of 6 scans have no labels" in err
    assert "000002.label, and 2 more." in err and "000003.label" not in err


def test_only_the_scans_taken_need_labels(tmp_path):
    sequence(tmp_path / "sk", "01", 5, missing=(1,))
    background = f'real = ["{tmp_path / "sk"}"]\nper_sequence = 3\n'
    space = load_space(one_car_config(tmp_path, background))
    assert [r.name for r in space.real_backgrounds] == ["01/000000", "01/000002", "01/000004"]
    assert {r.kind for r in space.real_backgrounds} == {"semantickitti"}


def test_a_bare_scan_may_have_no_labels_unless_they_are_required(tmp_path, capsys):
    bare = tmp_path / "mine" / "x.bin"
    bare.parent.mkdir()
    np.zeros((4, 4), np.float32).tofile(bare)
    space = load_space(one_car_config(tmp_path, f'real = ["{bare}"]\n'))
    assert space.real_backgrounds[0].kind == "none"
    err = refused(tmp_path, capsys, f'real = ["{bare}"]\nlabels = "required"\n')
    assert f"missing {bare.with_suffix('.label')} (or ../labels/x.label)" in err


@pytest.mark.parametrize("value", ['"maybe"', "true", '["optional"]'])
def test_a_bad_labels_value_exits_2_with_the_allowed_ones(tmp_path, capsys, value):
    sequence(tmp_path / "sk", "01", 1)
    err = refused(tmp_path, capsys, f'real = ["{tmp_path / "sk"}"]\nlabels = {value}\n')
    assert "c.toml: dims.background.labels: " in err
    assert 'allowed: "required" (every scan has labels), "optional"' in err


def test_per_sequence_beyond_a_sequences_scans_exits_2_naming_it(tmp_path, capsys):
    sequence(tmp_path / "sk", "01", 5)
    sequence(tmp_path / "sk", "02", 3)
    err = refused(tmp_path, capsys, f'real = ["{tmp_path / "sk"}"]\nper_sequence = 4\n')
    assert (f"c.toml: dims.background.per_sequence: 4 scans asked of each sequence, but "
            f"sequence 02 ({tmp_path / 'sk' / 'sequences' / '02' / 'velodyne'}) holds 3 scans; "
            "allowed: 1 to 3") in err
    background = f'real = ["{tmp_path / "sk"}"]\nper_sequence = 3\n'
    space = load_space(one_car_config(tmp_path, background))
    assert len(space.real_backgrounds) == 6


def test_unlabelled_scans_leave_the_real_columns_empty():
    truth = np.array([1, 1, 0, 0])         # an inserted car (0, 1); no label on the rest
    inserted = np.array([True, True, False, False])
    pred = np.array([1, 1, 1, 0])          # a car predicted on a real, unlabelled pixel
    labelled, _ = Scoring(parts=True).score(pred, truth, inserted)
    bare, _ = Scoring(parts=True).score(pred, truth, inserted, real_labelled=False)
    assert labelled["real_iou"] == 0.0 and bare["real_iou"] is None and bare["real_recall"] is None
    assert bare["inserted_recall"] == labelled["inserted_recall"] == 1.0
    assert bare["car_iou"] == labelled["car_iou"]


def test_optional_labels_run_on_an_unlabelled_sequence_and_say_so(tmp_path, capsys):
    pts, _ = street_cloud()
    velodyne = tmp_path / "sk" / "sequences" / "11" / "velodyne"
    velodyne.mkdir(parents=True)
    pts.tofile(velodyne / "000000.bin")
    cfg = space_toml(tmp_path / "test.toml", str(tmp_path / "sk"), 'labels = "optional"\n')
    run = tmp_path / "run"
    assert main(["grid", str(cfg), "--out", str(run), "--quiet", "--no-report", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["unlabelled_backgrounds"] == ["11/000000"]
    with sqlite3.connect(run / "results.sqlite") as con:
        rows = con.execute("SELECT status, inserted_recall, real_iou, real_recall "
                           "FROM samples").fetchall()
    assert len(rows) == 4 and all(r[0] == "ok" and r[1] is not None for r in rows)
    assert all(r[2] is None and r[3] is None for r in rows)
    # Retraining on a subset keeps the opt-in: its scans load again.
    subset = tmp_path / "subset.toml"
    subset.write_text(subset_config(cfg, [0], "x", load_space(cfg).real_backgrounds))
    assert tomllib.loads(subset.read_text())["dims"]["background"]["labels"] == "optional"
    assert load_space(subset).real_backgrounds[0].kind == "none"
    with pytest.raises(ConfigError, match=r"sequences/11/labels/ \(no such folder: 1 scan\)"):
        load_space(space_toml(tmp_path / "required.toml", str(tmp_path / "sk")))


@pytest.mark.skipif(not (MINI / "sequences" / "02").is_dir(),
                    reason=f"SemanticKITTI mini scans not found at {MINI}")
def test_a_bare_real_scan_leaves_real_iou_empty_and_the_summary_names_it(tmp_path, capsys):
    """02/000000 holds real cars the network finds: without its labels they are no car, and
    real_iou was 0.0 for every sample."""
    bare = tmp_path / "scan.bin"
    shutil.copy(MINI / "sequences" / "02" / "velodyne" / "000000.bin", bare)
    cfg = space_toml(tmp_path / "bare.toml", str(bare))
    run = tmp_path / "run"
    assert main(["grid", str(cfg), "--out", str(run), "--quiet", "--no-report"]) == 0
    out = capsys.readouterr().out
    assert f"real scans without labels: 1 ({tmp_path.name}/scan); their real_iou and " \
           "real_recall are empty" in out
    with sqlite3.connect(run / "results.sqlite") as con:
        rows = con.execute("SELECT status, car_fp, real_iou FROM samples").fetchall()
    assert any(r[1] > 0 for r in rows)   # cars predicted where there is no label of one
    assert all(r[0] != "ok" or r[2] is None for r in rows)


@pytest.mark.parametrize("objective, named", [(None, "car"), ("pedestrian", "pedestrian")])
def test_the_unlabelled_scans_line_names_the_runs_class(objective, named):
    """A pedestrian run's summary says a pedestrian predicted on a real one counts against the
    inserted pedestrian, not a car."""
    from types import SimpleNamespace

    from falsify.cli.run import summary_text
    s = SimpleNamespace(
        lowest=None, objective=objective, mean_car_iou=None, mean_objective=None, samples=2,
        computed_this_time=2, invalid=0, undefined=0, elapsed_s=1.0, blind_spots=0, cells=1,
        threshold=0.65, retraining_samples=0, retraining_skipped=None, run="r", estimated=None,
        executors=None,
        environment_changes=None,
        report=None, unlabelled_backgrounds=["seq/scan"])
    assert (f"a {named} predicted on one of their real {named}s counts against the inserted "
            f"{named}") in summary_text(s)


@pytest.mark.skipif(not SK20.exists(), reason="models/weights/squeezeseg20.onnx not present")
def test_a_semantickitti_model_refuses_unlabelled_scans_before_the_run(tmp_path, capsys):
    sequence(tmp_path / "sk", "11", 2, labels=False)
    err = refused(tmp_path, capsys, f'real = ["{tmp_path / "sk"}"]\nlabels = "optional"\n',
                  "--model", "squeezeseg20")
    assert ("c.toml: dims.background.real: squeezeseg20 predicts SemanticKITTI's classes and is "
            "scored on each scan's SemanticKITTI labels; 2 scans have none (11/000000, "
            "11/000001)") in err
