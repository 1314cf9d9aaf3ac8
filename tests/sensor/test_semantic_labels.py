"""Every synthetic point carries a SemanticKITTI raw id: per face in the streets, per pixel in
scans (weather and faults included), through .bin/.label files and `dataset --format
semantickitti`, whose files read back as SemanticKITTI's own tools read them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from falsify.classes import UNKNOWN
from falsify.cli import main
from falsify.data.scansets import load_sets
from falsify.data.training import VELO_TO_CAM, TrafficOptions, scene_for, world_from_sensor
from falsify.data.velodyne import TO_SEMANTICKITTI, read_kitti, write_kitti
from falsify.semantic import RAW_ID, RAW_NAMES, kitti4, split_label
from falsify.sensor.lidar import load_sensor
from falsify.sensor.scan import Scan
from falsify.sensor.simulator import PlacedCar, Simulator
from falsify.sensor.weather import Effects
from falsify.world.materials import MATERIAL_ID
from falsify.world.road_users import OTHER_VEHICLE_SEMANTIC, OTHER_VEHICLES
from falsify.world.space import load_space
from falsify.world.streets import _layout, build_background
from tests.conftest import CONFIGS

SMOKE = CONFIGS / "smoke.toml"
TOWN = next(i for i in range(100) if _layout(i).town)
BACKGROUNDS = (0, 1, 2, 3, 4, 5, TOWN)
REQUIRED = ("road", "sidewalk", "terrain", "building", "vegetation", "trunk", "pole",
            "traffic-sign", "fence", "car")


@pytest.fixture(scope="module")
def sim() -> Simulator:
    return Simulator(load_sensor(load_space(SMOKE).sensor))


def check_scan(scan: Scan) -> None:
    """The scan's semantic image is the raw ids whose four-class view is its label channel."""
    sem = scan.semantic
    assert sem is not None and sem.dtype == np.uint16 and sem.shape == scan.label.shape
    v = scan.valid
    assert (kitti4(sem[v]) == scan.label[v]).all()
    assert (sem[~v] == 0).all()
    assert set(np.unique(sem).tolist()) <= set(RAW_NAMES)


# -- the world ----------------------------------------------------------------------------------
@pytest.mark.parametrize("bg_id", BACKGROUNDS)
def test_every_face_has_a_semantickitti_id(bg_id: int) -> None:
    bg = build_background(bg_id)
    sem = bg.face_semantic
    assert sem.dtype == np.uint16 and sem.shape == (len(bg.faces),)
    assert not sem.flags.writeable
    assert set(np.unique(sem).tolist()) <= set(RAW_NAMES)
    assert (sem != 0).all()                              # nothing left unlabeled
    assert (kitti4(sem) == bg.face_class).all()          # the four classes are its view
    assert bg.semantics() is sem


def test_streets_hold_the_classes_semantickitti_annotates() -> None:
    seen: set[int] = set()
    for bg_id in BACKGROUNDS:
        seen |= set(np.unique(build_background(bg_id).face_semantic).tolist())
    names = {RAW_NAMES[i] for i in seen}
    assert set(REQUIRED) <= names, set(REQUIRED) - names
    assert {"person", "bicyclist", "bicycle", "truck"} <= names


@pytest.mark.parametrize("bg_id", (0, 2, TOWN))
def test_mixed_pieces_are_labelled_per_face(bg_id: int) -> None:
    """A tree's bark is trunk and its crown vegetation; a sign's plate is traffic-sign; the
    ground is road, sidewalk (kerbs too) or terrain by its surface."""
    bg = build_background(bg_id)
    sem, mat = bg.face_semantic, bg.face_material
    ground = bg.face_instance == 0
    expect = {"asphalt": "road", "bark": "trunk", "retro": "traffic-sign", "grass": "terrain",
              "foliage": "vegetation", "hedge": "vegetation", "chain-link": "fence",
              "facade": "building"}
    for material, name in expect.items():
        sel = mat == MATERIAL_ID[material]
        assert (sem[sel] == RAW_ID[name]).all(), material
    trees = np.unique(bg.face_instance[mat == MATERIAL_ID["bark"]])
    crowns = np.isin(bg.face_instance, trees) & (mat == MATERIAL_ID["foliage"])
    assert crowns.any() and (sem[crowns] == RAW_ID["vegetation"]).all()
    concrete_ground = ground & (mat == MATERIAL_ID["concrete"]) & (bg.face_class == UNKNOWN)
    assert set(np.unique(sem[concrete_ground]).tolist()) <= {RAW_ID["sidewalk"], RAW_ID["fence"],
                                                             RAW_ID["building"]}


def test_backgrounds_without_ids_derive_them_from_classes() -> None:
    bg = build_background(0)
    plain = dataclasses.replace(bg, face_semantic=None)
    derived = plain.semantics()
    assert (kitti4(derived) == bg.face_class).all()
    assert set(np.unique(derived).tolist()) <= {0, 10, 30, 31}
    two = dataclasses.replace(bg, faces=bg.faces[:2], face_class=bg.face_class[:2],
                              face_instance=bg.face_instance[:2], face_material=None)
    assert len(two.semantics()) == 2   # ids of other faces are not used


# -- scans --------------------------------------------------------------------------------------
def test_scans_of_samples_carry_semantic_ids(sim: Simulator) -> None:
    seen: set[int] = set()
    for k, sample in enumerate(load_space(SMOKE).grid()):
        scan = sim.scan(sample, rng=np.random.default_rng(k))
        check_scan(scan)
        car = scan.valid & (scan.instance == 1)     # the sampled car
        assert car.any() and (scan.semantic[car] == RAW_ID["car"]).all()
        seen |= set(np.unique(scan.semantic[scan.valid]).tolist())
    assert {RAW_ID["road"], RAW_ID["car"], RAW_ID["sidewalk"]} <= seen


def test_other_vehicles_cast_as_their_kind(sim: Simulator) -> None:
    for kind in OTHER_VEHICLES:
        car = sim.settle(1, PlacedCar(kind, 14.0, 0.0, 0.0, 1, cls=UNKNOWN))
        scan = sim.render(1, [car])
        check_scan(scan)
        mine = scan.valid & (scan.instance == 1)
        assert mine.any() and (scan.semantic[mine] == OTHER_VEHICLE_SEMANTIC[kind]).all()
    assert sim.car_semantic(PlacedCar("sedan", 0.0, 0.0, 0.0, 1)) == RAW_ID["car"]


@pytest.mark.parametrize("fx", [Effects(fog=30.0), Effects(rain=40.0), Effects(snow=5.0),
                                Effects(crosstalk=300, beam_loss=3), Effects(wet_road=1.0)],
                         ids=["fog", "rain", "snow", "faults", "wet"])
def test_weather_keeps_targets_ids_and_gives_spurious_returns_none(sim: Simulator,
                                                                   fx: Effects) -> None:
    sample = load_space(SMOKE).grid()[0]
    placed, pose = sim.placed_cars(sample), sim.ego_pose(sample.background)
    clear = sim.render(sample.background, placed, pose)
    other = sim.render(sample.background, placed, pose, None, fx, 11)
    check_scan(clear)
    check_scan(other)
    both = clear.valid & other.valid
    same = both & (np.abs(clear.image[..., 4] - other.image[..., 4]) < 1e-4)
    assert same.any()
    assert (other.semantic[same] == clear.semantic[same]).all()        # the target's id
    spurious = other.valid & ~same & (other.label == 0) & (other.instance == 0)
    if fx.fog or fx.crosstalk or fx.snow:
        assert (other.semantic[spurious] == 0).any()
    moved = other.valid & ~same
    assert (other.semantic[moved] == 0).all() or fx.wet_road   # only spurious returns move


# -- files --------------------------------------------------------------------------------------
def test_kitti_files_round_trip_semantic_ids(sim: Simulator, tmp_path: Path) -> None:
    sample = load_space(SMOKE).grid()[1]
    scan = sim.scan(sample, rng=np.random.default_rng(0))
    write_kitti(scan, tmp_path / "a.bin", tmp_path / "a.label")
    sem, inst = split_label(np.fromfile(tmp_path / "a.label", np.uint32))
    assert (sem == scan.semantic[scan.valid]).all()
    assert (inst == scan.instance[scan.valid]).all()
    back = read_kitti(tmp_path / "a.bin", tmp_path / "a.label", sim.sensor)
    check_scan(back)
    # every point read back carries the id written with it (points matched by their bytes)
    pts = np.fromfile(tmp_path / "a.bin", np.float32).reshape(-1, 4)[:, :3]
    written = {p.tobytes(): int(s) for p, s in zip(pts, sem, strict=True)}
    got = back.image[back.valid][:, :3].astype(np.float32)
    assert [written[p.tobytes()] for p in got] == back.semantic[back.valid].tolist()
    assert read_kitti(tmp_path / "a.bin", None, sim.sensor).semantic is None


def test_scans_without_ids_write_todays_labels(sim: Simulator, tmp_path: Path) -> None:
    scan = sim.scan(load_space(SMOKE).grid()[0])
    plain = Scan(scan.image, scan.instance)
    write_kitti(plain, tmp_path / "p.bin", tmp_path / "p.label")
    m = scan.valid
    want = ((scan.instance[m].astype(np.uint32) & 0xFFFF) << 16) | TO_SEMANTICKITTI[
        scan.image[m][:, 5].astype(np.int64)]
    assert (tmp_path / "p.label").read_bytes() == want.astype(np.uint32).tobytes()


# -- dataset --format semantickitti -------------------------------------------------------------
def make_dataset(out: Path, capsys, scans: int = 3) -> dict:
    assert main(["dataset", str(SMOKE), "--scans", str(scans), "--out", str(out), "--max-cars",
                 "4", "--format", "semantickitti", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def read_like_semantickitti(seq: Path, frame: str) -> tuple[np.ndarray, np.ndarray]:
    """What SemanticKITTI's laserscan.py reads: float32 N x 4 and uint32 labels."""
    scan = np.fromfile(seq / "velodyne" / f"{frame}.bin", dtype=np.float32).reshape((-1, 4))
    label = np.fromfile(seq / "labels" / f"{frame}.label", dtype=np.uint32).reshape(-1)
    return scan, label


def parse_matrices(line: str) -> np.ndarray:
    m = np.eye(4)
    m[:3] = np.array([float(v) for v in line.split()]).reshape(3, 4)
    return m


def test_dataset_writes_semantickitti_layout(tmp_path: Path, capsys) -> None:
    summary = make_dataset(tmp_path / "sk", capsys)
    assert summary["format"] == "semantickitti" and summary["written"] == 3
    seq = tmp_path / "sk" / "sequences" / "00"
    assert sorted(p.name for p in (seq / "velodyne").iterdir()) == [
        "000000.bin", "000001.bin", "000002.bin"]
    total, per_sem = 0, {}
    for k in range(3):
        pts, lab = read_like_semantickitti(seq, f"{k:06d}")
        assert len(pts) == len(lab) > 1000
        assert np.isfinite(pts).all() and (np.linalg.norm(pts[:, :3], axis=1) > 0).all()
        sem, inst = lab & 0xFFFF, lab >> 16
        assert set(np.unique(sem).tolist()) <= set(RAW_NAMES)
        assert (inst[sem == RAW_ID["road"]] == 0).all()          # stuff has no instance
        assert (inst[sem == RAW_ID["car"]] > 0).all()
        total += len(lab)
        for s, n in zip(*np.unique(sem, return_counts=True), strict=True):
            per_sem[RAW_NAMES[int(s)]] = per_sem.get(RAW_NAMES[int(s)], 0) + int(n)
    assert total == sum(summary["points_per_class"].values())
    assert per_sem == summary["points_per_semantic"]
    # calib.txt and poses.txt as generate_sequential.py parses them
    calib = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, content = line.strip().split(":")
        calib[key] = parse_matrices(content)
    assert np.allclose(calib["Tr"], VELO_TO_CAM)
    lines = (seq / "poses.txt").read_text().splitlines()
    assert len(lines) == 3
    sim = Simulator(load_sensor(load_space(SMOKE).sensor))
    for k, line in enumerate(lines):
        velo = np.linalg.inv(calib["Tr"]) @ parse_matrices(line) @ calib["Tr"]
        _, pose, _ = scene_for(k, 0, sim, TrafficOptions(max_cars=4))
        assert np.allclose(velo, world_from_sensor(sim.sensor, pose), atol=1e-9)
    # our own loader reads the root as SemanticKITTI: one labelled sequence
    (loaded,) = load_sets([str(tmp_path / "sk")], sim.sensor)
    assert loaded.name == "00" and len(loaded) == 3 and loaded.labelled().all()


def test_dataset_is_deterministic_and_resumes(tmp_path: Path, capsys) -> None:
    make_dataset(tmp_path / "a", capsys)
    make_dataset(tmp_path / "b", capsys)

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
                if p.is_file()}
    a = files(tmp_path / "a")
    assert a == files(tmp_path / "b")
    seq = tmp_path / "b" / "sequences" / "00"
    (seq / "velodyne" / "000001.bin").unlink()
    (seq / "poses.txt").unlink()
    assert make_dataset(tmp_path / "b", capsys)["written"] == 1
    assert files(tmp_path / "b") == a


def test_raw_id_lookups_agree_for_every_integer_type() -> None:
    """The uint16 fast path and the checked path give the same ids; ids no map names (past
    its end, or negative) read as unlabeled / unknown."""
    from falsify.semantic import LEARNING_MAP, train_ids

    raw = np.array([0, 10, 40, 48, 72, 252, 259, 260, 999, 65535], np.int64)
    expected = np.array([LEARNING_MAP[r] if r < len(LEARNING_MAP) else 0 for r in raw])
    for dtype in (np.uint16, np.int64, np.int32, np.uint32):
        assert np.array_equal(train_ids(raw.astype(dtype)), expected), dtype
        assert np.array_equal(kitti4(raw.astype(dtype)),
                              kitti4(raw.astype(np.uint16))), dtype
    assert train_ids(np.array([-1, 40], np.int64)).tolist() == [0, int(LEARNING_MAP[40])]
    assert kitti4(np.array([252], np.uint8)).tolist() == kitti4(np.array([252])).tolist()
