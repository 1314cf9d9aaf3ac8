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
from tests.conftest import KITTI_DIR

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
