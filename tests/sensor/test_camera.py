"""The camera sensor: labels agree with the LiDAR, image-only dims change only the image, the
car window equals a full cast, and `falsify scan --camera` / `grid --camera` write their files."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.images.png import decode_png, encode_png
from falsify.jobs.calib import car_points_on_car_pixels
from falsify.sensor.camera import camera_preset
from falsify.sensor.lidar import SensorPose, load_sensor
from falsify.sensor.look import Look, parse_look
from falsify.sensor.render import CameraRenderer
from falsify.sensor.scanner import PlacedCar
from falsify.sensor.simulator import Simulator
from falsify.world.space import load_space
from tests.conftest import CONFIGS

LOOK_DIMS = '''
[dims.colour]
values = ["red", "white", "#20a040"]
[dims.weather]
values = ["clear", "fog", "rain"]
[dims.time_of_day]
values = ["noon", "dusk", "night", "07:30"]
'''


@pytest.fixture(scope="module")
def sim():
    return Simulator(load_sensor("kitti-hdl64e-front"))


@pytest.fixture
def look_config(tmp_path):
    path = tmp_path / "looks.toml"
    path.write_text((CONFIGS / "smoke.toml").read_text() + LOOK_DIMS)
    return path


def test_car_points_land_on_car_pixels(sim):
    space = load_space(CONFIGS / "paper.toml")
    cam = camera_preset("kitti-centre")
    renderer = CameraRenderer(sim, cam)
    for values in ({"x": -3, "y": 7, "background": 2}, {"x": 4, "y": 16, "background": 9}):
        s = space.make(values)
        pts = sim.scan(s).points
        image = renderer.render_sample(s)
        n, inside, on = car_points_on_car_pixels(pts[:, :3], pts[:, 5], cam, image.cls)
        assert inside > 300 and on / inside >= 0.98, (values, n, inside, on)
        # Every car pixel belongs to the sampled car (instance 1) or a parked one (>= 1000).
        assert set(np.unique(image.instance[image.cls == 1])) <= {1} | set(range(1000, 10**6))


def test_window_equals_full_cast(sim):
    """Casting only the car's image window gives the same labels and depths as casting every
    pixel at the car, also for a car beside the camera (corners behind it: full image)."""
    cam = camera_preset("kitti-centre").scaled(0.25)
    r = CameraRenderer(sim, cam)
    origin, rot = r.pose_of(SensorPose())
    rays = cam.intrinsics.rays().reshape(-1, 3) @ rot.T
    for car in (PlacedCar("suv", 12.0, 2.5, 30.0, 1), PlacedCar("sedan", 0.0, 4.0, 0.0, 1),
                PlacedCar("van", 30.0, -6.0, -120.0, 1)):
        image = r.render(0, [car])
        bg_caster, _ = sim.background(0)
        t_bg, _ = bg_caster.bvh.cast(origin, rays, cam.max_depth)
        caster, _ = sim.car_caster(car.model)
        t_car, _ = caster.bvh.cast((origin - car.translation()) @ car.rotation(),
                               rays @ car.rotation(), cam.max_depth)
        car_px = (t_car < t_bg).reshape(cam.shape)
        assert np.array_equal(image.instance == 1, car_px)
        assert image.unoccluded[1] == int(np.isfinite(t_car).sum())
    behind = PlacedCar("sedan", -12.0, 0.0, 0.0, 1)
    assert len(r.window(behind, SensorPose())) == 0
    assert len(r.window(PlacedCar("sedan", 0.0, 4.0, 0.0, 1), SensorPose())) == \
        cam.shape[0] * cam.shape[1]


def test_depth_of_the_road_is_exact(sim):
    """Flat road below the horizon: depth along the optical axis is f * h / (v - cy)."""
    cam = camera_preset("kitti-centre")
    image = CameraRenderer(sim, cam).render(0, [])
    i = cam.intrinsics
    row, col = i.height - 1, i.width // 2
    expected = i.fy * sim.sensor.mount_height / (row + 0.5 - i.cy)
    assert image.cls[row, col] == 0
    assert abs(float(image.depth[row, col]) - expected) < 1e-3
    assert image.depth[0, col] == 0.0  # sky


def test_look_changes_image_not_labels(sim):
    cam = camera_preset("kitti-centre").scaled(0.3)
    r = CameraRenderer(sim, cam)
    cars = [PlacedCar("sedan", 10.0, 1.0, 0.0, 1)]
    base = r.render(1, cars, look=Look())
    seen = {base.rgb.tobytes()}
    for values in ({"colour": "red"}, {"weather": "fog"}, {"weather": "rain"},
                   {"time_of_day": "night"}, {"time_of_day": "dusk"}, {"weather": "cloudy"}):
        other = r.render(1, cars, look=parse_look(values))
        assert np.array_equal(other.cls, base.cls) and np.array_equal(other.depth, base.depth)
        assert other.rgb.tobytes() not in seen, values
        seen.add(other.rgb.tobytes())
    red = r.render(1, cars, look=parse_look({"colour": "red"})).rgb[base.instance == 1]
    white = r.render(1, cars, look=parse_look({"colour": "white"})).rgb[base.instance == 1]
    assert red[:, 0].mean() > red[:, 2].mean() + 30 and white.mean() > red.mean()
    night = r.render(1, cars, look=parse_look({"time_of_day": "night"})).rgb
    assert night.mean() < base.rgb.mean() / 3
    again = r.render(1, cars, look=Look())
    assert again.rgb.tobytes() == base.rgb.tobytes()  # deterministic


@pytest.mark.parametrize(("values", "message"), [
    ({"colour": "mauve"}, "dims.colour: 'mauve' is not a colour; allowed: red"),
    ({"weather": "snow"}, "dims.weather: 'snow' is not a weather; allowed: clear"),
    ({"time_of_day": "25:00"}, "dims.time_of_day: '25:00' is not a time"),
    ({"time_of_day": "7:3"}, "is not a time"),
])
def test_bad_look_values_name_the_dim(values, message):
    with pytest.raises(ConfigError, match=message):
        parse_look(values)


def test_scan_camera_files_and_image_dims_leave_scan_identical(tmp_path, look_config, capsys):
    outs = []
    for k, sets in enumerate((["colour=red", "weather=clear", "time_of_day=noon"],
                              ["colour=white", "weather=fog", "time_of_day=dusk"],
                              ["colour=#20a040", "weather=rain", "time_of_day=07:30"])):
        out = tmp_path / f"s{k}"
        args = ["scan", str(look_config), "--out", str(out), "--camera", "--json", "--set", "x=2"]
        for s in sets:
            args += ["--set", s]
        assert main(args) == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["camera"]["fraction"] >= 0.98
        outs.append(out)
    names = {"scan.npy", "scan.png", "scan.bin", "scan.label", "image.png", "class.png",
             "class.npy", "instance.npy", "depth.npy", "overlay.png", "scan-files.json"}
    assert {p.name for p in outs[0].iterdir()} == names
    for name in ("scan.npy", "scan.png", "scan.bin", "scan.label", "class.npy", "instance.npy",
                 "depth.npy"):
        assert len({(o / name).read_bytes() for o in outs}) == 1, name
    assert len({(o / "image.png").read_bytes() for o in outs}) == 3
    rgb = decode_png((outs[0] / "image.png").read_bytes())
    assert rgb.shape == (375, 1242, 3)
    # Without --camera, nothing of the camera is written.
    plain = tmp_path / "plain"
    assert main(["scan", str(look_config), "--out", str(plain), "--set", "x=2"]) == 0
    assert {p.name for p in plain.iterdir()} == {"scan.npy", "scan.png", "scan.bin", "scan.label",
                                                 "scan-files.json"}
    assert (plain / "scan.npy").read_bytes() == (outs[0] / "scan.npy").read_bytes()
    # The text names the camera's files; a scan without --camera into a folder that held one
    # leaves no earlier camera file beside it.
    assert main(["scan", str(look_config), "--out", str(outs[1]), "--set", "x=2", "--camera"]) == 0
    assert "the camera's image.png, class.png" in capsys.readouterr().out
    assert main(["scan", str(look_config), "--out", str(outs[1]), "--set", "x=2"]) == 0
    assert {p.name for p in outs[1].iterdir()} == {"scan.npy", "scan.png", "scan.bin",
                                                   "scan.label", "scan-files.json"}


@pytest.mark.parametrize(("args", "message"), [
    (["--camera", "fisheye"], "--camera: unknown camera 'fisheye'; allowed: kitti-centre"),
    (["--camera", "--set", "colour=mauve"], "is not one of red"),
])
def test_scan_camera_bad_input_exits_2(tmp_path, look_config, capsys, args, message):
    out = tmp_path / "o"
    assert main(["scan", str(look_config), "--out", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(("command", "extra"), [
    ("scan", ["--camera"]), ("scan", []), ("grid", ["--quiet"]),
    ("search", ["--algorithm", "random", "--budget", "2"]),
])
@pytest.mark.parametrize(("dim", "value", "message"), [
    ("colour", "mauve", "dims.colour: 'mauve' is not a colour"),
    ("time_of_day", "25:99", "dims.time_of_day: '25:99' is not a time"),
])
def test_space_with_unrenderable_look_fails_with_or_without_a_camera(
        tmp_path, capsys, command, extra, dim, value, message):
    """The value is stored with every sample, so it is checked even when no camera renders it."""
    config = tmp_path / "c.toml"
    look = f'[dims.{dim}]\nvalues = ["{value}"]\n'
    config.write_text((CONFIGS / "smoke.toml").read_text() + look)
    out = tmp_path / "o"
    assert main([command, str(config), "--out", str(out), *extra]) == 2
    assert f"{config}: {message}" in capsys.readouterr().err
    assert not out.exists()


def test_camera_only_dims_leave_the_lidar_results_alone(tmp_path):
    """colour, weather and time of day are the camera's: the same LiDAR samples with them give
    the same seeds, scans and scores as without them."""
    plain, looked = tmp_path / "plain.toml", tmp_path / "looked.toml"
    smoke = (CONFIGS / "smoke.toml").read_text().replace("values = [0, 1]", "values = [1]")
    plain.write_text(smoke + "[dims.rain]\nvalues = [0.0, 30.0]\n")
    looked.write_text(plain.read_text() + '[dims.colour]\nvalues = ["red", "blue"]\n'
                      '[dims.time_of_day]\nvalues = ["dusk"]\n')
    for cfg in (plain, looked):
        assert main(["grid", str(cfg), "--out", str(tmp_path / cfg.stem), "--quiet"]) == 0
    a = pd.read_csv(tmp_path / "plain" / "results.csv")
    b = pd.read_csv(tmp_path / "looked" / "results.csv")
    keys = ["x", "y", "background", "rain"]
    b = b.sort_values([*keys, "colour"]).reset_index(drop=True)
    a = a.sort_values(keys).loc[a.index.repeat(2)].sort_values(keys).reset_index(drop=True)
    for col in ("seed", "car_iou", "inserted_iou", "car_points", "label_points"):
        assert a[col].tolist() == b[col].tolist(), col


def test_png_reader_round_trip_and_filters():
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    assert np.array_equal(decode_png(encode_png(img)), img)
    # Rows written with each of PNG's five filters decode to the same pixels.
    import struct
    import zlib
    raw = img.reshape(7, 15).astype(np.int64)
    lines = []
    prev = np.zeros(15, np.int64)
    for r in range(7):
        kind = r % 5
        cur = raw[r]
        left = np.concatenate([[0, 0, 0], cur[:-3]])
        upleft = np.concatenate([[0, 0, 0], prev[:-3]])
        if kind == 0:
            f = cur
        elif kind == 1:
            f = cur - left
        elif kind == 2:
            f = cur - prev
        elif kind == 3:
            f = cur - (left + prev) // 2
        else:
            p = left + prev - upleft
            pa, pb, pc = abs(p - left), abs(p - prev), abs(p - upleft)
            f = cur - np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prev, upleft))
        lines.append(bytes([kind]) + (f % 256).astype(np.uint8).tobytes())
        prev = cur

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(
            ">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 5, 7, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(b"".join(lines))) + chunk(b"IEND", b""))
    assert np.array_equal(decode_png(png), img)
    with pytest.raises(ValueError, match="not a PNG"):
        decode_png(b"GIF89a")


def test_grid_camera_stores_retraining_images(tmp_path, capsys):
    from falsify.results.store import read_frame
    from tests.cli.test_pipeline import BUNDLED, small_config
    if not BUNDLED.exists():
        pytest.skip("bundled model not trained yet")
    config = small_config(tmp_path, xs=(-2.0, 2.0, 4.0), ys=(9.0, 9.0, 1.0), backgrounds=(0,),
                          extra='[dims.colour]\nvalues = ["blue"]\n')
    run = tmp_path / "run"
    assert main(["grid", str(config), "--out", str(run), "--quiet", "--no-report", "--json",
                 "--threshold", "1.0", "--camera"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["retraining_samples"] == len(read_frame(run)) == 2
    assert summary["retraining_camera"] == "kitti-centre"
    scans = sorted((run / "retrain").glob("??????.npy"))
    assert len(scans) == 2
    for scan in scans:
        stem = scan.name[:-3]
        for suffix in ("image.png", "class.png", "class.npy", "instance.npy", "depth.npy"):
            assert (run / "retrain" / f"{stem}{suffix}").exists()
        cls = np.load(run / "retrain" / f"{stem}class.npy")
        assert cls.shape == (375, 1242) and (cls == 1).sum() > 1000
    bad = small_config(tmp_path, extra='[dims.weather]\nvalues = ["snow"]\n')
    assert main(["grid", str(bad), "--out", str(tmp_path / "bad"), "--quiet", "--camera"]) == 2
    assert "dims.weather: 'snow' is not a weather" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_incremental_shading_equals_full_shading(sim):
    """Re-shading only the car pixels and the street pixels a car may shade gives the same
    bytes as shading every pixel, for sun, night and rain, several cars, and a moved ego."""
    cam = camera_preset("kitti-centre").scaled(0.4)
    fast = CameraRenderer(sim, cam)
    full = CameraRenderer(sim, cam, incremental=False)
    cars = [PlacedCar("suv", 9.0, 3.0, 200.0, 1), PlacedCar("van", 16.0, -4.0, 10.0, 2),
            PlacedCar("sedan", 25.0, 1.0, 90.0, 3)]
    for look, pose in ((Look(hour=16.5), SensorPose()), (Look(hour=9.0), SensorPose(5.0, 1.0)),
                       (parse_look({"weather": "rain", "time_of_day": "night"}), SensorPose()),
                       (Look(hour=12.0, weather="fog"), SensorPose(-3.0, 0.0, 4.0))):
        for placed in (cars, cars[:1], []):
            a = fast.render(2, placed, pose, look)
            b = full.render(2, placed, pose, look)
            assert np.array_equal(a.rgb, b.rgb), (look, pose, len(placed))
            assert np.array_equal(a.cls, b.cls) and np.array_equal(a.depth, b.depth)


def test_naive_path_renders_the_same_image(sim):
    """`bench camera`'s naive path (one merged trimesh scene, trimesh's ray queries, every pixel
    shaded) makes the image the fast path makes: the speed ratio compares like with like."""
    from falsify.bench.camera import naive_image

    space = load_space(CONFIGS / "paper.toml")
    cam = camera_preset("kitti-centre").scaled(0.3)
    # the paper's streets stand for real places: both paths build them from its world
    sim = Simulator(sim.sensor, background_source=space.background_source())
    r = CameraRenderer(sim, cam)
    s = space.make({"x": -3, "y": 8, "background": 4})
    fast = r.render_sample(s)
    rgb, owner = naive_image(space, s, r)
    assert np.mean(owner == np.where(fast.instance == 1, 0, np.where(fast.depth > 0, -1, -2))) \
        > 0.995
    close = np.abs(rgb.astype(int) - fast.rgb.astype(int)).max(axis=2) <= 2
    assert close.mean() > 0.99, close.mean()


def test_a_climbing_road_is_shaded_as_road_all_the_way_up():
    """The road's colour is decided against the road's own crown height at x, not against
    z = 0: street 9 climbs (0.86 m at x = 100 m), and its far road surface, crown and kerbside,
    stays road; a level surface 1 m above it (a car roof, a bus top) does not."""
    from falsify.sensor import shading
    from falsify.world.streets import build_background

    bg = build_background(9)
    t = bg.terrain
    x = np.array([10.0, 60.0, 100.0, 100.0, 100.0])
    y = np.array([3.0, 0.5, 0.5, 0.5 - float(t.kerb(100.0)), 2.0])
    z = t.height(x, y)
    assert z[2] > 0.5  # the street really climbs
    z[4] += 1.0
    col = np.zeros((len(x), 3))
    shading.ground_colours(bg, x, y, z, np.ones(len(x), bool), col)
    for k in range(4):
        assert tuple(col[k]) == shading._ROAD, (k, x[k], y[k], z[k])
    assert tuple(col[4]) != shading._ROAD


def test_the_lidars_fog_visibility_drives_the_camera(sim):
    """A sample's `fog` visibility V sets the camera's extinction ln(20) / V (as the LiDAR's),
    denser fog hides more of the far street, and a `weather` dim keeps its own say."""
    import math

    from falsify.sensor.look import look_of
    from falsify.world.space import parse_space

    dims = {"car_model": {"values": ["sedan"]}, "x": {"values": [1.0]}, "y": {"values": [10.0]},
            "background": {"values": [1]}, "fog": {"values": [0.0, 30.0, 300.0]},
            "rain": {"values": [0.0, 20.0]}}
    space = parse_space({"dims": dims})
    looks = {(s["fog"], s["rain"]): look_of(s) for s in space.grid()}
    assert looks[(0.0, 0.0)] == Look()
    assert looks[(30.0, 0.0)].weather == "fog"
    assert looks[(30.0, 0.0)].extinction == pytest.approx(math.log(20.0) / 30.0)
    assert looks[(0.0, 20.0)].weather == "rain" and looks[(0.0, 20.0)].extinction is None
    with_weather = parse_space({"dims": {**dims, "weather": {"values": ["cloudy"]}}})
    s = with_weather.make({"fog": 30.0})
    assert look_of(s).weather == "cloudy" and look_of(s).extinction is not None
    cam = camera_preset("kitti-centre").scaled(0.3)
    r = CameraRenderer(sim, cam)
    cars = [PlacedCar("sedan", 10.0, 1.0, 0.0, 1)]
    clear = r.render(1, cars, look=looks[(0.0, 0.0)])
    dense = r.render(1, cars, look=looks[(30.0, 0.0)])
    light = r.render(1, cars, look=looks[(300.0, 0.0)])
    far = clear.depth > 40
    assert far.any() and np.array_equal(dense.cls, clear.cls)

    def contrast(img):   # spread of the far pixels' brightness: fog flattens it
        return float(img.rgb[far].astype(float).mean(axis=1).std())
    assert contrast(dense) < contrast(light) < contrast(clear)
