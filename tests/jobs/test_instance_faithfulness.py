"""`falsify faithfulness --instances`: SemanticKITTI's labelled cars and persons, each against a
built-in actor of its class inserted in its place. A constructed scan holds a car and a person
whose points a known pose cast, so the pose found from the points can be checked; the fit split
of ../shared/data gives the figures where it is present."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.real_backgrounds import INSERTED_INSTANCE, RealScanner
from falsify.jobs.faithfulness import Spread
from falsify.jobs.instance_faithfulness import (
    instance_pose,
    interval95,
    run_instance_faithfulness,
)
from falsify.models.runners import load_segmenter
from falsify.semantic import RAW_ID, join_label
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import FIRST_CAR_INSTANCE, PlacedCar
from tests.data.test_real_backgrounds import MINI, street_cloud, write_scan

SENSOR = "kitti-hdl64e-front"
# Where the constructed scan's objects stand (Velodyne frame: x ahead, y left) and their ids.
CAR_AT, PERSON_AT = (14.0, 2.0, 30.0), (10.0, -3.0, 90.0)


def _scan_with(tmp_path, objects: list[tuple[str, float, float, float, str, int]]):
    """The constructed street with `objects` (model, x, y, heading, class, instance) cast into
    it by RealScanner, written as a labelled SemanticKITTI scan: the objects' points keep
    their class and instance, the street's points hidden behind them are gone."""
    pts, sem = street_cloud()
    street = write_scan(tmp_path / "street", pts, sem)
    scanner = RealScanner(load_sensor("kitti-hdl64e-360"), (street,))
    bg = scanner.background(0)
    placed = [scanner.settle(bg, PlacedCar(m, x, y, h, FIRST_CAR_INSTANCE + k))
              for k, (m, x, y, h, _, _) in enumerate(objects)]
    scan = scanner.insert(bg, placed)
    valid = scan.valid
    xyz = scan.image[valid][:, 0:3]
    raw = scan.semantic[valid].astype(np.uint32)
    inst = np.zeros(len(xyz), np.uint32)
    for k, (_, _, _, _, cls, instance) in enumerate(objects):
        mine = scan.instance[valid] == INSERTED_INSTANCE + k
        raw[mine] = RAW_ID[cls]
        inst[mine] = instance
    cloud = np.column_stack([xyz, np.full(len(xyz), 0.3)]).astype(np.float32)
    return write_scan(tmp_path / "scan", cloud, join_label(raw, inst)), placed


def test_the_pose_found_from_a_cars_points_is_where_it_stood(tmp_path):
    scan, placed = _scan_with(tmp_path, [("sedan", *CAR_AT, "car", 7)])
    from falsify.data.velodyne import read_bin
    from falsify.semantic import split_label
    pts = read_bin(scan.bin)[:, :3]
    sem, inst = split_label(np.fromfile(scan.label, np.uint32))
    car = pts[(inst == 7) & (sem == RAW_ID["car"])]
    model, x, y, heading, extent = instance_pose(car, "car", placed[0].z)
    assert math.hypot(x - CAR_AT[0], y - CAR_AT[1]) < 0.5
    assert abs(math.remainder(heading - CAR_AT[2], 180.0)) < 8.0   # the axis, either way
    assert 1.2 < extent[2] < 1.7 and model != "van"


def test_each_instance_is_scored_both_ways_and_the_real_one_is_gone(tmp_path):
    scan, _ = _scan_with(tmp_path, [("sedan", *CAR_AT, "car", 7),
                                    ("pedestrian", *PERSON_AT, "person", 9)])
    result = run_instance_faithfulness([scan.bin.parent], None, load_sensor(SENSOR),
                                       load_segmenter(None))
    rows = {r.cls: r for r in result.rows}
    assert set(rows) == {"car", "person"} and not result.skipped
    car, person = rows["car"], rows["person"]
    assert (car.instance, person.instance) == (7, 9)
    assert car.model != "pedestrian" and person.model.startswith("pedestrian")
    for r in (car, person):
        assert r.removed_points >= 30 and r.real_points >= 20
        # The same object cast at the pose found from its points: about as many pixels.
        assert 0.6 < r.inserted_points / r.real_points < 1.6, r
        assert r.collision_points == 0
        assert r.real.tp + r.real.fn == r.real_points
    assert result.classes["car"].pooled.cars == 1


def test_a_views_row_does_not_depend_on_the_scans_beside_it(tmp_path):
    """The insertion's random draws are seeded by the scan's content and the instance, so a
    scan alone and after another give the same row."""
    a, _ = _scan_with(tmp_path / "a", [("sedan", *CAR_AT, "car", 7)])
    b, _ = _scan_with(tmp_path / "b", [("pedestrian", *PERSON_AT, "person", 9),
                                       ("hatchback", 18.0, -2.0, 0.0, "car", 4)])
    runs = [run_instance_faithfulness(dirs, None, load_sensor(SENSOR), load_segmenter(None))
            for dirs in ([a.bin.parent], [b.bin.parent, a.bin.parent])]
    alone, after = ([r for r in res.rows if r.instance == 7] for res in runs)
    assert len(alone) == 1 and alone == after


def test_an_instance_spanning_more_than_one_object_is_skipped_and_named(tmp_path):
    scan, _ = _scan_with(tmp_path, [("sedan", *CAR_AT, "car", 7),
                                    ("sedan", 22.0, -4.0, 0.0, "car", 7)])
    result = run_instance_faithfulness([scan.bin.parent], None, load_sensor(SENSOR),
                                       load_segmenter(None))
    assert not result.rows
    assert len(result.skipped) == 1 and "more than one car" in result.skipped[0][3]


def test_the_interval_is_students_t_on_n_minus_1():
    s = Spread.of([0.1, -0.05, 0.02, 0.04])
    lo, hi = interval95(s)
    # t(0.975, 3) = 3.182 (tables); the expansion is within 1 % of it at 3 degrees of freedom.
    assert (hi - lo) / 2 == pytest.approx(3.182 * s.sem, rel=0.01)
    assert interval95(Spread.of([0.1])) is None


def test_cli_refuses_object_directories_with_instances_and_bad_min_points(tmp_path, capsys):
    assert main(["faithfulness", str(tmp_path), "--instances", str(tmp_path)]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["faithfulness", "--instances", str(tmp_path), "--min-points", "0"]) == 2
    assert "--min-points" in capsys.readouterr().err
    assert main(["faithfulness", "--min-points", "5"]) == 2
    assert "go with --instances" in capsys.readouterr().err
    out = tmp_path / "f.json"
    assert main(["faithfulness", "--instances", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert not out.exists()


@pytest.mark.skipif(not MINI.is_dir(), reason=f"SemanticKITTI mini scans not found at {MINI}")
def test_the_fit_split_holds_cars_and_persons_to_score(tmp_path, capsys):
    out = tmp_path / "f.json"
    assert main(["faithfulness", "--instances", str(MINI), "--sequences", "07", "--out",
                 str(out), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["classes"]["car"]["pooled"]["cars"] >= 10
    assert printed["classes"]["person"]["pooled"]["cars"] >= 10
    assert all(s[0].startswith("07/") for s in printed["skipped"])
    again = copy.deepcopy(printed)
    assert main(["faithfulness", "--instances", str(MINI), "--sequences", "07", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == again


def test_a_turned_scan_shows_what_stood_beside_the_sensor(tmp_path):
    """yaw_deg turns a real scan before projection: a car 12 m to the left, out of the front
    view, comes straight ahead with its range kept; rings still come from the stored order."""
    from dataclasses import replace

    from falsify.data.real_backgrounds import read_background
    scan, _ = _scan_with(tmp_path, [("sedan", 0.0, 12.0, 0.0, "car", 7)])
    sensor = load_sensor(SENSOR)
    ahead = read_background(scan, sensor)
    turned = read_background(replace(scan, yaw_deg=-90.0), sensor)
    assert not (ahead.scan.instance == 7).any()
    mine = turned.scan.instance == 7
    assert mine.sum() > 100
    cols = np.nonzero(mine)[1]
    assert abs(np.median(cols) - sensor.columns / 2) < 20
    r = turned.scan.image[mine][:, 4]
    assert 10.0 < np.median(r) < 13.0
    assert read_background(replace(scan, yaw_deg=0.0), sensor).scan.image.tobytes() == \
        ahead.scan.image.tobytes()
