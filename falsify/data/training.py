"""Training scans from "auto-driving" scenes: random streets, ego poses along the road, traffic.

This is not the falsification space: it draws its own backgrounds from ids disjoint from the test
configs (TRAIN_BACKGROUND_FIRST and up), so a falsification run tests the network on streets it
never saw. Each scan is fully determined by (seed, index), so a dataset can be resumed or
extended without changing the scans already written.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from falsify.classes import CAR, CLASSES, UNKNOWN
from falsify.data.velodyne import SEMANTICKITTI_SEQUENCE, kitti_arrays, semantickitti_paths
from falsify.errors import ConfigError
from falsify.fileio import write_bytes, write_json, write_npy, write_text
from falsify.semantic import RAW_NAMES, split_label, train_ids
from falsify.sensor.lidar import Sensor, SensorPose
from falsify.sensor.simulator import (
    EGO_X_BACKWARD,
    EGO_X_FORWARD,
    InvalidSample,
    PlacedCar,
    Simulator,
    check_placement,
    free_ego,
)
from falsify.sensor.weather import draw_effects
from falsify.world.cars import BUILTIN_MODELS
from falsify.world.materials import PAINTS
from falsify.world.profile import WorldProfile
from falsify.world.road_users import OTHER_VEHICLES
from falsify.world.space import EFFECT_DIMS, Categorical, Space

TRAIN_BACKGROUND_FIRST = 1000
SCANS_PER_BACKGROUND = 8
HELD_OUT_BACKGROUND_FIRST = 9000
CALIBRATION_SCANS = 64   # int8 calibration (models/export.py says what more scans gave)
TRAFFIC_KINDS = ("scattered", "drive")  # drive: lane-following traffic (falsify.data.traffic)
LABEL_SETS = ("kitti4", "semantickitti")   # what an npy scan's label channel holds
DATASET_FORMATS = ("npy", "semantickitti")  # what write_dataset writes
# KITTI's velodyne-to-camera axes (camera x right, y down, z forward; no offset): calib.txt's Tr,
# through which SemanticKITTI's tools turn poses.txt into velodyne poses.
VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class TrafficOptions:
    """How busy the training streets are."""

    max_cars: int = 12
    ahead: tuple[float, float] = (-15.0, 60.0)   # car positions relative to the ego, metres
    backgrounds: int = 1000                       # distinct backgrounds to draw from
    first_background: int = TRAIN_BACKGROUND_FIRST
    traffic: str = "scattered"                    # one of TRAFFIC_KINDS
    world: WorldProfile | None = None             # fitted poses and car counts (scattered only)


def training_simulator(sensor: Sensor, opts: TrafficOptions, max_hits: int) -> Simulator:
    """A Simulator for training scenes, one street held at a time, its streets built as
    `opts.world` says (parked cars thinned) or as they are."""
    source = None if opts.world is None else opts.world.background_source()
    return Simulator(sensor, max_bvh=1, max_hits=max_hits, background_source=source)


def scene_for(index: int, seed: int, sim: Simulator,
              opts: TrafficOptions) -> tuple[int, SensorPose, list[PlacedCar]]:
    """The background, ego pose and traffic of training scan `index` (deterministic)."""
    bg_id = opts.first_background + (index // SCANS_PER_BACKGROUND) % opts.backgrounds
    if opts.traffic == "drive":
        from falsify.data.traffic import drive_scene

        if opts.world is not None:
            raise ConfigError("--world: only with --traffic scattered")

        return (bg_id, *drive_scene(index, seed, sim, bg_id, opts.max_cars))
    if opts.traffic != "scattered":
        raise ConfigError(f"--traffic: {opts.traffic!r} is not one of {list(TRAFFIC_KINDS)}")
    rng = np.random.default_rng([seed, index])
    bg = sim.background(bg_id)[1]
    half = float(getattr(bg, "road_half_width", 9.0))
    off_crown = float(getattr(bg, "ego_dy", 0.0))   # pose y is across from the street's ego
    def draw() -> SensorPose:
        # Any lane, up to beside the parked cars, so the roadside is seen from close by too
        # (the middle of a road narrower than two lanes).
        reach = max(half - 3.3, 0.0)
        lane = rng.uniform(-reach, reach) - off_crown
        heading = rng.normal(0.0, 2.0) + (180.0 if rng.random() < 0.3 else 0.0)
        ego_x = rng.uniform(*EGO_X_FORWARD) if heading < 90 else rng.uniform(*EGO_X_BACKWARD)
        return SensorPose(ego_x, lane, heading)

    pose, ego = free_ego(sim, bg_id, draw, f"scan {index}")
    if opts.world is not None:
        # Its own stream: the pose and count draws leave the other draws of the scene alone.
        world_rng = np.random.default_rng([seed, index, 13])
        dpitch, dheight = opts.world.draw_pose(world_rng)
        pose = replace(pose, pitch_deg=pose.pitch_deg + dpitch, z=pose.z + dheight)
        wanted = opts.world.draw_cars(world_rng, opts.max_cars)
    else:
        wanted = None
    ego_x, heading = pose.x, pose.heading_deg
    obstacles = sim.obstacles(bg_id)
    forward = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
    placed: list[PlacedCar] = []
    outlines: list[np.ndarray] = []
    if wanted is None:
        wanted = int(rng.integers(0, opts.max_cars + 1))
    for _ in range(wanted * 4):
        if len(placed) == wanted:
            break
        # Hard negatives: about one vehicle in eight is a van, truck, bus or trailer (class 0).
        other = rng.random() < 0.12
        model = str(rng.choice(OTHER_VEHICLES if other else BUILTIN_MODELS))
        paint = int(PAINTS[int(rng.integers(len(PAINTS)))])
        along = rng.uniform(*opts.ahead)
        across = rng.uniform(-(half - 1.0), half - 1.0)
        cx = ego_x + along * forward[0]
        cy = across
        r = rng.random()
        if r < 0.7:
            car_heading = rng.normal(0.0, 4.0) + (180.0 if across > 0 and r < 0.35 else 0.0)
        else:
            car_heading = rng.uniform(-180.0, 180.0)
        car = PlacedCar(model, float(cx), float(cy), float(car_heading), 1 + len(placed),
                        cls=UNKNOWN if other else CAR, paint=paint)
        outline = sim.footprint(car)
        try:
            check_placement([*placed, car], [*outlines, outline], obstacles, ego=ego)
        except InvalidSample:
            continue
        placed.append(car)
        outlines.append(outline)
    return bg_id, pose, [sim.settle(bg_id, c) for c in placed]


def write_dataset(sensor: Sensor, out: Path, scans: int, seed: int = 0,
                  opts: TrafficOptions = TrafficOptions(), start: int = 0,
                  on_progress: Callable[[int, int], None] | None = None,
                  weather: Space | None = None, fmt: str = "npy",
                  labels: str = "kitti4") -> dict:
    """Write scans start..scans-1 (skipping ones already there) plus index.json: as NNNNNN.npy
    range images, or with fmt "semantickitti" in SemanticKITTI's layout (`semantickitti_paths`).
    npy scans hold our four classes in their label channel, or with labels "semantickitti"
    SemanticKITTI's train ids (falsify.semantic), what a 20-class network trains on.
    With `weather`, each scan draws its weather and faults from that space's effect dims (a
    training set that sees what the falsification space tests); without, scans are clear."""
    if scans <= 0:
        raise ConfigError(f"--scans: {scans} must be > 0")
    if fmt not in DATASET_FORMATS:
        raise ConfigError(f"--format: {fmt!r} is not one of {list(DATASET_FORMATS)}")
    if labels not in LABEL_SETS:
        raise ConfigError(f"--labels: {labels!r} is not one of {list(LABEL_SETS)}")
    semantickitti = fmt == "semantickitti"
    out.mkdir(parents=True, exist_ok=True)
    sim = training_simulator(sensor, opts, max_hits=8)
    drawn = [] if weather is None else [d for d in EFFECT_DIMS if d in weather.dims]
    counts = np.zeros(len(CLASSES), np.int64)
    sem_counts = np.zeros(1 << 16, np.int64)
    poses: list[np.ndarray] = []   # every scan's, for poses.txt
    written = 0
    for i in range(0 if semantickitti else start, scans):
        paths = semantickitti_paths(out, i) if semantickitti else (out / f"{i:06d}.npy",)
        done = i < start or all(p.exists() for p in paths)
        if done and not semantickitti:
            continue
        bg_id, pose, placed = scene_for(i, seed, sim, opts)
        if semantickitti:
            poses.append(world_from_sensor(sensor, pose))
        if done:
            continue
        rng = np.random.default_rng([seed, i, 1])
        effects = (None if not drawn else
                   draw_effects(weather, np.random.default_rng([seed, i, 3])))
        scan = sim.render(bg_id, placed, pose, rng, effects=effects)
        if semantickitti:
            points, values = kitti_arrays(scan)
            write_bytes(paths[1], values.tobytes())
            write_bytes(paths[0], points.tobytes())
            sem_counts += np.bincount(split_label(values)[0], minlength=1 << 16)
        elif labels == "semantickitti":
            image = scan.image.copy()
            image[..., 5] = np.where(scan.valid, train_ids(scan.semantic), 0)
            write_npy(paths[0], image)
        else:
            write_npy(paths[0], scan.image)
        lab = scan.image[..., 5][scan.valid].astype(np.int64)
        counts += np.bincount(lab, minlength=len(CLASSES))[:len(CLASSES)]
        written += 1
        if on_progress is not None and written % 50 == 0:
            on_progress(i + 1, scans)
    index = dataset_index(sensor, scans, seed, opts, weather, fmt, labels)
    extra: dict = {}
    if semantickitti:
        _write_calib_and_poses(out / "sequences" / SEMANTICKITTI_SEQUENCE, poses)
        extra["points_per_semantic"] = {RAW_NAMES.get(int(k), str(int(k))): int(sem_counts[k])
                                        for k in np.flatnonzero(sem_counts)}
    write_json(out / "index.json", index)
    return {**index, "written": written, "points_per_class": dict(
        zip(CLASSES, counts.tolist(), strict=True)), **extra}


def dataset_index(sensor: Sensor, scans: int, seed: int = 0,
                  opts: TrafficOptions = TrafficOptions(), weather: Space | None = None,
                  fmt: str = "npy", labels: str = "kitti4") -> dict:
    """The index.json of a set `write_dataset` writes with these arguments: what decides its
    scans, so a resumed or extended set can be checked against the one already there."""
    drawn = [] if weather is None else [d for d in EFFECT_DIMS if d in weather.dims]
    index = {"scans": scans, "seed": seed, "sensor": sensor.name,
             "first_background": opts.first_background, "backgrounds": opts.backgrounds,
             "max_cars": opts.max_cars, "ray_drop": sensor.ray_drop,
             "range_noise": sensor.range_noise}
    if sensor.file_sha256:   # sets of a preset sensor keep their index byte for byte
        index["sensor_file"] = sensor.file_sha256
    if opts.traffic != "scattered":  # scattered sets keep their index byte for byte
        index["traffic"] = opts.traffic
    if opts.world is not None:   # so do sets without a profile
        index["world"] = opts.world.name
    if drawn:   # so do clear sets
        index["effects"] = {d: _drawn_from(weather.dims[d]) for d in drawn}
    if labels != "kitti4":
        index["labels"] = labels
    if fmt == "semantickitti":   # npy sets keep their index byte for byte too
        index["format"] = fmt
        index["sequence"] = SEMANTICKITTI_SEQUENCE
    return index


def world_from_sensor(sensor: Sensor, pose: SensorPose) -> np.ndarray:
    """4x4 transform taking a scan's sensor-frame points into its street's world frame."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = pose.rotation(sensor), pose.origin(sensor)
    return m


def _write_calib_and_poses(seq: Path, poses: list[np.ndarray]) -> None:
    """calib.txt and poses.txt as SemanticKITTI's (KITTI odometry's) files: calib.txt holds
    P0..P3 (our kitti-centre camera, what --format kitti-object renders from the same pose; the
    odometry devkit's calib.txt has all four) and Tr (the velodyne-to-camera axes); poses.txt
    each scan's pose in the camera frame, Tr P Tr^-1, 12 values a row: what SemanticKITTI's
    tools read to aggregate scans (generate_sequential.py). Poses are in each scan's street
    frame: only scans of one background (SCANS_PER_BACKGROUND in a row) share a frame."""
    from falsify.sensor.camera import camera_preset

    def row(m: np.ndarray) -> str:
        return " ".join(f"{v:.12e}" for v in np.asarray(m)[:3].ravel()) + "\n"

    cams = camera_preset("kitti-centre").kitti_calib().P
    write_text(seq / "calib.txt", "".join(f"P{k}: {row(cams[k])}" for k in range(4))
               + "Tr: " + row(VELO_TO_CAM))
    inv = np.linalg.inv(VELO_TO_CAM)
    write_text(seq / "poses.txt", "".join(row(VELO_TO_CAM @ p @ inv) for p in poses))


def traffic_scans(sensor: Sensor, n: int, seed: int, opts: TrafficOptions,
                  stride: int) -> np.ndarray:
    """Range images (n, H, W, 6) of training-style scenes `0, stride, 2 * stride, ...`, without
    sensor noise: the synthetic scans used for calibration and held-out checks."""
    sim = training_simulator(sensor, opts, max_hits=1)
    images = []
    for i in range(n):
        bg, pose, cars = scene_for(i * stride, seed, sim, opts)
        images.append(sim.render(bg, cars, pose).image)
    return np.stack(images)


def calibration_scans(sensor: Sensor, n: int | None = None, seed: int = 0) -> np.ndarray:
    """Scans of training-style traffic (training backgrounds, never a test config's and never
    real KITTI) to calibrate int8 activation ranges; CALIBRATION_SCANS of them by default."""
    return traffic_scans(sensor, CALIBRATION_SCANS if n is None else n, seed, TrafficOptions(),
                         stride=4)


def held_out_scans(sensor: Sensor, n: int) -> np.ndarray:
    """Labelled scans on backgrounds no training or test config uses (ids 9000 and up)."""
    opts = TrafficOptions(backgrounds=max(1, n), first_background=HELD_OUT_BACKGROUND_FIRST)
    return traffic_scans(sensor, n, 77, opts, stride=8)


def _drawn_from(dim) -> dict:
    """What an effect dim's draws come from, for the set's index."""
    if isinstance(dim, Categorical):
        return {"values": list(dim.values)}
    return {"min": dim.lo, "max": dim.hi}


def write_dataset_parallel(workers: int, sensor: Sensor, out: Path, scans: int,
                           **kwargs) -> dict:
    """`write_dataset` split into `workers` spawned processes, each writing a contiguous range
    of indices; every scan depends on (seed, index) alone, so the files equal a one-process
    run's (npy sets: a SemanticKITTI set's poses.txt needs one process). Returns the summary
    with the workers' counts added up."""
    import concurrent.futures as cf
    import multiprocessing as mp

    bounds = np.linspace(0, scans, workers + 1).round().astype(int)
    with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        jobs = [pool.submit(write_dataset, sensor, out, int(hi), start=int(lo), **kwargs)
                for lo, hi in zip(bounds[:-1], bounds[1:], strict=True) if hi > lo]
        parts = [j.result() for j in jobs]
    summary = dict(parts[-1])
    summary["written"] = sum(p["written"] for p in parts)
    summary["points_per_class"] = {c: sum(p["points_per_class"][c] for p in parts)
                                   for c in CLASSES}
    # each process wrote index.json with its own end; the last range's is the whole set's
    write_json(out / "index.json", {k: v for k, v in parts[-1].items()
                                    if k not in ("written", "points_per_class")})
    return summary
