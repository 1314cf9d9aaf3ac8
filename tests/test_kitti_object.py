"""`falsify dataset --format kitti-object`: KITTI's layout, readable by our own KITTI reader,
deterministic, and consistent (points in 3D boxes land in the 2D boxes); label I/O."""

from __future__ import annotations

import json

import numpy as np
import pytest

from falsify.calib_check import check_kitti_dir
from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.kitti_object import KittiObject, read_calib, read_labels, read_velodyne

from .conftest import CONFIGS


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("ko") / "kitti"
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "2", "--out", str(out),
                 "--format", "kitti-object", "--max-cars", "6", "--json"]) == 0
    return out


def test_export_layout_and_contents(exported):
    for d, ext in (("velodyne", "bin"), ("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        assert sorted(p.name for p in (exported / d).iterdir()) == [f"00000{k}.{ext}"
                                                                   for k in range(2)]
    pts = read_velodyne(exported / "velodyne" / "000000.bin")
    assert pts.shape[1] == 4 and len(pts) > 10000
    calib = read_calib(exported / "calib" / "000000.txt")
    assert np.allclose(calib.R0_rect, np.eye(3))
    labels = read_labels(exported / "label_2" / "000000.txt")
    assert any(o.type == "Car" for o in labels)
    for o in labels:
        h, w, length = o.dimensions
        assert 0.3 < h < 3.5 and 0.2 < w < 3 and 0.2 < length < 7
        left, top, right, bottom = o.box2d
        assert -0.5 <= left < right <= 1241.5 and -0.5 <= top < bottom <= 374.5
        assert abs(o.location[1] - 1.73) < 0.2  # on the road or the sidewalk, 1.73 m below
        assert o.occluded in (0, 1, 2, 3) and 0 <= o.truncated <= 1


def test_export_points_in_boxes_land_in_2d_boxes(exported):
    report = check_kitti_dir(exported, None)
    cars = report.pooled(("Car",))
    assert cars["points_in_boxes"] > 2000 and cars["fraction"] >= 0.95, cars


def test_export_is_deterministic_and_resumable(exported, tmp_path, capsys):
    again = tmp_path / "again"
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "1", "--out", str(again),
                 "--format", "kitti-object", "--max-cars", "6"]) == 0
    for d, ext in (("velodyne", "bin"), ("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        name = f"000000.{ext}"
        assert (again / d / name).read_bytes() == (exported / d / name).read_bytes(), d
    capsys.readouterr()
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "1", "--out", str(again),
                 "--format", "kitti-object", "--max-cars", "6", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["written"] == 0


def test_label_line_round_trip(tmp_path):
    obj = KittiObject("Car", 0.12, 1, -1.57, (100.25, 150.5, 300.0, 260.75), (1.5, 1.8, 4.2),
                      (-2.5, 1.7, 18.25), 1.2)
    path = tmp_path / "l.txt"
    path.write_text(obj.line() + "\n" + obj.line() + " 0.93\n")
    back = read_labels(path)
    assert back == [obj, obj]
    corners = obj.corners()
    inside = obj.contains(np.vstack([corners.mean(axis=0), corners.mean(axis=0) + [0, -5, 0]]))
    assert inside.tolist() == [True, False]


@pytest.mark.parametrize(("line", "message"), [
    ("Tank 0 0 0 1 2 3 4 1 1 1 0 0 5 0", "unknown type 'Tank'; allowed: Car"),
    ("Car 0 0 0 1 2 3", "7 fields, expected 15"),
    ("Car 0 0 0 1 2 3 4 1 1 x 0 0 5 0", "must be numbers"),
])
def test_bad_label_line_names_file_and_line(tmp_path, line, message):
    path = tmp_path / "l.txt"
    path.write_text(line + "\n")
    with pytest.raises(FalsifyError, match=message):
        read_labels(path)


def test_dataset_bad_camera_exits_2(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "1", "--out", str(out),
                 "--format", "kitti-object", "--camera", "fisheye"]) == 2
    assert "unknown camera 'fisheye'" in capsys.readouterr().err
    assert not out.exists()
