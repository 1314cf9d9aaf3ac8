"""Insertion faithfulness over SemanticKITTI's labelled instances: each real car or person of a
scan against a built-in actor of its class inserted in its place, scored by the same network
over the same pixels (falsify.jobs.faithfulness does the same for KITTI object boxes).

Per instance of a scored class with at least `min_points` points, in a view of its own (the scan
turned so that the instance lies straight ahead: a front-view sensor then sees every instance of
the 360-degree scan) and with MIN_PIXELS pixels there, two arms:
- real: the scan as read; the label is the instance's pixels;
- inserted: the instance's points leave the range image, the cloud and the ground set (a
  SemanticKITTI instance is labelled point by point: no box to grow), then a built-in actor of
  its class is cast at its pose by RealScanner.insert; the label is the inserted pixels.
Pose, from the instance's points alone: heading along the longer side of the rectangle fitted
to their footprint (L-shape fitting, footprint_axis); centre from their extent along that axis
and across it, completed amodally where the points span less than the model (a car seen from
one side shows one face: the centre lies half the model's size behind the face nearest the
sensor); standing on the ground fitted under it.
Scored pixels: every row of the columns the inserted actor spans, less the pixels of the scan's
other instances of the same class.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from falsify.classes import CAR, PEDESTRIAN
from falsify.classes import CLASSES as FOUR_CLASSES
from falsify.data.real_backgrounds import (
    INSERTED_INSTANCE,
    PointIndex,
    RealBackground,
    RealScanner,
    fit_ground,
)
from falsify.data.real_backgrounds.ground import ground_points
from falsify.data.velodyne import read_bin
from falsify.errors import FalsifyError
from falsify.fileio import file_sha256
from falsify.jobs.faithfulness import Arms, Pooled, Spread, _rounded, pool, score_arm
from falsify.models.runners import Segmenter
from falsify.rotations import rot_z
from falsify.semantic import TRAIN_ID, split_label
from falsify.sensor.lidar import Sensor
from falsify.sensor.scan import Scan
from falsify.sensor.simulator import FIRST_CAR_INSTANCE, PlacedCar
from falsify.world.cars import BUILTIN_MODELS, car_dimensions, car_mesh
from falsify.world.real_scans import real_scans
from falsify.world.space import RealScan

SEED = 0
MIN_POINTS = 30     # an instance with fewer cloud points is too sparse to pose
MIN_PIXELS = 20     # nor one with fewer pixels in the sensor's image (out of view)
# The classes scored: raw SemanticKITTI ids (static and moving) and the four-class id predicted.
CLASSES: dict[str, tuple[tuple[int, ...], int]] = {"car": ((10, 252), CAR),
                                                   "person": ((30, 254), PEDESTRIAN)}
CHILD_HEIGHT_M = 1.35    # a person whose top is lower than this above the ground: the child model
# The most an instance's points may span (along, across): beyond it the id joins several objects
# or holds stray points, and no one pose fits; such an instance is skipped and named.
MAX_SPAN_M = {"car": (7.0, 3.0), "person": (1.6, 1.6)}
WALKING_SPAN_M = 0.45    # a person whose footprint spans more than this along its axis walks
POSE = ("heading along the footprint's fitted rectangle; centre completed amodally from the "
        "extent nearest the sensor; on the ground fitted under it")


@dataclass(frozen=True)
class InstanceRow(Arms):
    """One real labelled instance and the built-in actor inserted in its place."""

    frame: str                    # the scan, and the view's azimuth
    instance: int                 # SemanticKITTI instance id in the scan
    cls: str                      # "car" or "person"
    distance_m: float             # horizontal distance of the inserted actor's origin
    extent_lwh: tuple[float, float, float]   # the points' span along, across and up
    model: str
    model_lwh: tuple[float, float, float]
    heading_deg: float
    removed_points: int


@dataclass(frozen=True)
class ClassSummary:
    """A class's pooled scores and its mean per-instance IoU difference with a 95 % interval
    (Student's t on n - 1 degrees of freedom)."""

    pooled: Pooled
    ci95: tuple[float, float] | None


@dataclass(frozen=True)
class InstanceFaithfulness:
    """Every scored instance's row and each class's summary, with the settings behind them."""

    scans: tuple[str, ...]
    sensor: str
    model: str
    model_hash: str
    min_points: int
    seed: int
    pose: str
    rows: tuple[InstanceRow, ...]
    classes: dict[str, ClassSummary]
    skipped: tuple[tuple[str, str, int, str], ...]   # (scan, class, instance, why)

    def to_json(self) -> dict:
        out = asdict(self)
        for row, d in zip(self.rows, out["rows"], strict=True):
            d["iou_difference"] = row.iou_difference
        return _rounded(out)


def interval95(spread: Spread) -> tuple[float, float] | None:
    """Mean +- t(0.975, n - 1) x standard error; None under two values."""
    from falsify.sampler.level_set import t_quantile
    if spread.n < 2 or spread.sem is None or spread.mean is None:
        return None
    half = t_quantile(1.959963984540054, spread.n - 1) * spread.sem
    return spread.mean - half, spread.mean + half


def semantic_scans(paths: list[Path], sequences: list[str] | None) -> list[RealScan]:
    """The labelled SemanticKITTI scans the paths name; FalsifyError names one without labels."""
    found = [RealScan(*r) for r in real_scans([str(p) for p in paths], sequences)]
    bare = [r for r in found if r.kind != "semantickitti"]
    if bare:
        raise FalsifyError(f"{bare[0].bin}: no SemanticKITTI .label beside it or in ../labels/ "
                           "(instance faithfulness needs every point labelled)")
    return found


def person_model(extent: tuple[float, float, float]) -> str:
    """The built-in person nearest the points (extent: along, across, top above the ground):
    child under CHILD_HEIGHT_M, walking when the footprint spans more than WALKING_SPAN_M
    along its axis, else standing."""
    if extent[2] < CHILD_HEIGHT_M:
        return "child"
    return "pedestrian-walking" if extent[0] > WALKING_SPAN_M else "pedestrian"


def car_model(extent: tuple[float, float, float]) -> str:
    """The built-in car nearest in height (its top above the ground), and in length too where
    the points span most of a car's length (a car seen end-on shows no length)."""
    def cost(m: str) -> tuple[float, str]:
        length, _, height = model_size(m)
        c = abs(height - extent[2])
        if extent[0] >= 3.0:
            c += abs(length - extent[0])
        return c, m
    return min(BUILTIN_MODELS, key=cost)


def model_size(model: str) -> tuple[float, float, float]:
    """Length, width and height of a built-in model's body (no mirrors)."""
    if model in BUILTIN_MODELS:
        return car_dimensions(car_mesh(model, lod=0))
    from falsify.world.actors import actor_model
    v = actor_model(model)[0]
    size = v.max(axis=0) - v.min(axis=0)
    return float(size[0]), float(size[1]), float(size[2])


def footprint_axis(xy: np.ndarray, step_deg: float = 1.0, d0: float = 0.01) -> np.ndarray:
    """The unit direction of the longer side of the rectangle that best fits a footprint seen
    from one side: the closeness criterion of L-shape fitting (Zhang et al., "Efficient L-Shape
    Fitting for Vehicle Detection Using Laser Scanners", IEEE IV 2017): over rectangle angles
    in [0, 90) degrees, the one whose points lie nearest its edges (sum of 1 / max(d, d0))."""
    best, best_score = 0.0, -1.0
    for theta in np.radians(np.arange(0.0, 90.0, step_deg)):
        e1 = np.array([math.cos(theta), math.sin(theta)])
        c1, c2 = xy @ e1, xy @ np.array([-e1[1], e1[0]])
        d1 = np.minimum(c1 - c1.min(), c1.max() - c1)
        d2 = np.minimum(c2 - c2.min(), c2.max() - c2)
        score = float((1.0 / np.maximum(np.minimum(d1, d2), d0)).sum())
        if score > best_score:
            best, best_score = theta, score
    e1 = np.array([math.cos(best), math.sin(best)])
    e2 = np.array([-e1[1], e1[0]])
    return e1 if np.ptp(xy @ e1) >= np.ptp(xy @ e2) else e2


def instance_pose(points: np.ndarray, cls: str, ground_z: float
                  ) -> tuple[str, float, float, float, tuple[float, float, float]]:
    """(model, x, y, heading in degrees, extent) of a built-in actor standing where `points`
    (N x 3, the instance's) are, on ground at `ground_z`: see the module's docstring. Extent:
    the points' span along and across the axis, and their top above the ground."""
    xy = points[:, :2].astype(np.float64)
    mean = xy.mean(axis=0)
    axis = footprint_axis(xy - mean)
    if axis[0] < 0 or (axis[0] == 0 and axis[1] < 0):   # one of the two, fixed
        axis = -axis
    across = np.array([-axis[1], axis[0]])
    u, c = (xy - mean) @ axis, (xy - mean) @ across
    extent = (float(np.ptp(u)), float(np.ptp(c)), float(points[:, 2].max()) - ground_z)
    model = car_model(extent) if cls == "car" else person_model(extent)
    length, width, _ = model_size(model)
    centre = mean.copy()
    for direction, values, size in ((axis, u, length), (across, c, width)):
        lo, hi = float(values.min()), float(values.max())
        mid = (lo + hi) / 2
        if hi - lo < size:   # seen from one side: keep the face nearest the sensor
            away = float(direction @ mean) >= 0   # the sensor is at the origin
            mid = lo + size / 2 if away else hi - size / 2
        centre = centre + direction * mid
    heading = math.degrees(math.atan2(axis[1], axis[0]))
    return model, float(centre[0]), float(centre[1]), heading, extent


def without_instance(bg: RealBackground, xyz: np.ndarray, sem: np.ndarray, gone: np.ndarray,
                     pixels: np.ndarray, max_range: float) -> RealBackground:
    """The background with the instance's cloud points (`gone`) and pixels removed: the
    pixels empty (their rays reach max_range), cloud and ground rebuilt from the rest."""
    image = bg.scan.image.copy()
    inst = bg.scan.instance.copy()
    s = None if bg.scan.semantic is None else bg.scan.semantic.copy()
    image[pixels] = 0.0
    inst[pixels] = 0
    if s is not None:
        s[pixels] = 0
    valid = bg.valid & ~pixels
    dist = np.where(pixels, max_range, bg.dist)
    keep = ~gone
    return replace(bg, scan=Scan(image, inst, s), dist=dist, valid=valid,
                   cloud=PointIndex.of(xyz[keep], sem[keep]),
                   ground=PointIndex.of(ground_points(xyz[keep], sem[keep]).astype(np.float64)))


def run_instance_faithfulness(paths: list[Path], sequences: list[str] | None, sensor: Sensor,
                              segmenter: Segmenter, min_points: int = MIN_POINTS,
                              seed: int = SEED) -> InstanceFaithfulness:
    """Both arms for every scored instance of the labelled scans, each in its own view."""
    ids = predicted_ids(segmenter)
    scans = semantic_scans(paths, sequences)
    views = instance_views(scans, min_points)
    scanner = RealScanner(sensor, tuple(v.scan for v in views), max_backgrounds=1)
    rows: list[InstanceRow] = []
    skipped: list[tuple[str, str, int, str]] = []
    for k, view in enumerate(views):
        row = instance_row(scanner, k, view, segmenter, ids, seed, skipped)
        if row is not None:
            rows.append(row)
    classes = {}
    for cls in CLASSES:
        mine = [r for r in rows if r.cls == cls]
        p = pool(mine)
        classes[cls] = ClassSummary(p, interval95(p.iou_difference))
    return InstanceFaithfulness(tuple(s.name for s in scans), sensor.name, segmenter.spec.name,
                                segmenter.model_hash, min_points, seed, POSE, tuple(rows),
                                classes, tuple(skipped))


@dataclass(frozen=True)
class View:
    """One instance to score and the scan turned so that it lies straight ahead."""

    scan: RealScan
    source: str       # the scan's own name
    cls: str
    instance: int


def instance_views(scans: list[RealScan], min_points: int) -> list[View]:
    """Per scan, every instance of a scored class with at least `min_points` points, and the
    scan turned by minus the points' mean azimuth (a front-view sensor sees any of the 360
    degrees: all of a scan's instances count, not only those ahead)."""
    out = []
    for real in scans:
        pts = read_bin(real.bin)
        finite = np.isfinite(pts).all(axis=1)
        xyz = pts[finite, :3].astype(np.float64)
        sem, inst = split_label(np.fromfile(real.label, np.uint32)[finite])
        for cls, (raw_ids, _) in CLASSES.items():
            of_class = np.isin(sem, raw_ids)
            for i in np.unique(inst[of_class & (inst > 0)]):
                mine = of_class & (inst == i)
                if mine.sum() < min_points:
                    continue
                az = math.degrees(math.atan2(xyz[mine, 1].sum(), xyz[mine, 0].sum()))
                turn = round(-az, 2)
                out.append(View(replace(real, name=f"{real.name}@{az:+.0f}", yaw_deg=turn),
                                real.name, cls, int(i)))
    return out


def predicted_ids(segmenter: Segmenter) -> dict[str, int]:
    """The id the network's predictions give each scored class: our four classes' (car,
    pedestrian) or SemanticKITTI's train ids (car, person); FalsifyError names a network that
    predicts neither."""
    names = set(segmenter.spec.classes)
    if names <= set(FOUR_CLASSES):
        return {cls: four for cls, (_, four) in CLASSES.items()}
    missing = [n for n in CLASSES if n not in names]
    if missing:
        raise FalsifyError(f"{segmenter.spec.name}: predicts no {missing[0]}; instance "
                           "faithfulness scores car and person")
    return {cls: TRAIN_ID[cls] for cls in CLASSES}


def instance_row(scanner: RealScanner, k: int, view: View, segmenter: Segmenter,
                 ids: dict[str, int], seed: int, skipped: list[tuple[str, str, int, str]]
                 ) -> InstanceRow | None:
    """The row of view `k`: its instance removed and a built-in actor inserted in its place,
    both scans predicted in one batch; None (and a line in `skipped`) where the instance is too
    small in view or too wide for one object."""
    real = scanner.real[k]
    bg = scanner.background(k)
    raw_ids, _ = CLASSES[view.cls]
    pts = read_bin(real.bin)
    finite = np.isfinite(pts).all(axis=1)
    xyz = pts[finite, :3].astype(np.float64) @ rot_z(real.yaw_deg).T   # as the view turned it
    sem, inst = split_label(np.fromfile(real.label, np.uint32)[finite])
    sem = sem.astype(np.uint16)
    gone = np.isin(sem, raw_ids) & (inst == view.instance)
    pixels = bg.valid & np.isin(bg.scan.semantic, raw_ids) & (bg.scan.instance == view.instance)
    if pixels.sum() < MIN_PIXELS:
        skipped.append((view.source, view.cls, view.instance,
                        f"{int(pixels.sum())} pixels in view, fewer than {MIN_PIXELS}"))
        return None
    removed = without_instance(bg, xyz, sem, gone, pixels, scanner.sensor.max_range)
    centre = xyz[gone, :2].mean(axis=0)
    ground_z, _, _ = fit_ground(removed.ground, float(centre[0]), float(centre[1]), 1.5,
                                -scanner.sensor.mount_height)
    model, x, y, heading, extent = instance_pose(xyz[gone], view.cls, ground_z)
    span = MAX_SPAN_M[view.cls]
    if extent[0] > span[0] or extent[1] > span[1]:
        skipped.append((view.source, view.cls, view.instance,
                        f"its points span {extent[0]:.2f} x {extent[1]:.2f} m, more than one "
                        f"{view.cls} ({span[0]} x {span[1]})"))
        return None
    car = scanner.settle(removed, PlacedCar(model, x, y, heading, FIRST_CAR_INSTANCE))
    # seeded by the scan's content and the instance, not view k's place in the run
    rng = np.random.default_rng([seed, int(file_sha256(real.bin), 16), view.instance,
                                 list(CLASSES).index(view.cls)])
    scan = scanner.insert(removed, [car], rng)
    pred = segmenter.predict(np.stack([bg.scan.image, scan.image]))
    class_id = ids[view.cls]
    columns = np.zeros(bg.valid.shape, bool)
    columns[:, scanner.columns(car)] = True
    others = bg.valid & np.isin(bg.scan.semantic, raw_ids) & ~pixels
    mask = columns & ~others
    ins_label = scan.valid & (scan.instance >= INSERTED_INSTANCE)
    return InstanceRow(
        frame=real.name, instance=view.instance, cls=view.cls,
        distance_m=math.hypot(car.x, car.y), extent_lwh=extent, model=car.model,
        model_lwh=model_size(car.model), heading_deg=car.heading_deg,
        removed_points=int(gone.sum()),
        collision_points=int(scanner.body_points(removed.cloud.points, car).sum()),
        real_points=int(pixels.sum()), inserted_points=int(ins_label.sum()),
        scored_pixels=int(mask.sum()), left_out_pixels=int((columns & others).sum()),
        real=score_arm((pred.classes[0] == class_id) & bg.valid, pixels, mask),
        inserted=score_arm((pred.classes[1] == class_id) & scan.valid, ins_label, mask))
