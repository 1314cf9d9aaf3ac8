"""`falsify dataset --format kitti-object`: our training scenes in KITTI's 3D object layout.

Each frame is the same auto-driving scene as the .npy dataset's frame of the same index (seed,
index), scanned by the LiDAR and rendered by the camera: `velodyne/N.bin` (the scan's valid
points, sensor frame), `image_2/N.png`, `calib/N.txt` (our camera as P2 with R0_rect = I) and
`label_2/N.txt` (a Car, Pedestrian or Cyclist line for every object the camera sees).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from falsify.data.kitti_object import (
    CLASS_TYPE,
    Box3D,
    format_calib,
    object_label,
    oriented_box,
)
from falsify.data.training import TrafficOptions, scene_for, training_simulator
from falsify.errors import ConfigError
from falsify.fileio import write_bytes, write_json, write_text
from falsify.images.png import encode_png
from falsify.sensor.camera import Camera, CameraImage
from falsify.sensor.lidar import Sensor, SensorPose
from falsify.sensor.look import COLOURS, TIMES, Look
from falsify.sensor.render import CameraRenderer
from falsify.sensor.simulator import PlacedCar, Simulator
from falsify.world.streets import Background

_PAINTS = tuple(c for c in COLOURS if c != "gray")
_WEATHER_P = {"clear": 0.7, "cloudy": 0.15, "rain": 0.1, "fog": 0.05}
_DAY = ("morning", "noon", "afternoon", "dusk")


@dataclass(frozen=True)
class KittiExport:
    """What was written."""

    out: str
    frames: int
    written: int
    objects: dict[str, int]
    camera: str
    sensor: str


def frame_look(seed: int, index: int) -> tuple[Look, np.random.Generator]:
    """The weather and time of a frame (mostly clear days), and a generator for car paints."""
    rng = np.random.default_rng([seed, index, 2])
    weather = str(rng.choice(list(_WEATHER_P), p=list(_WEATHER_P.values())))
    return Look(weather=weather, hour=TIMES[str(rng.choice(_DAY))]), rng


def boxes_in_view(sim: Simulator, bg_id: int, placed: list[PlacedCar], pose: SensorPose,
                  image: CameraImage) -> list[tuple[Box3D, tuple[int, int, int, int], int, int]]:
    """Every car, pedestrian and cyclist with a pixel in the image: its box in the LiDAR frame,
    its visible pixel range, visible pixels and unoccluded pixels (-1 when unknown)."""
    s_rot = pose.rotation(sim.sensor)
    origin = pose.origin(sim.sensor)
    heading0 = np.radians(pose.heading_deg)
    _, bg = sim.background(bg_id)
    out = []
    ids, counts = np.unique(image.instance[image.instance > 0], return_counts=True)
    by_id = {c.instance: c for c in placed}
    for iid, count in zip(ids.tolist(), counts.tolist(), strict=True):
        rows, cols = np.nonzero(image.instance == iid)
        visible = (int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max()))
        if iid in by_id:
            car = by_id[iid]
            if car.cls not in CLASS_TYPE:   # a van, truck or bus: unlabelled, as on the streets
                continue
            _, corners = sim.car_caster(car.model)
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            centre_w = car.rotation() @ np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2,
                                                  lo[2]]) + car.translation()
            size = hi - lo
            box = Box3D(car.cls, iid, s_rot.T @ (centre_w - origin), float(size[0]),
                        float(size[1]), float(size[2]), np.radians(car.heading_deg) - heading0)
            out.append((box, visible, count, image.unoccluded.get(iid, -1)))
            continue
        world = street_object(bg, iid)
        if world is None:
            continue
        box = replace(world, centre=s_rot.T @ (world.centre - origin),
                      heading=world.heading - heading0)
        out.append((box, visible, count, -1))
    return out


def street_object(bg: Background, iid: int) -> Box3D | None:
    """The world-frame box of a street's car, pedestrian or cyclist `iid` (None for other
    objects), facing where the street placed it (its vertices alone leave the front unknown)."""
    faces = bg.face_instance == iid
    cls = int(bg.face_class[faces][0])
    if cls not in (1, 2, 3):
        return None
    facing = next((o.heading for o in bg.obstacles if o.instance == iid), None)
    centre, length, width, height, heading = oriented_box(
        bg.vertices[np.unique(bg.faces[faces])], facing)
    return Box3D(cls, iid, centre, length, width, height, heading)


def kitti_object_index(sensor: Sensor, camera: str, frames: int, seed: int = 0,
                       opts: TrafficOptions = TrafficOptions()) -> dict:
    """The index.json `write_kitti_object` writes: what decides its frames, so a resumed set
    can be checked against the one already there. The sensor's noise, the traffic and the world
    profile decide them too (left out, a resume with another --traffic or --world mixed two
    kinds of frame in one set); traffic and world are only named when set, as in the npy
    index."""
    index = {"format": "kitti-object", "frames": frames, "seed": seed, "sensor": sensor.name,
             "camera": camera, "first_background": opts.first_background,
             "backgrounds": opts.backgrounds, "max_cars": opts.max_cars,
             "ray_drop": sensor.ray_drop, "range_noise": sensor.range_noise}
    if sensor.file_sha256:   # a user's sensor file, by content
        index["sensor_file"] = sensor.file_sha256
    if opts.traffic != "scattered":
        index["traffic"] = opts.traffic
    if opts.world is not None:
        index["world"] = opts.world.name
    return index


def write_kitti_object(sensor: Sensor, camera: Camera, out: Path, frames: int, seed: int = 0,
                       opts: TrafficOptions = TrafficOptions()) -> KittiExport:
    """Write frames 0..frames-1 (skipping complete ones already there) and index.json."""
    if frames <= 0:
        raise ConfigError(f"--scans: {frames} must be > 0")
    # the npy and semantickitti sets' simulator: a --world profile's streets (parked cars
    # thinned) too, so frame i is their scan i
    sim = training_simulator(sensor, opts, max_hits=8)
    renderer = CameraRenderer(sim, camera)
    calib = camera.kitti_calib()
    calib_text = format_calib(calib)
    h, w = camera.shape
    counts: dict[str, int] = {}
    written = 0
    for i in range(frames):
        name = f"{i:06d}"
        paths = {d: out / d / f"{name}.{ext}" for d, ext in
                 (("velodyne", "bin"), ("image_2", "png"), ("calib", "txt"), ("label_2", "txt"))}
        if all(p.exists() for p in paths.values()):
            continue
        bg_id, pose, placed = scene_for(i, seed, sim, opts)
        scan = sim.render(bg_id, placed, pose, np.random.default_rng([seed, i, 1]))
        look, rng = frame_look(seed, i)
        paints = [COLOURS[str(rng.choice(_PAINTS))] for _ in placed]
        image = renderer.render(bg_id, placed, pose, look, paints)
        lines = []
        for box, visible, count, alone in boxes_in_view(sim, bg_id, placed, pose, image):
            obj = object_label(box, calib, visible, count, alone, (w, h))
            if alone < 0:  # occlusion of background objects is not computed: KITTI's "unknown"
                obj = replace(obj, occluded=3)
            lines.append(obj.line())
            counts[obj.type] = counts.get(obj.type, 0) + 1
        pts = scan.image[scan.valid][:, :4].astype(np.float32)
        write_bytes(paths["velodyne"], pts.tobytes())
        write_bytes(paths["image_2"], encode_png(image.rgb))
        write_text(paths["calib"], calib_text)
        write_text(paths["label_2"], "".join(line + "\n" for line in lines))
        written += 1
    write_json(out / "index.json", kitti_object_index(sensor, camera.name, frames, seed, opts))
    return KittiExport(str(out), frames, written, counts, camera.name, sensor.name)
