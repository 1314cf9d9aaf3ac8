"""Training scans from "auto-driving" scenes: random streets, ego poses along the road, traffic.

This is not the falsification space: it draws its own backgrounds from ids disjoint from the test
configs (TRAIN_BACKGROUND_FIRST and up), so a falsification run tests the network on streets it
never saw. Each scan is fully determined by (seed, index), so a dataset can be resumed or
extended without changing the scans already written.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.classes import CAR, CLASSES, UNKNOWN
from falsify.errors import ConfigError
from falsify.fileio import write_json, write_npy
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
from falsify.world.road_users import OTHER_VEHICLES
from falsify.world.space import EFFECT_DIMS, Categorical, Space

TRAIN_BACKGROUND_FIRST = 1000
SCANS_PER_BACKGROUND = 8
HELD_OUT_BACKGROUND_FIRST = 9000
CALIBRATION_SCANS = 64   # int8 calibration (models/export.py says what more scans gave)
TRAFFIC_KINDS = ("scattered", "drive")  # drive: lane-following traffic (falsify.data.traffic)


@dataclass(frozen=True)
class TrafficOptions:
    """How busy the training streets are."""

    max_cars: int = 12
    ahead: tuple[float, float] = (-15.0, 60.0)   # car positions relative to the ego, metres
    backgrounds: int = 1000                       # distinct backgrounds to draw from
    first_background: int = TRAIN_BACKGROUND_FIRST
    traffic: str = "scattered"                    # one of TRAFFIC_KINDS


def scene_for(index: int, seed: int, sim: Simulator,
              opts: TrafficOptions) -> tuple[int, SensorPose, list[PlacedCar]]:
    """The background, ego pose and traffic of training scan `index` (deterministic)."""
    bg_id = opts.first_background + (index // SCANS_PER_BACKGROUND) % opts.backgrounds
    if opts.traffic == "drive":
        from falsify.data.traffic import drive_scene

        return (bg_id, *drive_scene(index, seed, sim, bg_id, opts.max_cars))
    if opts.traffic != "scattered":
        raise ConfigError(f"--traffic: {opts.traffic!r} is not one of {list(TRAFFIC_KINDS)}")
    rng = np.random.default_rng([seed, index])
    bg = sim.background(bg_id)[1]
    half = float(getattr(bg, "road_half_width", 9.0))
    def draw() -> SensorPose:
        # Any lane, up to beside the parked cars, so the roadside is seen from close by too.
        lane = rng.uniform(-(half - 3.3), half - 3.3)
        heading = rng.normal(0.0, 2.0) + (180.0 if rng.random() < 0.3 else 0.0)
        ego_x = rng.uniform(*EGO_X_FORWARD) if heading < 90 else rng.uniform(*EGO_X_BACKWARD)
        return SensorPose(ego_x, lane, heading)

    pose, ego = free_ego(sim, bg_id, draw, f"scan {index}")
    ego_x, heading = pose.x, pose.heading_deg
    obstacles = sim.obstacles(bg_id)
    forward = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
    placed: list[PlacedCar] = []
    outlines: list[np.ndarray] = []
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
            check_placement([*placed, car], [*outlines, outline], obstacles, ego)
        except InvalidSample:
            continue
        placed.append(car)
        outlines.append(outline)
    return bg_id, pose, [sim.settle(bg_id, c) for c in placed]


def write_dataset(sensor: Sensor, out: Path, scans: int, seed: int = 0,
                  opts: TrafficOptions = TrafficOptions(), start: int = 0,
                  on_progress: Callable[[int, int], None] | None = None,
                  weather: Space | None = None) -> dict:
    """Write scans start..scans-1 as NNNNNN.npy (skipping ones already there) plus index.json.
    With `weather`, each scan draws its weather and faults from that space's effect dims (a
    training set that sees what the falsification space tests); without, scans are clear."""
    if scans <= 0:
        raise ConfigError(f"--scans: {scans} must be > 0")
    out.mkdir(parents=True, exist_ok=True)
    sim = Simulator(sensor, max_bvh=1, max_hits=8)
    drawn = [] if weather is None else [d for d in EFFECT_DIMS if d in weather.dims]
    counts = np.zeros(len(CLASSES), np.int64)
    written = 0
    for i in range(start, scans):
        path = out / f"{i:06d}.npy"
        if path.exists():
            continue
        bg_id, pose, placed = scene_for(i, seed, sim, opts)
        rng = np.random.default_rng([seed, i, 1])
        effects = (None if not drawn else
                   draw_effects(weather, np.random.default_rng([seed, i, 3])))
        scan = sim.render(bg_id, placed, pose, rng, effects=effects)
        write_npy(path, scan.image)
        lab = scan.image[..., 5][scan.valid].astype(np.int64)
        counts += np.bincount(lab, minlength=len(CLASSES))[:len(CLASSES)]
        written += 1
        if on_progress is not None and written % 50 == 0:
            on_progress(i + 1, scans)
    index = {"scans": scans, "seed": seed, "sensor": sensor.name,
             "first_background": opts.first_background, "backgrounds": opts.backgrounds,
             "max_cars": opts.max_cars, "ray_drop": sensor.ray_drop,
             "range_noise": sensor.range_noise}
    if opts.traffic != "scattered":  # scattered sets keep their index byte for byte
        index["traffic"] = opts.traffic
    if drawn:   # so do clear sets
        index["effects"] = {d: _drawn_from(weather.dims[d]) for d in drawn}
    write_json(out / "index.json", index)
    return {**index, "written": written, "points_per_class": dict(
        zip(CLASSES, counts.tolist(), strict=True))}


def traffic_scans(sensor: Sensor, n: int, seed: int, opts: TrafficOptions,
                  stride: int) -> np.ndarray:
    """Range images (n, H, W, 6) of training-style scenes `0, stride, 2 * stride, ...`, without
    sensor noise: the synthetic scans used for calibration and held-out checks."""
    sim = Simulator(sensor, max_bvh=1, max_hits=1)
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
