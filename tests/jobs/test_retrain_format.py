"""`--retrain-format semantickitti`: a run's retraining set as SemanticKITTI's .bin and .label
files, what a user's own trainer (RangeNet++, SalsaNext, point networks) reads. The files hold
the replayed scans' points and labels exactly: the network scores them as the rows say."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.data.velodyne import kitti_arrays
from falsify.errors import FalsifyError
from falsify.jobs.run import RunRequest, execute
from falsify.results.replay import Replay
from falsify.results.store import open_run
from falsify.semantic import RAW_ID, split_label
from tests.data.test_real_backgrounds import space_toml, street_cloud, write_scan

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "configs" / "smoke.toml"
SEQ = Path("sequences") / "00"


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, str]:
    """The smoke grid at threshold 0.95 (every cell blind: all 8 scans in the set)."""
    out = tmp_path_factory.mktemp("sk") / "run"
    argv = ["grid", str(SMOKE), "--out", str(out), "--threshold", "0.95", "--no-report",
            "--retrain-format", "semantickitti", "--quiet"]
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    return out, buf.getvalue()


def _pairs(out: Path) -> list[tuple[Path, Path]]:
    bins = sorted((out / "retrain" / SEQ / "velodyne").glob("*.bin"))
    return [(b, out / "retrain" / SEQ / "labels" / f"{b.stem}.label") for b in bins]


def test_the_set_is_sequences_00_velodyne_and_labels_named_in_index_csv(run):
    out, text = run
    index = pd.read_csv(out / "retrain" / "index.csv")
    pairs = _pairs(out)
    assert len(index) == len(pairs) == 8
    assert list(index["file"]) == [f"sequences/00/velodyne/{e:06d}.bin"
                                   for e in index["eval_index"]]
    for b, lab in pairs:
        assert b.stat().st_size == 4 * lab.stat().st_size > 0   # N x 4 float32, N uint32
    assert sorted(p.name for p in (out / "retrain").iterdir()) == ["index.csv", "sequences"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["retraining_format"] == "semantickitti" and summary["retraining_samples"] == 8
    assert "retraining set: 8 scans in" in text and "(SemanticKITTI layout)" in text


def test_the_files_hold_the_replayed_scans_points_and_labels_exactly(run):
    out, _ = run
    data = open_run(out)
    replay = Replay(data.space, lod=2)
    for _, row in data.frame.iterrows():
        _, scan = replay.scan(row)
        points, labels = kitti_arrays(scan)
        b = out / "retrain" / SEQ / "velodyne" / f"{int(row['eval_index']):06d}.bin"
        assert np.array_equal(np.fromfile(b, np.float32).reshape(-1, 4), points)
        got = np.fromfile(b.parent.parent / "labels" / f"{b.stem}.label", np.uint32)
        assert np.array_equal(got, labels)
        assert (split_label(got)[0] == RAW_ID["car"]).sum() > 0


def test_predict_on_the_set_scores_each_scan_as_its_row(run, tmp_path, capsys):
    """What a user does next: the set read back as a SemanticKITTI root scores, scan by scan,
    the car IoU its row holds (on our streets the points project to the same pixels)."""
    out, _ = run
    assert main(["predict", str(out / "retrain"), "--out", str(tmp_path / "p"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    per_scan = {Path(p["scan"]).stem: p["car_iou"] for s in result["sets"]
                for p in s["per_scan"]}
    rows = pd.read_csv(out / "results.csv").set_index("eval_index")
    assert len(per_scan) == 8
    for stem, iou in per_scan.items():
        assert iou == pytest.approx(rows.loc[int(stem), "car_iou"], abs=1e-12), stem


def test_npy_again_on_resume_replaces_the_layout(run, tmp_path):
    """Resumed with the default layout: nothing recomputed, the set rewritten as range images
    of the same points, and no SemanticKITTI file left beside them."""
    out, _ = run
    bins = {b.stem: np.fromfile(b, np.float32).reshape(-1, 4) for b, _ in _pairs(out)}
    copy = tmp_path / "run"
    import shutil
    shutil.copytree(out, copy)
    s = execute(RunRequest(config=SMOKE, out=copy, command="grid", resume=True,
                           threshold=0.95, report=False))
    assert s.computed_this_time == 0 and s.retraining_samples == 8
    assert "retraining_format" not in s.to_json()
    names = sorted(p.name for p in (copy / "retrain").iterdir())
    assert names == sorted(["index.csv", *(f"{k}.npy" for k in bins)])
    for stem, points in bins.items():
        image = np.load(copy / "retrain" / f"{stem}.npy")
        valid = image[..., 4] > 0
        assert np.array_equal(image[valid][:, :4].astype(np.float32), points)


def test_camera_images_sit_in_the_sequence(tmp_path):
    out = tmp_path / "run"
    execute(RunRequest(config=SMOKE, out=out, command="grid", threshold=0.95, report=False,
                       camera="kitti-centre", retrain_format="semantickitti"))
    seq = out / "retrain" / SEQ
    assert sorted(p.name for p in (seq / "image_2").iterdir()) == [
        f"{k:06d}.png" for k in range(8)]
    assert sorted(p.name for p in (seq / "camera").iterdir())[:4] == [
        "000000.class.npy", "000000.class.png", "000000.depth.npy", "000000.instance.npy"]


def test_a_real_background_keeps_its_raw_ids_and_the_inserted_car_its_own_instance(tmp_path):
    """On a real scan the labels are the scan's own raw ids (road, building) and the placed
    car's points raw id 10 with an instance id of their own."""
    pts, sem = street_cloud()
    street = write_scan(tmp_path / "street", pts, sem)
    cfg = space_toml(tmp_path / "real.toml", str(street.bin))
    out = tmp_path / "run"
    execute(RunRequest(config=cfg, out=out, command="grid", threshold=1.0, report=False,
                       retrain_format="semantickitti"))
    pairs = _pairs(out)
    assert len(pairs) == 4
    for _, lab in pairs:
        ids, inst = split_label(np.fromfile(lab, np.uint32))
        assert set(ids.tolist()) == {RAW_ID["road"], RAW_ID["building"], RAW_ID["car"]}
        car = ids == RAW_ID["car"]
        assert len(set(inst[car].tolist())) == 1 and inst[car][0] > 0
        assert not inst[~car].any()


def test_grid_and_search_offer_every_layout_the_writer_knows():
    from falsify.cli import build_parser
    from falsify.jobs.retraining_set import RETRAIN_FORMATS

    for command, extra in (("grid", []), ("search", ["--algorithm", "random"])):
        base = [command, "c.toml", "--out", "o", *extra]
        assert build_parser().parse_args(base).retrain_format == "npy"
        for fmt in RETRAIN_FORMATS:
            args = build_parser().parse_args([*base, "--retrain-format", fmt])
            assert args.retrain_format == fmt


@pytest.mark.parametrize("fmt", ["kitti", "NPY", ""])
def test_another_layout_is_refused_naming_the_allowed(tmp_path, fmt, capsys):
    out = tmp_path / "run"
    with pytest.raises(FalsifyError, match=r"--retrain-format: .* is not one of \['npy', "
                       r"'semantickitti'\]"):
        execute(RunRequest(config=SMOKE, out=out, command="grid", retrain_format=fmt))
    assert not out.exists()
    with pytest.raises(SystemExit) as exc:
        main(["grid", str(SMOKE), "--out", str(out), "--retrain-format", fmt])
    assert exc.value.code == 2 and "--retrain-format" in capsys.readouterr().err
    assert not out.exists()


def test_a_retraining_set_with_its_camera_files_is_what_train_reads(tmp_path, capsys):
    """Before: `falsify train --data RUN/retrain` after `grid --camera` stopped on the camera's
    000000.class.npy ("has shape (375, 1242), expected (H, W, 6)"); readers of a folder of range
    images now take its scans, the files index.csv names, and leave the camera arrays."""
    pytest.importorskip("torch")
    from falsify.data.range_npy import npy_files

    out = tmp_path / "run"
    execute(RunRequest(config=SMOKE, out=out, command="grid", threshold=0.95, report=False,
                       camera="kitti-centre"))
    retrain = out / "retrain"
    listed = sorted(pd.read_csv(retrain / "index.csv")["file"])
    assert len(listed) == 8 and (retrain / "000000.class.npy").is_file()
    assert [p.name for p in npy_files(retrain)] == listed
    assert main(["train", "--data", str(retrain), "--out", str(tmp_path / "net"), "--epochs",
                 "1", "--batch", "8", "--no-export", "--json"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])   # one line an epoch
    assert last["stopped"] == "done" and last["epoch"] == 1
