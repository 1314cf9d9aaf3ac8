"""`falsify faithfulness` on the real KITTI object frames (skipped without ../shared/data): a row
per Car box, the inserted car labelled car where the real one was removed, byte-identical output,
and the command's exit 2 on a missing folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.classes import CAR
from falsify.cli import main
from falsify.data.kitti_object import points_in_box, read_calib, read_labels
from falsify.data.real_backgrounds import COLLISION_POINTS, INSERTED_INSTANCE, RealScanner
from falsify.jobs.faithfulness import (
    box_pose,
    insert_in_place,
    object_scans,
    rect_to_velo,
    run_faithfulness,
)
from falsify.semantic import RAW_ID
from falsify.sensor.lidar import load_sensor
from tests.conftest import KITTI_DIR, MINI

DIRS = [KITTI_DIR / "object", KITTI_DIR / "object-extra"]


@pytest.fixture(scope="module")
def dirs() -> list[Path]:
    for d in DIRS:
        if not (d / "velodyne").is_dir():
            pytest.skip(f"KITTI object frames not found at {d} (shared/data/ is beside the repo)")
    return DIRS


@pytest.fixture(scope="module")
def result(dirs):
    from falsify.models.runners import load_segmenter
    return run_faithfulness(dirs, load_sensor("kitti-hdl64e-front"), load_segmenter(None))


def car_boxes(dirs: list[Path]) -> list[tuple[str, int]]:
    """(frame name, box line) of every Car box with a 3D extent, read straight from label_2."""
    out = []
    for d in dirs:
        for label in sorted((d / "label_2").glob("*.txt")):
            out += [(f"{d.name}/{label.stem}", k) for k, o in enumerate(read_labels(label))
                    if o.type == "Car" and o.has_3d]
    return out


def test_every_car_box_gets_a_row(dirs, result):
    assert [(r.frame, r.box) for r in result.rows] == car_boxes(dirs)
    assert len(result.frames) == 6 and result.pooled.cars == len(result.rows) >= 1
    for r in result.rows:
        assert r.real_points > 0 and r.inserted_points > 0
        assert r.collision_points < COLLISION_POINTS
        assert r.scored_pixels > 0 and r.model_lwh[0] > 0
    pooled = result.pooled.real
    assert pooled.tp == sum(r.real.tp for r in result.rows)
    assert pooled.fn == sum(r.real.fn for r in result.rows)


def test_inserted_car_is_labelled_car_and_the_real_one_is_gone(dirs):
    sensor = load_sensor("kitti-hdl64e-front")
    scans = object_scans(dirs)
    scanner = RealScanner(sensor, tuple(scans))
    checked = 0
    for f, real in enumerate(scans):
        calib = read_calib(real.bin.parent.parent / "calib" / f"{real.bin.stem}.txt")
        bg = scanner.background(f)
        for k, obj in enumerate(read_labels(real.label)):
            if obj.type != "Car":
                continue
            ins = insert_in_place(scanner, bg, obj, calib, np.random.default_rng(0))
            scan = ins.scan
            inserted = scan.valid & (scan.instance >= INSERTED_INSTANCE)
            assert inserted.any()
            assert (scan.label[inserted] == CAR).all()
            assert (scan.semantic[inserted] == RAW_ID["car"]).all()
            assert not (scan.instance == k + 1).any()          # the real car's pixels left
            rest = scan.valid & ~inserted
            assert not points_in_box(scan.image[rest][:, :3].astype(np.float64), ins.grown,
                                     calib).any()
            assert not points_in_box(ins.removed.cloud.points, ins.grown, calib).any()
            assert not points_in_box(ins.removed.ground.points, ins.grown, calib).any()
            assert ins.removed_points == len(bg.cloud) - len(ins.removed.cloud) > 0
            assert (ins.removed.valid == ins.removed.scan.valid).all()
            # the pose: the box's bottom centre, back in the rectified frame
            car = box_pose(obj, calib, "sedan")
            back = calib.velo_to_rect(np.array([[car.x, car.y, car.z]]))[0]
            assert np.allclose(back, obj.location, atol=1e-6)
            checked += 1
    assert checked == len(car_boxes(dirs))


def test_rect_to_velo_inverts_velo_to_rect(dirs):
    calib = read_calib(dirs[0] / "calib" / "000000.txt")
    p = np.array([[10.0, -2.0, -1.5], [40.0, 5.0, 0.3]])
    assert np.allclose(rect_to_velo(calib, calib.velo_to_rect(p)), p, atol=1e-9)


def test_cli_json_is_deterministic_and_parses(dirs, result, tmp_path, capsys):
    """The command's JSON, printed and written, is byte for byte the in-process run's."""
    out = tmp_path / "faithfulness.json"
    assert main(["faithfulness", *map(str, dirs), "--json", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    expected = json.dumps(result.to_json(), indent=2, sort_keys=True)
    assert out.read_bytes() == (expected + "\n").encode()
    assert printed == expected + "\n"
    doc = json.loads(printed)
    assert [(r["frame"], r["box"]) for r in doc["rows"]] == car_boxes(dirs)
    assert set(doc["pooled"]) == {"cars", "real", "inserted", "iou_difference",
                                  "recall_difference"}


def test_cli_missing_folder_exits_2(tmp_path, capsys):
    missing = tmp_path / "no-such-object-dir"
    assert main(["faithfulness", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "plain").mkdir()
    assert main(["faithfulness", str(tmp_path / "plain"), "--json"]) == 2
    assert "not a KITTI object directory" in capsys.readouterr().err


def test_a_cars_numbers_do_not_depend_on_the_frames_beside_it(dirs, result):
    """Each car's dropouts are seeded by its frame's content: reversing the directories or
    running one alone gives every car the same row (they moved with the frame's position)."""
    from falsify.models.runners import load_segmenter
    rows = {(r["frame"], r["box"]): r for r in result.to_json()["rows"]}
    for run in ([dirs[1], dirs[0]], [dirs[1]]):
        other = run_faithfulness(run, load_sensor("kitti-hdl64e-front"), load_segmenter(None))
        assert other.rows
        for r in other.to_json()["rows"]:
            assert r == rows[(r["frame"], r["box"])]


def object_copy(tmp_path: Path, dirs: list[Path], scans: list[str], labels: list[str]) -> Path:
    """A KITTI object directory of symlinks: velodyne/, calib/ and image_2/ of `scans`, label_2/
    of `labels`."""
    d = tmp_path / "obj"
    for sub, ext, names in (("velodyne", "bin", scans), ("calib", "txt", scans),
                            ("image_2", "png", scans), ("label_2", "txt", labels)):
        (d / sub).mkdir(parents=True)
        for n in names:
            (d / sub / f"{n}.{ext}").symlink_to(dirs[0] / sub / f"{n}.{ext}")
    return d


@pytest.mark.parametrize("command", [["faithfulness"], ["predict", "--out", "OUT"]])
def test_labels_without_a_scan_exit_2(dirs, tmp_path, capsys, command):
    """label_2/000001.txt (a Car) without velodyne/000001.bin is named, not skipped."""
    d = object_copy(tmp_path, dirs, ["000002"], ["000001", "000002"])
    out = tmp_path / "out"
    argv = [str(out) if a == "OUT" else a for a in command]
    assert main([*argv, str(d)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(d / "label_2" / "000001.txt") in err
    assert "velodyne/000001.bin" in err and not out.exists()


def test_a_frame_named_twice_exits_2(dirs, capsys):
    assert main(["faithfulness", str(dirs[0]), str(dirs[0])]) == 2
    assert "given twice" in capsys.readouterr().err


def semantic_root(tmp_path: Path, ids: list[str]) -> Path:
    """A SemanticKITTI root of symlinks to fit sequences of semantickitti-mini (never its
    evaluation sequences 00, 03, 06, 08)."""
    root = tmp_path / "sk" / "sequences"
    root.mkdir(parents=True)
    for sid in ids:
        assert sid not in ("00", "03", "06", "08")
        if not (MINI / "sequences" / sid / "velodyne").is_dir():
            pytest.skip(f"semantickitti-mini's sequence {sid} not found at {MINI}")
        (root / sid).symlink_to(MINI / "sequences" / sid)
    return root.parent


@pytest.mark.parametrize("form", [["04,05"], ["04", "05"]])
def test_instances_sequences_take_the_comma_form(tmp_path, capsys, form):
    """--sequences SS,SS as every other command takes it (the space list still reads the same)."""
    root = semantic_root(tmp_path, ["04", "05"])
    assert main(["faithfulness", "--instances", str(root), "--sequences", *form,
                 "--min-points", "100000", "--json"]) == 0
    scans = json.loads(capsys.readouterr().out)["scans"]
    assert scans and {s.split("/")[0] for s in scans} == {"04", "05"}


def test_instances_unknown_sequence_names_the_allowed(tmp_path, capsys):
    root = semantic_root(tmp_path, ["04"])
    assert main(["faithfulness", "--instances", str(root), "--sequences", "04,07"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--sequences 04,07" in err and "allowed: 04" in err
