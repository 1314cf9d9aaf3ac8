"""The paper's calibration formula against the pinhole projection, KITTI calib files, and the
`calib` check on real KITTI object frames."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.kitti_object import format_calib, read_calib
from falsify.errors import FalsifyError
from falsify.jobs.calib import check_kitti_dir
from falsify.paths import CONFIGS
from falsify.sensor.calibration import (
    Extrinsic,
    KittiCalib,
    Pinhole,
    paper_angles,
    paper_pixel,
    project_points,
)
from falsify.sensor.camera import KITTI_P2, KITTI_R0_RECT, KITTI_TR_VELO_TO_CAM, camera_preset


def _points_in_view(intr: Pinhole, n: int, rng, near=0.5, far=200.0, margin=0.0):
    """LiDAR-frame points whose pinhole projection spreads over the whole image."""
    u = rng.uniform(margin, intr.width - margin, n)
    v = rng.uniform(margin, intr.height - margin, n)
    depth = np.exp(rng.uniform(np.log(near), np.log(far), n))
    x_cam = (u - intr.cx) / intr.fx * depth
    y_cam = (v - intr.cy) / intr.fy * depth
    return np.stack([depth, -x_cam, -y_cam], axis=1)  # optical (x right, y down) to LiDAR


@pytest.mark.parametrize("intr", [
    camera_preset("kitti-centre").intrinsics,
    Pinhole(640, 480, 100.0, 100.0, 320.0, 240.0),  # 145 x 135 degrees: far from the axis
    Pinhole(64, 2000, 5000.0, 5000.0, 32.0, 1000.0),  # narrow, tall
])
def test_paper_formula_matches_pinhole_to_a_micro_pixel(intr):
    rng = np.random.default_rng(0)
    pts = _points_in_view(intr, 20000, rng)
    # The image's corners and centre lines exactly, near and very far.
    corners = np.array([[0.0, 0.0], [intr.width, 0], [0, intr.height], [intr.width, intr.height],
                        [intr.cx, 0], [0, intr.cy], [intr.cx, intr.cy]])
    for depth in (1e-3, 1.0, 1e5):
        x = (corners[:, 0] - intr.cx) / intr.fx * depth
        y = (corners[:, 1] - intr.cy) / intr.fy * depth
        pts = np.concatenate([pts, np.stack([np.full(len(x), depth), -x, -y], 1)])
    u, v, _ = project_points(pts, intr, Extrinsic.shared_centre())
    phi, theta = paper_angles(pts)
    i, j = paper_pixel(phi, theta, intr.paper_setup(f=0.0042))
    assert np.abs(i - u).max() < 1e-6 and np.abs(j - v).max() < 1e-6
    # The focal distance's unit does not matter: only ratios enter the formula.
    i2, j2 = paper_pixel(phi, theta, intr.paper_setup(f=35.0))
    assert np.abs(i2 - i).max() < 1e-6 and np.abs(j2 - j).max() < 1e-6


def test_lidar_azimuth_and_elevation_are_not_the_papers_angles():
    """Plugging the LiDAR's own azimuth and elevation into the formula is right only on the
    centre lines: off them it misses by pixels, so the angles must be the ones documented."""
    intr = camera_preset("kitti-centre").intrinsics
    p = np.array([[10.0, 5.0, -3.0]])  # right of the axis and below it
    u, v, _ = project_points(p, intr, Extrinsic.shared_centre())
    az = math.atan2(p[0, 1], p[0, 0])
    el = math.atan2(p[0, 2], math.hypot(p[0, 0], p[0, 1]))
    i, j = paper_pixel(np.array([az]), np.array([-el]), intr.paper_setup())
    assert abs(j[0] - v[0]) > 10.0
    phi, theta = paper_angles(p)
    i, j = paper_pixel(phi, theta, intr.paper_setup())
    assert abs(i[0] - u[0]) < 1e-9 and abs(j[0] - v[0]) < 1e-9


def test_paper_setup_needs_a_centred_square_camera():
    with pytest.raises(ValueError, match="centred principal point"):
        camera_preset("kitti-rig").intrinsics.paper_setup()


def test_points_behind_or_on_the_camera_plane_have_no_pixel():
    cam = camera_preset("kitti-centre")
    pts = np.array([[-5.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1e-9, 0.0, 0.0], [1e-300, 1.0, 1.0],
                    [5.0, 0.0, 0.0]])
    col, row, inside = cam.project(pts)
    assert inside.tolist() == [False, False, False, False, True]
    assert (col[4], row[4]) == (621, 187)


def test_rig_preset_is_kittis_published_projection():
    """P2 · R0_rect · Tr_velo_to_cam, as KITTI documents it, against the camera's own model."""
    cam = camera_preset("kitti-rig")
    rng = np.random.default_rng(1)
    pts = np.stack([rng.uniform(3, 80, 5000), rng.uniform(-20, 20, 5000),
                    rng.uniform(-2, 3, 5000)], 1)
    r0 = np.eye(4)
    r0[:3, :3] = KITTI_R0_RECT
    tr = np.eye(4)
    tr[:3] = KITTI_TR_VELO_TO_CAM
    h = KITTI_P2 @ r0 @ tr @ np.c_[pts, np.ones(len(pts))].T
    u_kitti, v_kitti = h[0] / h[2], h[1] / h[2]
    u, v, _ = project_points(pts, cam.intrinsics, cam.extrinsic)
    assert np.abs(u - 0.5 - u_kitti).max() < 1e-6 and np.abs(v - 0.5 - v_kitti).max() < 1e-6
    # The camera sits 0.27 m ahead of the LiDAR and 0.08 m below it, as on KITTI's car.
    centre = cam.extrinsic.centre
    assert 0.2 < centre[0] < 0.35 and -0.12 < centre[2] < -0.04


def test_calib_file_round_trip(tmp_path):
    cam = camera_preset("kitti-rig")
    path = tmp_path / "c.txt"
    path.write_text(format_calib(cam.kitti_calib()))
    again = read_calib(path)
    intr, ext = again.camera2(cam.intrinsics.width, cam.intrinsics.height)
    pts = np.array([[10.0, 2.0, -1.0], [40.0, -8.0, 1.5]])
    a = project_points(pts, intr, ext)
    b = project_points(pts, cam.intrinsics, cam.extrinsic)
    assert np.allclose(a[0], b[0], atol=1e-6) and np.allclose(a[1], b[1], atol=1e-6)


@pytest.mark.parametrize(("edit", "message"), [
    (lambda t: t.replace("R0_rect", "R0"), "missing R0_rect"),
    (lambda t: t.replace("P2: ", "P2: 1.0 "), "P2 has 13 values"),
    (lambda t: t.replace("Tr_velo_to_cam: ", "Tr_velo_to_cam: x "), "Tr_velo_to_cam: not a"),
])
def test_bad_calib_file_names_the_key(tmp_path, edit, message):
    path = tmp_path / "c.txt"
    path.write_text(edit(format_calib(camera_preset("kitti-centre").kitti_calib())))
    with pytest.raises(FalsifyError, match=message):
        read_calib(path)


# -- real KITTI object frames ------------------------------------------------------------------
@pytest.fixture
def kitti_object(kitti_dir):
    d = kitti_dir / "object"
    if not (d / "calib").is_dir():
        pytest.skip(f"KITTI object frames not found at {d}")
    return d


def test_calib_on_real_kitti_frames(kitti_object, tmp_path, capsys):
    out = tmp_path / "overlays"
    assert main(["calib", str(kitti_object), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    pooled = summary["pooled"]
    assert pooled["points_in_boxes"] > 1000 and pooled["fraction"] >= 0.95, pooled
    assert summary["by_type"]["Car"]["fraction"] >= 0.95
    assert all(o["type"] != "DontCare" for o in summary["objects"])
    assert sorted(p.name for p in out.iterdir()) == ["000000.png", "000001.png", "000002.png",
                                                     "calib-overlays.json"]


def test_calib_check_can_fail(kitti_object, tmp_path):
    """A camera 40 px off (or no rectification and the wrong axes) drops the score: the check
    measures the calibration, not just that points exist."""
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(kitti_object, bad)
    for f in (bad / "calib").glob("*.txt"):
        c = read_calib(f)
        p2 = c.P2.copy()
        p2[0, 2] += 40.0
        f.write_text(format_calib(KittiCalib((c.P[0], c.P[1], p2, c.P[3]), c.R0_rect,
                                             c.Tr_velo_to_cam)))
    assert check_kitti_dir(bad, None).pooled()["fraction"] < 0.9


def test_calib_bad_directory_exits_2(tmp_path, capsys):
    assert main(["calib", str(tmp_path), "--json"]) == 2
    assert "not a KITTI object directory" in capsys.readouterr().err
    assert main(["calib"]) == 2
    assert "give a KITTI object DIRECTORY or --scenes" in capsys.readouterr().err


def test_calib_writes_overlays_only_into_out(kitti_object, tmp_path, capsys, monkeypatch):
    """Without --out nothing is written anywhere, the current directory included."""
    monkeypatch.chdir(tmp_path)
    assert main(["calib", str(kitti_object), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["pooled"]["points_in_boxes"] > 1000
    assert summary["overlays"] == [] and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, says", [
    (["DIR", "--samples", "5"], "calib --samples: used with --scenes only"),
    (["DIR", "--camera", "kitti-centre"], "calib --camera: used with --scenes only"),
    (["--scenes", "CONFIG", "--out", "OUT"], "calib --out: overlays are written for a KITTI"),
])
def test_calib_refuses_options_of_the_other_mode(tmp_path, capsys, argv, says):
    """An option the chosen mode does not use is an error, not silently ignored."""
    (tmp_path / "dir").mkdir()
    argv = [{"DIR": str(tmp_path / "dir"), "CONFIG": str(CONFIGS / "smoke.toml"),
             "OUT": str(tmp_path / "out")}.get(a, a) for a in argv]
    assert main(["calib", *argv]) == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
