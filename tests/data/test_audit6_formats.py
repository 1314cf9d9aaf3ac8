"""Audit of the data formats against their published specifications, at the extremes: KITTI's
object devkit (label_2, calib), SemanticKITTI's .bin/.label/calib.txt/poses.txt, and the
split manifests `falsify holdout` writes. Synthetic data only (configs/smoke.toml, 1-2 scans)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import falsify.fileio
from falsify.cli import main
from falsify.data.holdout import load_manifest, manifest_text, toml_string
from falsify.data.kitti_frames import label_points
from falsify.data.kitti_object import (
    Box3D,
    format_calib,
    object_label,
    read_calib,
    read_labels,
    read_velodyne,
)
from falsify.data.range_npy import load_scan_npy
from falsify.data.scansets import load_sets
from falsify.data.velodyne import kitti_arrays, label_instances, read_kitti, write_kitti
from falsify.errors import FalsifyError
from falsify.semantic import split_label
from falsify.sensor.calibration import KittiCalib
from falsify.sensor.camera import KITTI_HEIGHT, KITTI_WIDTH, camera_preset
from falsify.sensor.lidar import load_sensor
from falsify.sensor.scan import Scan
from tests.conftest import CONFIGS

SMOKE = CONFIGS / "smoke.toml"


def tiny_scan(instances: list[int]) -> Scan:
    """A 1 x N scan of valid points (class car) with the given instance ids."""
    n = len(instances)
    image = np.zeros((1, n, 6), np.float32)
    image[0, :, 0] = np.arange(1, n + 1)           # x: in front, never the origin
    image[0, :, 3] = 0.5                            # remission
    image[0, :, 4] = np.arange(1, n + 1)            # range > 0: valid
    image[0, :, 5] = 1
    return Scan(image, np.array([instances], np.int32))


# -- SemanticKITTI .label: instance ids beyond 16 bits -----------------------------------------
def test_instances_above_16_bits_are_neither_cut_nor_merged() -> None:
    """An inserted car's instance (65536 + k, real_backgrounds.INSERTED_INSTANCE) was masked to
    its low 16 bits: car 0 became 0 ("no instance") and car 1 merged with real instance 1."""
    ids = [0, 1, 7, 65536, 65537, 65537, 131073, 1]
    _, labels = kitti_arrays(tiny_scan(ids))
    sem, inst = split_label(labels)
    assert (sem == 10).all()                          # the semantic half is untouched
    assert inst[0] == 0 and inst[1] == inst[7] == 1 and inst[2] == 7   # ids that fit stay
    big = inst[3:7]
    assert (big > 7).all() and len(set(big.tolist())) == 3 and big[1] == big[2]
    assert label_instances(np.array([0, 3, 65535])).tolist() == [0, 3, 65535]


def test_write_kitti_is_atomic(tmp_path: Path, monkeypatch) -> None:
    """A write that fails (killed) before its rename leaves neither the file nor a temp file."""
    def fail(*_args) -> None:
        raise OSError("killed")
    monkeypatch.setattr(falsify.fileio.os, "replace", fail)
    with pytest.raises(OSError):
        write_kitti(tiny_scan([0, 1]), tmp_path / "a.bin", tmp_path / "a.label")
    assert list(tmp_path.iterdir()) == []


# -- SemanticKITTI layout written and read back ------------------------------------------------
@pytest.fixture(scope="module")
def semantickitti(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sk") / "sk"
    assert main(["dataset", str(SMOKE), "--scans", "2", "--out", str(out), "--max-cars", "4",
                 "--format", "semantickitti", "--json"]) == 0
    return out


def test_semantickitti_files_follow_the_spec_and_read_back(semantickitti: Path) -> None:
    seq = semantickitti / "sequences" / "00"
    names = sorted(p.name for p in (seq / "velodyne").iterdir())
    assert names == ["000000.bin", "000001.bin"]
    sensor = load_sensor("kitti-hdl64e-front")
    for name in names:
        raw = (seq / "velodyne" / name).read_bytes()
        pts = np.frombuffer(raw, "<f4").reshape(-1, 4)       # little-endian float32 x4
        lab = np.frombuffer((seq / "labels" / name.replace(".bin", ".label")).read_bytes(), "<u4")
        assert len(lab) == len(pts) > 1000
        assert np.isfinite(pts).all() and (np.linalg.norm(pts[:, :3], axis=1) > 0.5).all()
        assert pts[:, 3].min() >= 0 and pts[:, 3].max() <= 1
        back = read_kitti(seq / "velodyne" / name, seq / "labels" / name.replace(".bin", ".label"),
                          sensor)
        m = back.valid
        # every point read back carries the semantic and instance ids written with it
        by_bytes = {p.tobytes(): int(v) for p, v in zip(pts[:, :3], lab, strict=True)}
        got = back.image[m][:, :3].astype(np.float32)
        want = np.array([by_bytes[p.tobytes()] for p in got], np.uint32)
        sem, inst = split_label(want)
        assert (sem == back.semantic[m]).all() and (inst == back.instance[m]).all()
    (loaded,) = load_sets([str(semantickitti)], sensor)
    assert loaded.name == "00" and len(loaded) == 2 and loaded.labelled().all()


def test_semantickitti_calib_holds_p0_to_p3_and_tr(semantickitti: Path) -> None:
    """The odometry devkit's calib.txt (SemanticKITTI's) has P0, P1, P2, P3 and Tr, 12 values
    each; only Tr was written."""
    seq = semantickitti / "sequences" / "00"
    rows = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        rows[key] = np.array([float(v) for v in values.split()])
    assert list(rows) == ["P0", "P1", "P2", "P3", "Tr"]
    assert all(v.size == 12 for v in rows.values())
    assert np.array_equal(rows["P2"].reshape(3, 4), camera_preset("kitti-centre").kitti_calib().P2)
    poses = (seq / "poses.txt").read_text().splitlines()
    assert len(poses) == 2 and all(len(p.split()) == 12 for p in poses)


def test_dataset_twice_gives_the_same_bytes(semantickitti: Path, tmp_path: Path) -> None:
    again = tmp_path / "sk"
    assert main(["dataset", str(SMOKE), "--scans", "2", "--out", str(again), "--max-cars", "4",
                 "--format", "semantickitti", "--json"]) == 0

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
                if p.is_file()}
    assert files(again) == files(semantickitti)


# -- KITTI object calib and labels -------------------------------------------------------------
@pytest.mark.parametrize("camera", ["kitti-centre", "kitti-rig"])
def test_calib_round_trips_bit_for_bit(tmp_path: Path, camera: str) -> None:
    """13 significant digits moved kitti-rig's Tr_velo_to_cam by 5e-14: not a round trip."""
    calib = camera_preset(camera).kitti_calib()
    text = format_calib(calib)
    assert [line.split(":")[0] for line in text.splitlines()] == [
        "P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"]
    (tmp_path / "c.txt").write_text(text)
    back = read_calib(tmp_path / "c.txt")
    for a, b in [*zip(back.P, calib.P, strict=True), (back.R0_rect, calib.R0_rect),
                 (back.Tr_velo_to_cam, calib.Tr_velo_to_cam)]:
        assert np.array_equal(a, b)
    assert format_calib(back) == text


@pytest.fixture(scope="module")
def kitti_object(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ko") / "ko"
    assert main(["dataset", str(SMOKE), "--scans", "2", "--out", str(out), "--max-cars", "6",
                 "--format", "kitti-object", "--json"]) == 0
    return out


def test_kitti_object_labels_follow_the_devkit(kitti_object: Path) -> None:
    calib = camera_preset("kitti-centre").kitti_calib()
    n = 0
    for name in ("000000", "000001"):
        back = read_calib(kitti_object / "calib" / f"{name}.txt")
        assert np.array_equal(back.P2, calib.P2)
        pts = read_velodyne(kitti_object / "velodyne" / f"{name}.bin")
        assert len(pts) > 1000 and pts[:, 3].min() >= 0 and pts[:, 3].max() <= 1
        lines = (kitti_object / "label_2" / f"{name}.txt").read_text().splitlines()
        for line, o in zip(lines, read_labels(kitti_object / "label_2" / f"{name}.txt"),
                           strict=True):
            assert len(line.split()) == 15 and o.type in ("Car", "Pedestrian", "Cyclist")
            assert 0 <= o.truncated <= 1 and o.occluded in (0, 1, 2, 3)
            assert -math.pi <= o.rotation_y <= math.pi and -math.pi <= o.alpha <= math.pi
            # alpha = rotation_y - atan2(x, z), wrapped, to the file's two decimals
            x, _, z = o.location
            want = math.remainder(o.rotation_y - math.atan2(x, z), 2 * math.pi)
            assert abs(math.remainder(o.alpha - want, 2 * math.pi)) <= 0.011, line
            left, top, right, bottom = o.box2d
            assert 0 <= left < right <= KITTI_WIDTH - 1
            assert 0 <= top < bottom <= KITTI_HEIGHT - 1
            assert o.has_3d and z > 0
            n += 1
    assert n > 5


def test_kitti_object_frames_with_a_van_truck_or_bus_in_view_are_written(tmp_path: Path) -> None:
    """Before: a frame whose camera saw a placed delivery van, box truck or bus (class 0)
    stopped the export with a KeyError traceback, exit 1, on smoke's third frame. Such vehicles
    stay unlabelled, as the streets' own are; every frame is written."""
    out = tmp_path / "ko"
    assert main(["dataset", str(SMOKE), "--scans", "3", "--out", str(out),
                 "--format", "kitti-object"]) == 0
    for sub, ext in (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt"),
                     ("image_2", "png")):
        assert sorted(p.name for p in (out / sub).iterdir()) == [
            f"00000{k}.{ext}" for k in range(3)]
    types = {o.type for k in range(3) for o in read_labels(out / "label_2" / f"00000{k}.txt")}
    assert types <= {"Car", "Pedestrian", "Cyclist"} and "Car" in types


# -- split manifests ---------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["a\U0001F600.bin", "del\x7f.bin", 'q"uote\\.bin'])
def test_holdout_manifest_reads_back_any_file_name(tmp_path: Path, capsys, name: str) -> None:
    """json.dumps wrote U+1F600 as a surrogate pair, invalid TOML: the manifest `falsify
    holdout` had just written failed to load (exit 2) and stayed on disk."""
    folder = tmp_path / "scans"
    folder.mkdir()
    (folder / name).write_bytes(np.arange(8, dtype=np.float32).tobytes())
    out = tmp_path / "splits.toml"
    assert main(["holdout", str(folder), "--out", str(out), "--json"]) == 0
    held = load_manifest(out)
    assert [s.name for s in held.scans] == [f"scans/{name}"]
    assert held.held_out([folder / name]) == [folder / name]


def test_toml_string_and_note_are_valid_toml() -> None:
    """A --note with a control character made the manifest's comment invalid TOML."""
    for text, want in [("plain", "plain"), ("tab\there", "tab\there"), ("c\x01\x1f", "c\x01\x1f"),
                       ("bad\udcff", "bad\ufffd"), ("\udcf0\udc9f\udc98\udc80", "\U0001F600"),
                       ("\\\"", "\\\""), ("", "")]:
        assert tomllib.loads(f"n = {toml_string(text)}")["n"] == want
    assert tomllib.loads(manifest_text([], "a\x01b\nc")) == {"holdout": {}}


# -- KITTI object frames: what the camera sees -------------------------------------------------
def test_the_image_spans_half_a_pixel_beyond_the_edge_centres() -> None:
    """KITTI's P2 puts pixel centres on integers: a 1242-pixel image spans u in [-0.5, 1241.5].
    label_points took [0, 1242]: it ignored points on the first column's outer half and counted
    points half a pixel past the last column as seen."""
    p2 = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    axes = KittiCalib((p2,) * 4, np.eye(3),
                      np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]]))
    x = 10.0

    def at(u: float, v: float) -> list[float]:
        return [x, -(u - 600) * x / 700, -(v - 180) * x / 700]
    pts = np.array([at(-0.25, 100), at(1241.25, 100), at(1241.75, 100), at(600, 374.75),
                    at(600, -0.75)])
    cls = label_points(pts, [], axes, (1242, 375))
    assert cls.tolist() == [0, 0, 255, 255, 255]


# -- falsify dataset: options a format does not use, and resumes that differ -------------------
@pytest.mark.parametrize(("extra", "said"), [
    (["--workers", "2"], "--workers 2: only --format npy"),
    (["--labels", "semantickitti"], "--labels semantickitti: only --format npy"),
])
def test_kitti_object_refuses_options_it_would_ignore(tmp_path: Path, capsys, extra: list[str],
                                                      said: str) -> None:
    """--workers and --labels were silently ignored with --format kitti-object (exit 0)."""
    out = tmp_path / "ko"
    assert main(["dataset", str(SMOKE), "--scans", "1", "--out", str(out), "--format",
                 "kitti-object", *extra]) == 2
    assert said in capsys.readouterr().err and not out.exists()


def test_kitti_object_resume_with_other_traffic_is_refused(tmp_path: Path, capsys) -> None:
    """index.json left out the traffic, world and sensor noise: a resume with --traffic drive
    added drive frames to a scattered set and exited 0."""
    out = tmp_path / "ko"
    base = ["dataset", str(SMOKE), "--out", str(out), "--format", "kitti-object", "--max-cars",
            "2", "--first-background", "1000", "--backgrounds", "1"]
    assert main([*base, "--scans", "1", "--json"]) == 0
    index = json.loads((out / "index.json").read_text())
    assert index["ray_drop"] >= 0 and index["range_noise"] == 0.02 and "traffic" not in index
    capsys.readouterr()
    for extra, said in ((["--traffic", "drive"], "traffic (--traffic)"),
                        (["--range-noise", "0.05"], "range_noise (--range-noise)")):
        assert main([*base, "--scans", "2", *extra]) == 2
        assert said in capsys.readouterr().err
    assert sorted(p.name for p in (out / "velodyne").iterdir()) == ["000000.bin"]


def test_kitti_object_frame_is_the_semantickitti_scan_with_a_world(tmp_path: Path,
                                                                   capsys) -> None:
    """With --world the kitti-object export built its streets without the profile (parked cars
    not thinned), so frame 0 was not the npy / semantickitti set's scan 0."""
    world = CONFIGS / "worlds" / "semantickitti-fit-parked.json"
    for fmt in ("kitti-object", "semantickitti"):
        assert main(["dataset", str(SMOKE), "--scans", "1", "--out", str(tmp_path / fmt),
                     "--format", fmt, "--world", str(world), "--json"]) == 0
    ko = (tmp_path / "kitti-object" / "velodyne" / "000000.bin").read_bytes()
    sk = tmp_path / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin"
    assert ko == sk.read_bytes()
    index = json.loads((tmp_path / "kitti-object" / "index.json").read_text())
    assert index["world"] == "semantickitti-fit-parked"


def test_holdout_manifest_is_utf8_in_an_ascii_locale(tmp_path: Path) -> None:
    """Written as UTF-8 but read back in the locale's encoding: under LC_ALL=POSIX `falsify
    holdout` could not read the manifest it had just written for a non-ASCII file name."""
    folder = tmp_path / "scans"
    folder.mkdir()
    (folder / "a\U0001F600.bin").write_bytes(np.arange(8, dtype=np.float32).tobytes())
    env = {**os.environ, "LC_ALL": "POSIX", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    proc = subprocess.run([sys.executable, "-m", "falsify", "holdout", str(folder), "--out",
                           str(tmp_path / "splits.toml")], env=env, capture_output=True)
    assert proc.returncode == 0, proc.stderr
    assert [s.name for s in load_manifest(tmp_path / "splits.toml").scans] == [
        "scans/a\U0001F600.bin"]


@pytest.mark.parametrize("scans", ["0", "-3", "1000001"])
def test_scan_counts_outside_six_digit_names_exit_2(tmp_path: Path, capsys, scans: str) -> None:
    """Names are 6 digits (000000.bin): --scans 1000001 wrote 1000000.bin, which sorts before
    100001.bin, out of index and poses.txt order."""
    out = tmp_path / "sk"
    assert main(["dataset", str(SMOKE), "--scans", scans, "--out", str(out), "--format",
                 "semantickitti"]) == 2
    assert "--scans" in capsys.readouterr().err and not out.exists()


# -- .npy range images -------------------------------------------------------------------------
def test_a_npz_or_text_named_npy_is_refused_naming_the_file(tmp_path: Path) -> None:
    """np.load took a .npz saved as x.npy and the reader failed with AttributeError ('NpzFile'
    object has no attribute 'ndim'); a text file was said to hold pickled data."""
    with open(tmp_path / "z.npy", "wb") as fh:
        np.savez(fh, a=np.zeros((2, 3, 6), np.float32))
    (tmp_path / "t.npy").write_text("x, y, z\n")
    for name in ("z.npy", "t.npy"):
        with pytest.raises(FalsifyError, match=f"{name}: not a .npy file"):
            load_scan_npy(tmp_path / name)
    np.save(tmp_path / "ok.npy", np.zeros((2, 3, 6), np.float32))
    assert load_scan_npy(tmp_path / "ok.npy").shape == (2, 3, 6)


def test_2d_boxes_stay_within_the_image_pixel_indices() -> None:
    """A box touching the image border was written as -0.50 .. 1241.50 (x) and 374.50 (y):
    outside the devkit's 0-based pixel indices, where KITTI's own labels stop (0.00, 1241.00,
    374.00)."""
    calib = camera_preset("kitti-centre").kitti_calib()
    box = Box3D(1, 1, np.array([4.0, 0.0, -1.7]), 4.0, 1.8, 1.5, 0.0)
    w, h = KITTI_WIDTH, KITTI_HEIGHT
    edge = object_label(box, calib, (0, 0, w - 1, h - 1), 10, 10, (w, h))
    assert edge.box2d == (0.0, 0.0, w - 1.0, h - 1.0)
    inside = object_label(box, calib, (100, 50, 200, 150), 10, 10, (w, h))
    assert inside.box2d == (99.5, 49.5, 200.5, 150.5)
