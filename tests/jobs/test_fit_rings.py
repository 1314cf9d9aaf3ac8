"""The ring geometry fit: it recovers each row's elevation and origin height from scans cast by
a sensor with per-row origins, says which ring it cannot fit, refuses held-out and repeated
frames, and on KITTI's object frames finds the HDL-64E's two blocks of laser origins."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from falsify.cli import main as falsify_main
from falsify.errors import FalsifyError
from falsify.jobs.fit_rings import fit, fit_rings
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import Simulator
from falsify.world.streets import build_background


def main(argv: list[str]) -> int:
    """`falsify fit-rings ARGV`."""
    return falsify_main(["fit-rings", *argv])


def fit_returns_main(argv: list[str]) -> int:
    """`falsify fit-returns ARGV`."""
    return falsify_main(["fit-returns", *argv])


def tilted_room():
    """Ground tilted 4 % along x, inside walls 12-30 m away: every ring of a 360-degree sensor
    meets surfaces at many ranges."""
    v = [[-200.0, -200.0, -8.0], [200.0, -200.0, 8.0], [200.0, 200.0, 8.0], [-200.0, 200.0, -8.0]]
    f = [[0, 1, 2], [0, 2, 3]]
    x0, x1, y0, y1, top = -14.0, 30.0, -12.0, 20.0, 40.0
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    for i in range(4):
        (ax, ay), (bx, by) = corners[i], corners[(i + 1) % 4]
        n = len(v)
        v += [[ax, ay, -10.0], [bx, by, -10.0], [bx, by, top], [ax, ay, top]]
        f += [[n, n + 1, n + 2], [n, n + 2, n + 3]]
    bg = build_background(0)
    faces = np.array(f, np.int32)
    return dataclasses.replace(bg, vertices=np.array(v), faces=faces,
                               face_class=np.zeros(len(faces), np.uint8),
                               face_instance=np.zeros(len(faces), np.int32), obstacles=(),
                               face_material=None, terrain=None)


def test_fit_recovers_the_rows_elevations_and_origins():
    base = load_sensor("kitti-hdl64e-360")
    dz = tuple(0.21 - 0.0004 * k if k < 32 else 0.12 for k in range(64))
    sensor = dataclasses.replace(base, ring_offsets_m=dz)
    scan = Simulator(sensor, background_source=lambda _id: tilted_room()).render(0, [])
    valid = scan.image[..., 4] > 0
    rows = np.broadcast_to(np.arange(sensor.rows)[:, None], sensor.shape)[valid]
    rings = fit_rings(scan.image[..., :3][valid], rows, sensor.rows)
    np.testing.assert_allclose([r.theta_deg for r in rings], sensor.elevations_deg, atol=2e-3)
    np.testing.assert_allclose([r.dz_m for r in rings], dz, atol=1e-3)
    assert all(r.residual_deg < 1e-3 for r in rings)
    # the same points seen as from one origin do not fit a single elevation per ring
    plain = Simulator(base, background_source=lambda _id: tilted_room()).render(0, [])
    flat = fit_rings(plain.image[..., :3][valid], rows, sensor.rows)
    np.testing.assert_allclose([r.dz_m for r in flat], 0.0, atol=1e-3)


def test_fit_names_the_ring_it_cannot_fit():
    pts = np.array([[10.0 + i, 0.0, -1.0] for i in range(60)])
    with pytest.raises(FalsifyError, match="ring 1: 0 points"):
        fit_rings(pts, np.zeros(60, int), 2)
    same_range = np.array([[10.0 * np.cos(a), 10.0 * np.sin(a), -1.0]
                           for a in np.linspace(0, 6, 60)])
    with pytest.raises(FalsifyError, match="ring 0: its points span 0.00 m"):
        fit_rings(same_range, np.zeros(60, int), 1)


def test_cli_refuses_held_out_repeated_and_unordered_frames(tmp_path, capsys):
    """Held-out frames are refused by content, whatever their folder is called (a manifest,
    not a path name, says what is evaluation data); so are a frame given twice and bad files."""
    held = tmp_path / "object" / "velodyne" / "000000.bin"
    held.parent.mkdir(parents=True)
    np.random.default_rng(1).normal(0, 10, (100, 4)).astype(np.float32).tofile(held)
    manifest = tmp_path / "splits-eval.toml"
    assert falsify_main(["holdout", str(held), "--out", str(manifest)]) == 0
    capsys.readouterr()
    out = tmp_path / "returns.json"
    for argv in ([str(held)], ["--out", str(out), str(held)]):
        fit = main if len(argv) == 1 else fit_returns_main
        assert fit([*argv, "--holdout", str(manifest)]) == 2
        assert "000000.bin: a held-out scan" in capsys.readouterr().err
    assert not out.exists()
    copy = tmp_path / "copy.bin"
    copy.write_bytes(held.read_bytes())
    assert main([str(held.parent), str(copy)]) == 2
    assert f"{copy}: the same bytes as {held}; fit-rings' frames take each scan once" in \
        capsys.readouterr().err
    assert main([str(held), str(held)]) == 2
    assert "given twice" in capsys.readouterr().err
    for name, data, says in (("empty.bin", b"", "0 bytes, not N x 4"),
                             ("odd.bin", b"x" * 20, "20 bytes, not N x 4"),
                             ("frame.npy", b"x" * 16, "not a KITTI .bin frame")):
        (tmp_path / name).write_bytes(data)
        assert main([str(tmp_path / name)]) == 2
        assert says in capsys.readouterr().err
    (tmp_path / "none").mkdir()
    assert main([str(tmp_path / "none")]) == 2
    assert "none: no .bin frames here" in capsys.readouterr().err
    shuffled = tmp_path / "renamed" / "000009.bin"
    shuffled.parent.mkdir(parents=True)
    np.random.default_rng(0).normal(0, 10, (5000, 4)).astype(np.float32).tofile(shuffled)
    assert main([str(shuffled)]) == 2
    assert "000009.bin: not in KITTI's ring order" in capsys.readouterr().err


def test_object_frames_show_two_blocks_of_laser_origins(kitti_dir):
    frames = sorted((kitti_dir / "object" / "velodyne").glob("*.bin"))
    if not frames:
        pytest.skip("KITTI object frames not found")
    rings = fit(frames)
    dz = np.array([r.dz_m for r in rings])
    assert np.all((dz[:32] > 0.19) & (dz[:32] < 0.22))     # upper block
    assert np.all((dz[32:] > 0.11) & (dz[32:] < 0.13))     # lower block
    assert max(r.residual_deg for r in rings) < 0.01
    # the preset's one-origin elevations are what the rings look like from the origin at the
    # ranges they usually meet: above each laser's own elevation in every ring
    preset = np.asarray(load_sensor("kitti-hdl64e-front").elevations_deg)
    assert np.all(preset > [r.theta_deg for r in rings])
