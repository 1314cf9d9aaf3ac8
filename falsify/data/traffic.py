"""Traffic like a driving log: the ego drives in a lane, other cars follow lanes or park.

`falsify dataset --traffic drive` draws scenes from this module instead of the scattered
placement in falsify.data.training. Real training sets (KITTI, driving logs) look like this: cars
are lane-aligned, ahead or oncoming at driving distances, parked along the kerbs, and only
rarely close beside the ego or across lanes. A network trained on such scans is the paper's
"network trained on driving data", whose blind spots a systematic test then finds.

Right-hand traffic on the straight road along world x: lanes with y < 0 drive towards +x
(heading 0), lanes with y > 0 towards -x (heading 180); parking strips run along both kerbs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from falsify.sensor import simulator
from falsify.sensor.lidar import SensorPose
from falsify.world.cars import BUILTIN_MODELS

PARKING_STRIP = 2.2     # metres between the kerb and the outermost lane
LANE_WIDTH = (3.0, 3.8)  # a lane is as wide as the road allows within these bounds
# Share of the other cars that drive in a lane, park at a kerb, or do something rare (close
# beside the ego, straddling two lanes, turned): the rest after moving and parked is rare.
MOVING_SHARE = 0.72
PARKED_SHARE = 0.24
HEADING_NOISE_DEG = 2.0   # sigma of a moving car's heading about its lane's direction
LATERAL_NOISE_M = 0.25    # sigma of a moving car's offset from its lane centre
SAME_LANE_GAP = (8.0, 60.0)   # distance to a car in the ego's lane (ahead), metres
OTHER_LANE_MIN_GAP = 6.0      # cars in other lanes keep at least this far ahead or behind
ALONG = (-15.0, 60.0)         # where other cars are drawn along the ego's direction


@dataclass(frozen=True)
class Lanes:
    """The lane centres of a road (y, metres) and their driving direction (+1 = +x)."""

    centres: tuple[float, ...]
    directions: tuple[int, ...]
    width: float
    half_width: float


def lanes_of(road_half_width: float) -> Lanes:
    """Lanes that fill the road between the parking strips, split evenly by the centre line."""
    usable = max(road_half_width - PARKING_STRIP, LANE_WIDTH[0])
    per_side = max(1, int(usable // LANE_WIDTH[0]))
    width = min(usable / per_side, LANE_WIDTH[1])
    centres, directions = [], []
    for k in range(per_side):
        c = (k + 0.5) * width
        centres += [-c, c]
        directions += [1, -1]
    return Lanes(tuple(centres), tuple(directions), float(width), float(road_half_width))


def drive_scene(index: int, seed: int, sim: simulator.Simulator, bg_id: int,
                max_cars: int) -> tuple[SensorPose, list[simulator.PlacedCar]]:
    """The ego pose and traffic of drive scan `index` on background `bg_id` (deterministic)."""
    rng = np.random.default_rng([seed, index, 7])
    bg = sim.background(bg_id)[1]
    lanes = lanes_of(float(getattr(bg, "road_half_width", 9.0)))
    lanes_drawn: list[int] = []

    def draw() -> SensorPose:
        lanes_drawn.append(ego_lane := int(rng.integers(len(lanes.centres))))
        direction = lanes.directions[ego_lane]
        ego_y = lanes.centres[ego_lane] + rng.normal(0.0, LATERAL_NOISE_M / 2)
        heading = (0.0 if direction > 0 else 180.0) + rng.normal(0.0, 1.0)
        span = simulator.EGO_X_FORWARD if direction > 0 else simulator.EGO_X_BACKWARD
        ego_x = rng.uniform(*span)
        return SensorPose(float(ego_x), float(ego_y), float(heading))

    # Stood on the terrain (a bare pose is at z = 0, a metre under the road on a hill, and the
    # scan then sees the road surface as a wall at the bumper) and out of parked buses.
    pose, ego = simulator.free_ego(sim, bg_id, draw, f"drive scan {index}")
    ego_lane, ego_x = lanes_drawn[-1], pose.x
    direction = lanes.directions[ego_lane]
    obstacles = sim.obstacles(bg_id)
    placed: list[simulator.PlacedCar] = []
    outlines: list[np.ndarray] = []
    wanted = int(rng.integers(0, max_cars + 1))
    for _ in range(wanted * 4):
        if len(placed) == wanted:
            break
        car = _other_car(rng, lanes, ego_lane, float(ego_x), direction, 1 + len(placed))
        outline = sim.footprint(car)
        try:
            simulator.check_placement([*placed, car], [*outlines, outline], obstacles, ego=ego)
        except simulator.InvalidSample:
            continue
        placed.append(car)
        outlines.append(outline)
    return pose, [sim.settle(bg_id, c) for c in placed]


def _other_car(rng: np.random.Generator, lanes: Lanes, ego_lane: int, ego_x: float,
               direction: int, instance: int) -> simulator.PlacedCar:
    """One car: in a lane at a driving gap, parked at a kerb, or (rarely) anywhere on the road."""
    model = str(rng.choice(BUILTIN_MODELS))
    kind = rng.random()
    if kind < MOVING_SHARE:
        lane = int(rng.integers(len(lanes.centres)))
        if lane == ego_lane:
            along = rng.uniform(*SAME_LANE_GAP)
        else:
            along = rng.uniform(*ALONG)
            if abs(along) < OTHER_LANE_MIN_GAP:
                along = math.copysign(OTHER_LANE_MIN_GAP, along) + along
        y = lanes.centres[lane] + rng.normal(0.0, LATERAL_NOISE_M)
        heading = (0.0 if lanes.directions[lane] > 0 else 180.0)
        heading += rng.normal(0.0, HEADING_NOISE_DEG)
    elif kind < MOVING_SHARE + PARKED_SHARE:
        side = 1 if rng.random() < 0.5 else -1
        along = rng.uniform(*ALONG)
        y = side * (lanes.half_width - 1.25 - rng.uniform(0.0, 0.3))
        # Parked with the traffic of their side, a few the other way round.
        heading = (180.0 if side > 0 else 0.0) + (180.0 if rng.random() < 0.1 else 0.0)
        heading += rng.normal(0.0, 1.5)
    else:
        along = rng.uniform(-8.0, 40.0)
        y = rng.uniform(-(lanes.half_width - 1.2), lanes.half_width - 1.2)
        heading = (0.0 if y < 0 else 180.0) + rng.normal(0.0, 10.0)
    x = ego_x + direction * along
    return simulator.PlacedCar(model, float(x), float(y), float(math.remainder(heading, 360.0)),
                               instance)
