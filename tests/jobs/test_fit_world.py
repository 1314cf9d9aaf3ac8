"""fit-world: the road plane, cars in view and the profile a world draws from, on constructed
scans with known answers, the refusal of evaluation data, and the profile in `dataset`."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.errors import ConfigError, FalsifyError
from falsify.jobs.fit_world import (
    check_fit_data,
    describe,
    ground_plane,
    scene_stats,
    summarise,
    wasserstein_1d,
)
from falsify.paths import CONFIGS
from falsify.semantic import RAW_ID, join_label
from falsify.world.profile import WorldProfile, load_profile
from tests.conftest import HOLDOUT, KITTI_DIR

MINI = KITTI_DIR / "semantickitti-mini"
FIT_SEQUENCES = "01,02,04,05,07,09,10"


def _plane_scan(pitch_deg: float, roll_deg: float, height: float, rng_seed: int = 0,
                cars: tuple[tuple[float, float, int], ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Road points on z = tan(pitch) x + tan(roll) y - h' (h' so the sensor stands `height`
    above the plane), kerb-top outliers, and car blobs (x, y, points) as instances 1, 2, ..."""
    rng = np.random.default_rng(rng_seed)
    a, b = math.tan(math.radians(pitch_deg)), math.tan(math.radians(roll_deg))
    c = -height * math.sqrt(1 + a * a + b * b)
    x = rng.uniform(2, 29, 4000)
    y = rng.uniform(-1, 1, 4000) * x * 0.95
    z = a * x + b * y + c
    pts = [np.stack([x, y, z], 1)]
    sem = [np.full(len(x), RAW_ID["road"])]
    inst = [np.zeros(len(x), np.uint16)]
    kx = np.linspace(5, 25, 60)
    kerb = np.stack([kx, np.full(60, 4.0), a * kx + b * 4.0 + c + 0.4], 1)
    pts.append(kerb)  # 60 road-labelled points 0.4 m above the road: left out by the refit
    sem.append(np.full(60, RAW_ID["road"]))
    inst.append(np.zeros(60, np.uint16))
    for k, (cx, cy, n) in enumerate(cars, start=1):
        pts.append(np.stack([cx + rng.normal(0, 0.5, n), cy + rng.normal(0, 0.5, n),
                             np.full(n, c + 0.8)], 1))
        sem.append(np.full(n, RAW_ID["car"]))
        inst.append(np.full(n, k, np.uint16))
    p = np.concatenate(pts)
    points = np.concatenate([p, np.zeros((len(p), 1))], 1).astype(np.float32)
    labels = join_label(np.concatenate(sem).astype(np.uint32),
                        np.concatenate(inst).astype(np.uint32)).astype(np.uint32)
    return points, labels


def test_ground_plane_is_exact_on_a_plane_with_outliers():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 30, 500), rng.uniform(-10, 10, 500)
    z = 0.03 * x - 0.02 * y - 1.8
    z[:20] += 0.5   # kerb tops
    a, b, c, res = ground_plane(x, y, z)
    assert (a, b, c) == pytest.approx((0.03, -0.02, -1.8), abs=1e-9)
    assert res < 1e-9


@pytest.mark.parametrize("pitch,roll,height", [(2.0, 0.0, 1.73), (-1.5, 1.0, 1.9),
                                               (0.0, -2.0, 1.6)])
def test_scene_stats_recover_the_pose_and_count_cars(pitch, roll, height):
    cars = ((10.0, 2.0, 40), (20.0, -5.0, 25), (15.0, 0.0, 10),   # the last is too small
            (70.0, 0.0, 50))                                       # beyond CAR_RANGE
    points, labels = _plane_scan(pitch, roll, height, cars=cars)
    # a car behind the sensor is out of the front 90 degrees
    back = np.array([[-10.0, 0.0, -1.0, 0.0]] * 30, np.float32)
    points = np.concatenate([points, back])
    labels = np.concatenate([labels, join_label(np.full(30, RAW_ID["car"], np.uint32),
                                                np.full(30, 9, np.uint32)).astype(np.uint32)])
    s = scene_stats("constructed", points, labels)
    # exact up to the float32 of a .bin: 1e-4 degrees, 0.1 mm
    assert s.pitch_deg == pytest.approx(pitch, abs=1e-4)
    assert s.roll_deg == pytest.approx(roll, abs=1e-4)
    assert s.height_m == pytest.approx(height, abs=1e-4)
    assert s.roughness_m < 1e-5
    assert s.cars_front == 2
    assert 0 < s.car_share < 0.05 and s.green_share == 0.0


def test_a_scan_without_road_is_named():
    points = np.zeros((10, 4), np.float32)
    points[:, 0] = 5.0
    with pytest.raises(FalsifyError, match="seq/000001: 0 road points"):
        scene_stats("seq/000001", points, np.zeros(10, np.uint32))


def test_wasserstein_of_a_shift_is_the_shift_and_matches_its_definition():
    rng = np.random.default_rng(2)
    a = rng.normal(0, 1, 300)
    assert wasserstein_1d(a, a + 0.7) == pytest.approx(0.7, abs=1e-9)
    assert wasserstein_1d(a, a) == 0.0
    # unequal sizes: the integral of |F_a - F_b| on a fine grid
    b = rng.normal(0.3, 2.0, 117)
    grid = np.linspace(-10, 10, 200_001)
    fa = np.searchsorted(np.sort(a), grid, side="right") / len(a)
    fb = np.searchsorted(np.sort(b), grid, side="right") / len(b)
    assert wasserstein_1d(a, b) == pytest.approx(np.trapezoid(np.abs(fa - fb), grid), abs=1e-3)


def _write_sequence(root: Path, seq: str, scans: list[tuple[np.ndarray, np.ndarray]],
                    labelled: bool = True) -> Path:
    folder = root / "sequences" / seq
    (folder / "velodyne").mkdir(parents=True)
    (folder / "labels").mkdir()
    for i, (points, labels) in enumerate(scans):
        points.tofile(folder / "velodyne" / f"{i:06d}.bin")
        if labelled:
            labels.tofile(folder / "labels" / f"{i:06d}.label")
    return folder


def test_a_semantickitti_roots_official_split_is_held_out_unless_its_manifest_says(tmp_path):
    """Without a manifest a SemanticKITTI root holds out 08 (and 11-21); a splits.toml beside the
    data replaces that rule with its own."""
    root = tmp_path / "sk"
    _write_sequence(root, "08", [_plane_scan(1.0, 0.0, 1.73)])
    _write_sequence(root, "05", [_plane_scan(2.0, 0.0, 1.73)])
    check_fit_data([str(root)], ["05"])   # a training sequence: fine
    with pytest.raises(FalsifyError, match=r"08/velodyne/000000\.bin: a held-out scan "
                                           r"\(SemanticKITTI's official split"):
        check_fit_data([str(root)], None)
    (root / "splits.toml").write_text('[holdout]\nsequences = ["05"]\n')
    check_fit_data([str(root)], ["08"])   # the manifest's own split: 08 is fit data here
    with pytest.raises(FalsifyError, match=r"05/velodyne/000000\.bin: a held-out scan \("
                                           + str(root / "splits.toml")):
        check_fit_data([str(root)], ["05"])


def _copy_sequence(src: Path, dst: Path, link: bool = False) -> None:
    """A sequence's first scan and its labels under dst (a copy, or symlinks)."""
    for sub, name in (("velodyne", "000000.bin"), ("labels", "000000.label")):
        (dst / sub).mkdir(parents=True, exist_ok=True)
        if link:
            (dst / sub / name).symlink_to(src / sub / name)
        else:
            shutil.copyfile(src / sub / name, dst / sub / name)


@pytest.mark.skipif(not (MINI / "sequences" / "00").is_dir(),
                    reason=f"{MINI}: SemanticKITTI mini set not present")
@pytest.mark.parametrize("link", [False, True], ids=["copy", "symlink"])
def test_cli_refuses_a_held_out_scan_through_a_copy_or_a_symlink(tmp_path, capsys, link,
                                                                 monkeypatch):
    """The project's manifest holds out sequence 00 by content: its scan copied (or linked) into
    another root as sequence 05 is refused by name, with the manifest and the original named,
    and nothing is written (also without FALSIFY_HOLDOUT: --holdout alone)."""
    monkeypatch.delenv("FALSIFY_HOLDOUT", raising=False)
    _copy_sequence(MINI / "sequences" / "00", tmp_path / "elsewhere" / "sequences" / "05", link)
    out = tmp_path / "sub" / "profile.json"
    rc = main(["fit-world", str(tmp_path / "elsewhere"), "--holdout", str(HOLDOUT),
               "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "05/velodyne/000000.bin: a held-out scan" in err and str(HOLDOUT) in err
    assert "the same bytes as semantickitti" in err   # the original, as the manifest names it
    assert not out.exists() and not out.parent.exists()


@pytest.mark.skipif(not (MINI / "sequences" / "08").is_dir(),
                    reason=f"{MINI}: SemanticKITTI mini set not present")
def test_cli_refuses_the_real_evaluation_split_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "sub" / "profile.json"
    rc = main(["fit-world", str(MINI), "--sequences", "05,03", "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "03/velodyne/000000.bin: a held-out scan" in err
    assert not out.exists() and not out.parent.exists()


def test_cli_refuses_a_scan_given_twice_by_path_or_by_content(tmp_path, capsys):
    """A fit would weigh a repeated scan double: the same folder twice, or a byte-identical copy
    in another sequence, exits 2 naming both, and nothing is written."""
    a = _write_sequence(tmp_path / "r", "05", [_plane_scan(1.0, 0.0, 1.73, s) for s in (0, 1)])
    out = tmp_path / "profile.json"
    assert main(["fit-world", str(a), str(a), "--out", str(out)]) == 2
    assert "000000.bin: given twice; fit-world's scans take each scan once" in \
        capsys.readouterr().err
    b = _write_sequence(tmp_path / "r", "07", [_plane_scan(2.0, 0.0, 1.73, 5)])
    shutil.copyfile(a / "velodyne" / "000001.bin", b / "velodyne" / "000001.bin")
    shutil.copyfile(a / "labels" / "000001.label", b / "labels" / "000001.label")
    assert main(["fit-world", str(tmp_path / "r"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"07/velodyne/000001.bin: the same bytes as {a / 'velodyne' / '000001.bin'}" in err
    assert not out.exists()


def test_a_scan_without_labels_is_named(tmp_path):
    _write_sequence(tmp_path, "05", [_plane_scan(1.0, 0.0, 1.73)], labelled=False)
    with pytest.raises(FalsifyError, match=r"000000\.bin: no SemanticKITTI \.label"):
        describe([str(tmp_path)])


@pytest.mark.skipif(not (MINI / "sequences" / "05").is_dir(),
                    reason=f"{MINI}: SemanticKITTI mini set not present")
def test_the_fit_split_shows_pitch_our_world_lacks(tmp_path, capsys):
    out = tmp_path / "profile.json"
    rc = main(["fit-world", str(MINI), "--sequences", FIT_SEQUENCES, "--out", str(out),
               "--base-scans", "3", "--parked-keep", "1", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    profile = load_profile(out)
    assert len(profile.scans) == 21 and profile.scans[0] == "01/000000"
    assert doc["fit"]["scans"] == 21 and doc["world"]["scans"] == 3
    # the real places' road pitch spreads over degrees; the world's own over tenths
    fit, world = doc["fit"]["pitch_deg"], doc["world"]["pitch_deg"]
    assert fit["p95"] - fit["p5"] > 2.0 > 0.5 > world["p95"] - world["p5"]
    assert 1.6 < doc["fit"]["height_m"]["p50"] < 1.85
    # each fit scan's place travels in the profile; the real places hold vegetation 15-30 m
    # out and unlabeled clutter 30-60 m out that the streets as built lack
    assert [p.name for p in profile.places] == list(profile.scans)
    places, world = doc["places_fit"], doc["places_world"]
    assert places["vegetation 15-30 m"]["p50"] > world["vegetation 15-30 m"]["p50"]
    assert places["unlabeled 30-60 m"]["p50"] > 0.05 > world["unlabeled 30-60 m"]["p50"]
    assert world["unlabeled 30-60 m"]["w1"] > 0.05
    # What the shipped places profile measured on the real scans is what fit-world measures
    # today (its base and parked share are measured on the world: docs/world.md).
    shipped = load_profile(CONFIGS / "worlds" / "semantickitti-places.json")
    for key in ("scans", "pitch_deg", "height_m", "cars_front", "pitch_jitter_deg",
                "height_jitter_m", "places"):
        assert getattr(profile, key) == getattr(shipped, key), key


def _profile(tmp_path: Path, **over) -> Path:
    doc = {"version": 1, "name": "test", "scans": ["a/000000"], "pitch_deg": [2.5],
           "height_m": [1.95], "cars_front": [1], "base_pitch_deg": 0.0, "base_height_m": 1.73,
           "pitch_jitter_deg": 0.0, "height_jitter_m": 0.0, **over}
    path = tmp_path / "profile.json"
    path.write_text(json.dumps(doc))
    return path


def test_a_profiled_world_shows_the_profiles_pose(tmp_path):
    out = tmp_path / "set"
    rc = main(["dataset", "configs/paper.toml", "--scans", "4", "--seed", "3",
               "--first-background", "1000", "--backgrounds", "625", "--format",
               "semantickitti", "--world", str(_profile(tmp_path)), "--out", str(out), "--json"])
    assert rc == 0
    stats = describe([str(out)])
    summary = summarise(stats)
    # the world's own pitch spreads over about +-0.2 degrees and its height over +-0.03 m
    assert summary["pitch_deg"]["p50"] == pytest.approx(2.5, abs=0.35)
    assert summary["height_m"]["p50"] == pytest.approx(1.95, abs=0.06)
    assert all(s.cars_front <= 1 + 6 for s in stats)   # one placed car, the street's parked
    assert json.loads((out / "index.json").read_text())["world"] == "test"


def test_a_profiled_dataset_is_deterministic_and_a_plain_one_unchanged(tmp_path):
    prof = _profile(tmp_path, pitch_jitter_deg=0.3, height_jitter_m=0.02,
                    scans=["a", "b"], pitch_deg=[1.0, -1.0], height_m=[1.7, 1.8],
                    cars_front=[0, 3])
    base = ["dataset", "configs/paper.toml", "--scans", "3", "--seed", "4",
            "--first-background", "1000", "--backgrounds", "625"]
    for name in ("a", "b"):
        assert main([*base, "--world", str(prof), "--out", str(tmp_path / name), "--json"]) == 0
    assert main([*base, "--out", str(tmp_path / "plain"), "--json"]) == 0
    for i in range(3):
        f = f"{i:06d}.npy"
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
        assert (tmp_path / "a" / f).read_bytes() != (tmp_path / "plain" / f).read_bytes()
    assert "world" not in json.loads((tmp_path / "plain" / "index.json").read_text())


@pytest.mark.parametrize("over,needle", [
    ({"pitch_deg": [1.0, 2.0]}, "pitch_deg has 2 values for 1 scans"),
    ({"height_m": [float("nan")]}, "finite"),
    ({"pitch_deg": [40.0]}, "within ±15 degrees"),
    ({"colour": "red"}, "unknown key 'colour'"),
    ({"version": 7}, "not a world profile of version 1"),
    ({"cars_front": [-1]}, "cars_front must be in 0..40"),
    ({"parked_keep": 1.5}, "parked_keep must be a number in 0..1"),
    ({"parked_keep": "most"}, "parked_keep must be a number in 0..1"),
])
def test_bad_profiles_exit_2_naming_the_file_and_key(tmp_path, capsys, over, needle):
    prof = _profile(tmp_path, **over)
    out = tmp_path / "never"
    rc = main(["dataset", "configs/paper.toml", "--scans", "2", "--world", str(prof),
               "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert str(prof) in err and needle in err
    assert not out.exists()


def test_missing_profile_and_drive_traffic_are_refused(tmp_path, capsys):
    assert main(["dataset", "configs/paper.toml", "--scans", "2", "--world",
                 str(tmp_path / "nope.json"), "--out", str(tmp_path / "o")]) == 2
    assert "nope.json: no such file" in capsys.readouterr().err
    assert main(["dataset", "configs/paper.toml", "--scans", "2", "--world",
                 str(_profile(tmp_path)), "--traffic", "drive", "--out",
                 str(tmp_path / "o")]) == 2
    assert "--traffic drive" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_profile_draws_are_seeded_and_bounded():
    p = WorldProfile("t", ("a", "b"), (1.0, -1.0), (1.7, 1.9), (0, 5), base_pitch_deg=0.5,
                     base_height_m=1.73, pitch_jitter_deg=0.0, height_jitter_m=0.0)
    draws = {tuple(round(v, 6) for v in p.draw_pose(np.random.default_rng(s)))
             for s in range(40)}
    assert draws == {(0.5, -0.03), (-1.5, 0.17)}   # each fit scan's, less the base
    assert p.draw_pose(np.random.default_rng(5)) == p.draw_pose(np.random.default_rng(5))
    assert max(p.draw_cars(np.random.default_rng(s), 3) for s in range(40)) == 3
    with pytest.raises(ConfigError, match="no scans"):
        WorldProfile("t", (), (), (), ())


def test_silverman_bandwidth_follows_its_formula():
    from falsify.jobs.fit_world import silverman_bandwidth

    v = np.random.default_rng(3).normal(0.0, 2.0, 500)
    iqr = np.subtract(*np.percentile(v, [75, 25]))
    expected = 0.9 * min(v.std(ddof=1), iqr / 1.34) * 500 ** -0.2
    assert silverman_bandwidth(v) == pytest.approx(expected, rel=1e-12)
    assert silverman_bandwidth(np.full(5, 1.7)) == 0.0   # no spread: no jitter


def test_fit_world_options_are_checked_before_anything_runs(tmp_path, capsys):
    out = tmp_path / "sub" / "profile.json"
    _write_sequence(tmp_path / "root", "05", [_plane_scan(1.0, 0.0, 1.73)])
    root = str(tmp_path / "root")
    for argv, needle in ((["--base-scans", "0"], "--base-scans: 0 must be in 1..10000"),
                         (["--compare", str(tmp_path / "nope")], "nope: no such file"),
                         (["--sequences", "99"], "--sequences 99"),
                         (["--parked-keep", "1,1.5"], "--parked-keep: '1,1.5'"),
                         (["--parked-keep", "half"], "--parked-keep: 'half'")):
        assert main(["fit-world", root, "--out", str(out), *argv]) == 2
        assert needle in capsys.readouterr().err
        assert not out.parent.exists()


def test_thinning_drops_whole_parked_cars_nested_and_fixed_per_street():
    from falsify.classes import CAR
    from falsify.world.streets import build_background, thin_parked_cars

    bg = build_background(1003)
    assert thin_parked_cars(bg, 1.0) is bg
    cars = set(np.unique(bg.face_instance[bg.face_class == CAR]).tolist())
    assert len(cars) >= 10
    kept = {}
    for keep in (0.0, 0.25, 0.5):
        b = thin_parked_cars(bg, keep)
        left = set(np.unique(b.face_instance[b.face_class == CAR]).tolist())
        kept[keep] = left
        gone = cars - left
        # a dropped car loses every face and its footprint; a kept one keeps all of its faces
        assert not np.isin(b.face_instance, list(gone)).any()
        for i in left:
            assert (b.face_instance == i).sum() == (bg.face_instance == i).sum()
        assert {o.instance for o in b.obstacles} & gone == set()
        assert len(b.obstacles) == len(bg.obstacles) - len(gone)
        # everything that is not a parked car stays, face for face
        other = bg.face_class != CAR
        assert (b.face_class != CAR).sum() == other.sum()
        assert np.array_equal(b.faces[b.face_class != CAR], bg.faces[other])
        assert thin_parked_cars(bg, keep).faces.tobytes() == b.faces.tobytes()
    assert kept[0.0] == set() and kept[0.25] <= kept[0.5] < cars
    with pytest.raises(ConfigError, match="parked_keep: 1.2 is not in 0..1"):
        thin_parked_cars(bg, 1.2)


def test_a_profile_without_parked_cars_shows_only_its_placed_ones(tmp_path):
    base = ["dataset", "configs/paper.toml", "--scans", "3", "--seed", "5",
            "--first-background", "1000", "--backgrounds", "625", "--format", "semantickitti"]
    for keep, name in ((0.0, "none"), (1.0, "all")):
        (tmp_path / name).mkdir()
        prof = _profile(tmp_path / name, cars_front=[0], parked_keep=keep)
        assert main([*base, "--world", str(prof), "--out", str(tmp_path / name / "set"),
                     "--json"]) == 0
    bare = describe([str(tmp_path / "none" / "set")])
    full = describe([str(tmp_path / "all" / "set")])
    # no car placed and no parked car kept: not one car point; the streets as built show some
    assert all(s.car_share == 0.0 for s in bare)
    assert sum(s.cars_front for s in full) > 0
    (tmp_path / "default").mkdir()
    assert load_profile(_profile(tmp_path / "default")).parked_keep == 1.0


def test_fit_world_keeps_the_parked_share_nearest_the_fit_scans(tmp_path, capsys):
    from falsify.jobs.fit_world import parked_score

    # fit scans with no car at all: the fit must drop every parked car it may
    _write_sequence(tmp_path / "root", "05", [_plane_scan(0.5, 0.0, 1.73, rng_seed=k)
                                              for k in range(3)])
    out = tmp_path / "profile.json"
    rc = main(["fit-world", str(tmp_path / "root"), "--out", str(out), "--base-scans", "2",
               "--parked-keep", "1,0", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    tries = {t["keep"]: t for t in doc["parked_keep_tries"]}
    assert set(tries) == {0.0, 1.0}
    assert tries[0.0]["score"] < tries[1.0]["score"]
    assert tries[0.0]["cars_front_mean"] < tries[1.0]["cars_front_mean"]
    assert load_profile(out).parked_keep == 0.0
    assert doc["profiled_world"]["scans"] == 2
    none = [scene_stats("a", *_plane_scan(0.0, 0.0, 1.7))]
    assert parked_score(none, none) == 0.0
