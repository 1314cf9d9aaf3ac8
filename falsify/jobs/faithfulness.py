"""How faithful an inserted car is: the network's car IoU on each real labelled car of KITTI object
frames against its IoU on a synthetic car inserted in that car's place.

Per `Car` box with a 3D extent, two arms over the same pixels (every row of the columns the
inserted car spans, less the pixels of the frame's other labelled cars and vans):
- real: the frame as read; the label is the box's points;
- inserted: the box's points (in the box grown by MARGIN_M on its sides and top; the points
  under it are ground and stay) leave the range image, the cloud and the ground set, then the
  built-in model nearest the box's size is cast at the box's pose by RealScanner.insert; the
  label is the inserted pixels.
The car stands on the box's bottom centre, turned by its rotation_y, with pitch and roll 0: a
KITTI box is upright and its bottom is where the labeller put the ground. The gap between that
bottom and the ground plane fit_ground fits under the car is kept as a diagnostic.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from falsify.classes import CAR
from falsify.data.kitti_object import (
    KittiObject,
    check_labels_have_scans,
    points_in_box,
    read_calib,
    read_labels,
)
from falsify.data.real_backgrounds import (
    INSERTED_INSTANCE,
    RealBackground,
    RealScanner,
    fit_ground,
)
from falsify.data.scansets import check_named_once
from falsify.errors import FalsifyError
from falsify.fileio import file_sha256
from falsify.models.runners import Segmenter
from falsify.results.metrics import confusion
from falsify.sensor.calibration import KittiCalib
from falsify.sensor.lidar import Sensor
from falsify.sensor.scan import Scan
from falsify.sensor.simulator import FIRST_CAR_INSTANCE, PlacedCar
from falsify.world.cars import BUILTIN_MODELS, car_dimensions, car_mesh
from falsify.world.real_scans import is_object_dir, real_scans
from falsify.world.space import RealScan

MARGIN_M = 0.2            # the removed car's box grows this much on its sides and top
SEED = 0                  # the return model's dropouts on an inserted car: seeded per car
#                           by (SEED, the sha256 of its frame's .bin, its box's label line)
SCORED_TYPE = "Car"       # the boxes scored, one row each
LEFT_OUT_TYPES = ("Car", "Van")   # other boxes of these types are neither TP, FP nor FN
POSE = "bottom centre and rotation_y of the box; pitch and roll 0"


@dataclass(frozen=True)
class ArmScore:
    """One arm's car counts over the scored pixels and their ratios (None: empty denominator)."""

    tp: int
    fp: int
    fn: int
    iou: float | None
    recall: float | None
    precision: float | None

    @classmethod
    def of(cls, tp: int, fp: int, fn: int) -> ArmScore:
        def ratio(num: int, den: int) -> float | None:
            return num / den if den else None
        return cls(tp, fp, fn, ratio(tp, tp + fp + fn), ratio(tp, tp + fn), ratio(tp, tp + fp))


@dataclass(frozen=True)
class Arms:
    """What both arms of one object have: the points left in the inserted body, each arm's
    pixels, the pixels scored and left out, and each arm's score."""

    collision_points: int        # cloud points left in the inserted object's body
    real_points: int             # pixels of the real object in the image
    inserted_points: int         # pixels of the inserted object
    scored_pixels: int           # pixels both arms are scored over
    left_out_pixels: int         # pixels of other objects of the class in its columns
    real: ArmScore
    inserted: ArmScore

    @property
    def iou_difference(self) -> float | None:
        """Inserted minus real IoU; None where either is undefined."""
        if self.real.iou is None or self.inserted.iou is None:
            return None
        return self.inserted.iou - self.real.iou


@dataclass(frozen=True)
class CarRow(Arms):
    """One real car and the synthetic car inserted in its place."""

    frame: str                   # object directory / frame id, e.g. "object/000002"
    box: int                     # the box's line in label_2 (0-based)
    distance_m: float            # horizontal distance of the box's bottom centre
    box_lwh: tuple[float, float, float]     # the box's length, width, height (m)
    model: str                   # the built-in model inserted
    model_lwh: tuple[float, float, float]   # its body's length, width, height (no mirrors)
    heading_deg: float           # the inserted car's heading, Velodyne frame
    ground_gap_m: float          # box bottom minus the ground plane fitted under it
    removed_points: int          # cloud points dropped (inside the grown box)


@dataclass(frozen=True)
class Spread:
    """Mean, sample standard deviation, standard error, least and greatest of per-car values."""

    n: int
    mean: float | None
    std: float | None
    sem: float | None
    min: float | None
    max: float | None

    @classmethod
    def of(cls, values: list[float]) -> Spread:
        if not values:
            return cls(0, None, None, None, None, None)
        a = np.asarray(values, np.float64)
        std = float(a.std(ddof=1)) if len(a) > 1 else None
        return cls(len(a), float(a.mean()), std, None if std is None else std / math.sqrt(len(a)),
                   float(a.min()), float(a.max()))


@dataclass(frozen=True)
class Pooled:
    """TP, FP and FN summed over the cars, then divided; per-car differences (inserted - real)."""

    cars: int
    real: ArmScore
    inserted: ArmScore
    iou_difference: Spread
    recall_difference: Spread


@dataclass(frozen=True)
class FaithfulnessResult:
    """Every scored car's row and the pooled summary, with the settings that produced them."""

    directories: tuple[str, ...]
    frames: tuple[str, ...]
    sensor: str
    model: str
    model_hash: str
    margin_m: float
    seed: int
    pose: str
    rows: tuple[CarRow, ...]
    pooled: Pooled

    def to_json(self) -> dict:
        """Plain JSON-ready data: every row (with its IoU difference) and the pooled summary."""
        out = asdict(self)
        for row, d in zip(self.rows, out["rows"], strict=True):
            d["iou_difference"] = row.iou_difference
        return _rounded(out)


@dataclass(frozen=True)
class Insertion:
    """One box's inserted arm: the background with the real car removed and the scan with the
    synthetic car in its place."""

    car: PlacedCar
    removed: RealBackground
    removed_points: int
    scan: Scan
    grown: KittiObject


def object_scans(paths: list[Path]) -> list[RealScan]:
    """The frames of KITTI object directories, in order; FalsifyError naming a path that is
    missing or is not an object directory (velodyne/, label_2/, calib/), and labels whose
    velodyne/ scan is missing (as a scan whose labels are missing is named) or a frame named
    twice (it would count twice)."""
    for p in paths:
        if not p.exists():
            raise FalsifyError(f"{p}: no such folder (expected a KITTI object directory: "
                               "velodyne/, label_2/, calib/)")
        if not p.is_dir() or not is_object_dir(p) or not (p / "calib").is_dir():
            raise FalsifyError(f"{p}: not a KITTI object directory (expected velodyne/, "
                               "label_2/ and calib/ folders)")
        check_labels_have_scans(p)
    found = real_scans([str(p) for p in paths])
    check_named_once([b for _, b, _, _ in found])
    return [RealScan(name, b, label, kind) for name, b, label, kind in found]


def nearest_model(obj: KittiObject) -> tuple[str, tuple[float, float, float]]:
    """The built-in model whose body length, width and height are nearest (Euclidean) the box's,
    and those dimensions. Bodies are measured without mirrors (level of detail 0): KITTI's car
    widths are body widths."""
    h, w, length = obj.dimensions
    best = min(BUILTIN_MODELS, key=lambda m: (float(np.linalg.norm(
        np.subtract(model_dimensions(m), (length, w, h)))), m))
    return best, model_dimensions(best)


def model_dimensions(model: str) -> tuple[float, float, float]:
    """Length, width and height of a built-in model's body (its coarse mesh: no mirrors)."""
    return car_dimensions(car_mesh(model, lod=0))


def grown_box(obj: KittiObject, margin: float = MARGIN_M) -> KittiObject:
    """The box grown by `margin` on its four sides and its top; its bottom stays (the points
    under a car are its ground)."""
    h, w, length = obj.dimensions
    return replace(obj, dimensions=(h + margin, w + 2 * margin, length + 2 * margin))


def rect_to_velo(calib: KittiCalib, p_rect: np.ndarray) -> np.ndarray:
    """Rectified camera-frame points back to the Velodyne frame (velo_to_rect inverted)."""
    a = calib.R0_rect @ calib.Tr_velo_to_cam[:, :3]
    b = calib.R0_rect @ calib.Tr_velo_to_cam[:, 3]
    return np.linalg.solve(a, (np.atleast_2d(p_rect) - b).T).T


def box_pose(obj: KittiObject, calib: KittiCalib, model: str,
             instance: int = FIRST_CAR_INSTANCE) -> PlacedCar:
    """`model` standing on the box's bottom centre, facing along the box's length axis (its
    rotation_y turned into the Velodyne frame), upright."""
    ry = obj.rotation_y
    loc = np.asarray(obj.location, np.float64)
    ends = rect_to_velo(calib, np.stack([loc, loc + (math.cos(ry), 0.0, -math.sin(ry))]))
    fwd = ends[1] - ends[0]
    x, y, z = (float(v) for v in ends[0])
    return PlacedCar(model, x=x, y=y, heading_deg=math.degrees(math.atan2(fwd[1], fwd[0])),
                     instance=instance, z=z)


def in_box(points: np.ndarray, box: KittiObject, calib: KittiCalib) -> np.ndarray:
    """points_in_box, testing only the points within the box's half diagonal of its centre
    (a whole cloud through the calibration is the slow part)."""
    h, w, length = box.dimensions
    centre = rect_to_velo(calib, np.asarray(box.location) - (0.0, h / 2, 0.0))[0]
    radius = 0.5 * math.sqrt(h * h + w * w + length * length) + 1e-3
    near = np.flatnonzero(((np.asarray(points, np.float64) - centre) ** 2).sum(axis=1)
                          <= radius * radius)
    out = np.zeros(len(points), bool)
    out[near] = points_in_box(np.asarray(points[near], np.float64), box, calib)
    return out


def remove_box(bg: RealBackground, box: KittiObject, calib: KittiCalib, max_range: float
               ) -> tuple[RealBackground, int]:
    """The background without the points inside `box`: their pixels empty (each keeps its ray's
    direction; its ray now reaches `max_range`), and gone from the cloud and the ground set;
    and how many cloud points went."""
    image = bg.scan.image.copy()
    inst = bg.scan.instance.copy()
    sem = None if bg.scan.semantic is None else bg.scan.semantic.copy()
    rows, cols = np.nonzero(bg.valid)
    inside = in_box(image[rows, cols, 0:3], box, calib)
    rows, cols = rows[inside], cols[inside]
    image[rows, cols] = 0.0
    inst[rows, cols] = 0
    if sem is not None:
        sem[rows, cols] = 0
    valid = bg.valid.copy()
    valid[rows, cols] = False
    dist = bg.dist.copy()
    dist[rows, cols] = max_range
    in_cloud = in_box(bg.cloud.points, box, calib)
    removed = replace(bg, scan=Scan(image, inst, sem), dist=dist, valid=valid,
                      cloud=bg.cloud.subset(~in_cloud),
                      ground=bg.ground.subset(~in_box(bg.ground.points, box, calib)))
    return removed, int(in_cloud.sum())


def insert_in_place(scanner: RealScanner, bg: RealBackground, obj: KittiObject,
                    calib: KittiCalib, rng: np.random.Generator | None,
                    margin: float = MARGIN_M) -> Insertion:
    """The inserted arm of one box: its real car removed, the nearest built-in model cast at
    its pose."""
    model, _ = nearest_model(obj)
    car = box_pose(obj, calib, model)
    grown = grown_box(obj, margin)
    removed, n = remove_box(bg, grown, calib, scanner.sensor.max_range)
    return Insertion(car, removed, n, scanner.insert(removed, [car], rng), grown)


def score_arm(pred_car: np.ndarray, label: np.ndarray, scored: np.ndarray) -> ArmScore:
    """Car TP, FP and FN over the `scored` pixels (all (H, W) bool)."""
    counts = confusion(pred_car[scored].astype(np.uint8), label[scored].astype(np.uint8), 2)
    tp, fp, fn = (int(v) for v in counts[1])
    return ArmScore.of(tp, fp, fn)


def run_faithfulness(paths: list[Path], sensor: Sensor, segmenter: Segmenter,
                     margin: float = MARGIN_M, seed: int = SEED) -> FaithfulnessResult:
    """Both arms for every `Car` box with a 3D extent in the object directories' frames."""
    scans = object_scans(paths)
    scanner = RealScanner(sensor, tuple(scans), max_backgrounds=1)
    rows: list[CarRow] = []
    for f in range(len(scans)):
        rows += frame_rows(scanner, f, segmenter, margin, seed)
    return FaithfulnessResult(tuple(str(p) for p in paths), tuple(s.name for s in scans),
                              sensor.name, segmenter.spec.name, segmenter.model_hash, margin,
                              seed, POSE, tuple(rows), pool(rows))


def frame_rows(scanner: RealScanner, f: int, segmenter: Segmenter, margin: float = MARGIN_M,
               seed: int = SEED) -> list[CarRow]:
    """The rows of frame `f` of the scanner's real scans: its real scan and one inserted scan
    per scored box, predicted in one batch. Each car's dropouts are seeded by the frame's
    content and the box's line, so neither the frames beside it nor their order moves them."""
    real = scanner.real[f]
    bg = scanner.background(f)
    if not len(bg.cloud):
        raise FalsifyError(f"{real.bin}: no points (expected N x 4 float32: x, y, z, "
                           "reflectance)")
    calib = read_calib(real.bin.parent.parent / "calib" / f"{real.bin.stem}.txt")
    boxes = read_labels(real.label) if real.label is not None else []
    scored = [k for k, o in enumerate(boxes) if o.type == SCORED_TYPE and o.has_3d]
    if not scored:
        return []
    frame_id = int(file_sha256(real.bin), 16)
    inserted = [insert_in_place(scanner, bg, boxes[k], calib,
                                np.random.default_rng([seed, frame_id, k]), margin)
                for k in scored]
    pred = segmenter.predict(np.stack([bg.scan.image, *(i.scan.image for i in inserted)]))
    car_pred = pred.classes == CAR
    rows = []
    for n, (k, ins) in enumerate(zip(scored, inserted, strict=True), 1):
        others = [j + 1 for j, o in enumerate(boxes)
                  if j != k and o.type in LEFT_OUT_TYPES and o.has_3d]
        columns = np.zeros(bg.scan.valid.shape, bool)
        columns[:, scanner.columns(ins.car)] = True
        left_out = columns & np.isin(bg.scan.instance, others)
        mask = columns & ~left_out
        real_label = bg.scan.valid & (bg.scan.instance == k + 1)
        ins_label = ins.scan.valid & (ins.scan.instance >= INSERTED_INSTANCE)
        car = ins.car
        _, corners = scanner.sim.car_caster(car.model)
        reach = float(np.hypot(*np.abs(corners[:, :2]).max(axis=0)))
        ground_z, _, _ = fit_ground(ins.removed.ground, car.x, car.y, reach,
                                    -scanner.sensor.mount_height)
        h, w, length = boxes[k].dimensions
        rows.append(CarRow(
            frame=real.name, box=k, distance_m=math.hypot(car.x, car.y),
            box_lwh=(length, w, h), model=car.model, model_lwh=model_dimensions(car.model),
            heading_deg=car.heading_deg, ground_gap_m=car.z - ground_z,
            removed_points=ins.removed_points,
            collision_points=int(scanner.body_points(ins.removed.cloud.points, car).sum()),
            real_points=int(real_label.sum()), inserted_points=int(ins_label.sum()),
            scored_pixels=int(mask.sum()), left_out_pixels=int(left_out.sum()),
            real=score_arm(car_pred[0] & bg.scan.valid, real_label, mask),
            inserted=score_arm(car_pred[n] & ins.scan.valid, ins_label, mask)))
    return rows


def pool(rows: list[CarRow]) -> Pooled:
    """Counts summed over the cars, then IoU, recall and precision; per-car differences."""
    def summed(arm: str) -> ArmScore:
        scores = [getattr(r, arm) for r in rows]
        return ArmScore.of(sum(s.tp for s in scores), sum(s.fp for s in scores),
                           sum(s.fn for s in scores))
    recall = [r.inserted.recall - r.real.recall for r in rows
              if r.inserted.recall is not None and r.real.recall is not None]
    return Pooled(len(rows), summed("real"), summed("inserted"),
                  Spread.of([d for r in rows if (d := r.iou_difference) is not None]),
                  Spread.of(recall))


def _rounded(value):
    """Floats rounded to 6 decimals, tuples as lists: stable, readable JSON."""
    if isinstance(value, float):
        return round(value, 6)
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    return value
