"""The objects under test a space may place besides the car models (the `actor` dim): people in
four poses, riders, a riderless bicycle and the large vehicles, each with its mesh and the raw
SemanticKITTI id its points carry.

Labels follow SemanticKITTI: a rider and the bicycle or motorbike under them are one bicyclist
or motorcyclist (as our streets' cyclists are), a bicycle without rider is bicycle, the large
vehicles truck, bus and other-vehicle. The four-class view follows from falsify.semantic.kitti4
(person -> pedestrian, bicyclist and motorcyclist -> cyclist, the rest unknown). Frames as in
falsify.world.cars: origin at the footprint centre on the ground, +x forward.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from falsify.semantic import RAW_ID
from falsify.world import shapes
from falsify.world.materials import mid
from falsify.world.road_users import (
    OTHER_VEHICLE_SEMANTIC,
    Part,
    bicycle_parts,
    merge_parts,
    vehicle_model,
)

# Where an actor may stand (`[dims.actor] on = ...`): any surface, the road (road or parking
# in SemanticKITTI's labels), or the sidewalk.
SURFACES: tuple[str, ...] = ("any", "road", "sidewalk")


@dataclass(frozen=True)
class ActorKind:
    """A built-in actor: the raw SemanticKITTI id of its points, whether it may stand beyond a
    street's kerb (people and bicycles: the kerb's outline stops vehicles only) and how its mesh
    is made."""

    semantic: int
    crosses_kerbs: bool
    build: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]


def _person(height: float, stride: float, arm_swing: float, lean: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v, f = shapes.person(height, stride, arm_swing)
    if lean:   # a runner leans into the stride
        c, s = np.cos(lean), np.sin(lean)
        v = v @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]).T
    return merge_parts([(v, f, mid("clothing"))])


def _cyclist() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v, f = shapes.cyclist(1.75)
    return merge_parts([(v, f, mid("clothing"))])


def _bicycle() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return merge_parts(bicycle_parts(np.random.default_rng(11)))


def motorcyclist_parts() -> list[Part]:
    """A motorbike (wheels, engine, tank, seat, fork and bar) along +x with a helmeted rider."""
    r = 0.31
    rear, front = np.array([-0.72, 0.0, r]), np.array([0.72, 0.0, r])
    parts: list[Part] = [(*shapes.torus(c, [0, 1, 0], r - 0.06, 0.06, 20, 8), mid("rubber"))
                         for c in (rear, front)]
    parts += [
        (*shapes.oriented_box([-0.05, 0.0, 0.45], [0.6, 0.32, 0.35]), mid("metal")),   # engine
        (*shapes.oriented_box([0.2, 0.0, 0.78], [0.5, 0.3, 0.2]), mid("paint mid")),   # tank
        (*shapes.oriented_box([-0.4, 0.0, 0.78], [0.55, 0.28, 0.12]), mid("rubber")),  # seat
        (*shapes.oriented_box([-0.75, 0.0, 0.7], [0.35, 0.2, 0.1]), mid("paint mid")),  # tail
        (*shapes.cylinder(front, [0.5, 0.0, 1.0], 0.03, 6), mid("metal")),             # fork
        (*shapes.cylinder(rear, [-0.1, 0.0, 0.45], 0.03, 6), mid("metal")),            # swingarm
        (*shapes.cylinder([0.5, -0.35, 1.02], [0.5, 0.35, 1.02], 0.02, 6), mid("metal")),
    ]
    hip = np.array([-0.35, 0.0, 0.9])
    shoulder = np.array([0.0, 0.0, 1.42])
    for side in (1.0, -1.0):
        knee = np.array([0.1, side * 0.22, 0.75])
        peg = np.array([-0.15, side * 0.2, 0.35])
        parts.append((*shapes.cylinder(hip + [0, side * 0.11, 0], knee, 0.08, 6, 0.065),
                      mid("clothing")))
        parts.append((*shapes.cylinder(knee, peg, 0.06, 6, 0.05), mid("clothing")))
        parts.append((*shapes.cylinder(shoulder + [0, side * 0.2, 0], [0.5, side * 0.3, 1.02],
                                       0.05, 6, 0.045), mid("clothing")))
    middle = (hip + shoulder) / 2
    lean = np.arctan2(shoulder[2] - hip[2], shoulder[0] - hip[0])
    tv, tf = shapes.oriented_box([0, 0, 0], [float(np.linalg.norm(shoulder - hip)) + 0.1,
                                             0.4, 0.24])
    c, s = np.cos(lean), np.sin(lean)
    parts.append((tv @ np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]).T + middle, tf,
                  mid("clothing")))
    parts.append((*shapes.icosphere(shoulder + [0.1, 0.0, 0.24], 0.15, 1), mid("paint dark")))
    return parts


def _vehicle(kind: str) -> Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    return lambda: tuple(a.copy() for a in vehicle_model(kind))


BUILTIN_ACTORS: dict[str, ActorKind] = {
    "pedestrian": ActorKind(RAW_ID["person"], True, lambda: _person(1.75, 0.08, 0.05)),
    "pedestrian-walking": ActorKind(RAW_ID["person"], True, lambda: _person(1.75, 0.6, 0.25)),
    "pedestrian-running": ActorKind(RAW_ID["person"], True,
                                    lambda: _person(1.75, 1.0, 0.45, lean=0.15)),
    "child": ActorKind(RAW_ID["person"], True, lambda: _person(1.15, 0.35, 0.15)),
    "cyclist": ActorKind(RAW_ID["bicyclist"], True, _cyclist),
    "bicycle": ActorKind(RAW_ID["bicycle"], True, _bicycle),
    "motorcyclist": ActorKind(RAW_ID["motorcyclist"], False,
                              lambda: merge_parts(motorcyclist_parts())),
    "truck": ActorKind(RAW_ID["truck"], False, _vehicle("box truck")),
    "bus": ActorKind(RAW_ID["bus"], False, _vehicle("bus")),
    "other-vehicle": ActorKind(RAW_ID["other-vehicle"], False, _vehicle("trailer")),
}
ACTOR_NAMES: tuple[str, ...] = tuple(BUILTIN_ACTORS)
# Raw ids of what may stand beyond a kerb, built in or a user's mesh of that class.
KERB_CROSSING_IDS: frozenset[int] = frozenset(
    RAW_ID[n] for n in ("person", "bicyclist", "bicycle", "moving-person", "moving-bicyclist"))


@functools.cache
def actor_model(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A built-in actor's vertices, faces and per-face material (read-only: cached)."""
    v, f, mat = BUILTIN_ACTORS[name].build()
    for a in (v, f, mat):
        a.setflags(write=False)
    return v, f, mat


def model_semantic(model: str, user: Mapping[str, Any] | None = None) -> int:
    """The raw SemanticKITTI id of a model's points: a user mesh's declared class (`user`: the
    space's UserCars by name), a built-in actor's, the other vehicles' kind; else car."""
    if user and model in user:
        return user[model].semantic
    if model in OTHER_VEHICLE_SEMANTIC:
        return OTHER_VEHICLE_SEMANTIC[model]
    if model in BUILTIN_ACTORS:
        return BUILTIN_ACTORS[model].semantic
    return RAW_ID["car"]
