"""SemanticKITTI's label set: raw ids as `.label` files hold them, the 19-class learning map that
networks are trained and scored on, and the four-class view (unknown, car, pedestrian, cyclist)
that the SqueezeSeg networks use.

Ids and the learning map are those of SemanticKITTI's `semantic-kitti.yaml` (Behley et al.,
"SemanticKITTI: A Dataset for Semantic Scene Understanding of LiDAR Sequences", ICCV 2019).
A `.label` value is `instance << 16 | semantic` (uint32).
"""

from __future__ import annotations

import numpy as np

from falsify.classes import CAR, CYCLIST, PEDESTRIAN

# Raw SemanticKITTI ids and their names (moving-* ids are the moving versions of the same class).
RAW_NAMES: dict[int, str] = {
    0: "unlabeled", 1: "outlier", 10: "car", 11: "bicycle", 13: "bus", 15: "motorcycle",
    16: "on-rails", 18: "truck", 20: "other-vehicle", 30: "person", 31: "bicyclist",
    32: "motorcyclist", 40: "road", 44: "parking", 48: "sidewalk", 49: "other-ground",
    50: "building", 51: "fence", 52: "other-structure", 60: "lane-marking", 70: "vegetation",
    71: "trunk", 72: "terrain", 80: "pole", 81: "traffic-sign", 99: "other-object",
    252: "moving-car", 253: "moving-bicyclist", 254: "moving-person", 255: "moving-motorcyclist",
    256: "moving-on-rails", 257: "moving-bus", 258: "moving-truck", 259: "moving-other-vehicle",
}
RAW_ID: dict[str, int] = {name: i for i, name in RAW_NAMES.items()}

# The 19 classes networks are trained on (index 0 is "unlabeled", ignored in scoring).
TRAIN_CLASSES: tuple[str, ...] = (
    "unlabeled", "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist",
    "motorcyclist", "road", "parking", "sidewalk", "other-ground", "building", "fence",
    "vegetation", "trunk", "terrain", "pole", "traffic-sign",
)
TRAIN_ID: dict[str, int] = {name: i for i, name in enumerate(TRAIN_CLASSES)}

_LEARNING_MAP: dict[int, str] = {
    0: "unlabeled", 1: "unlabeled", 10: "car", 11: "bicycle", 13: "other-vehicle",
    15: "motorcycle", 16: "other-vehicle", 18: "truck", 20: "other-vehicle", 30: "person",
    31: "bicyclist", 32: "motorcyclist", 40: "road", 44: "parking", 48: "sidewalk",
    49: "other-ground", 50: "building", 51: "fence", 52: "unlabeled", 60: "road",
    70: "vegetation", 71: "trunk", 72: "terrain", 80: "pole", 81: "traffic-sign",
    99: "unlabeled", 252: "car", 253: "bicyclist", 254: "person", 255: "motorcyclist",
    256: "other-vehicle", 257: "other-vehicle", 258: "truck", 259: "other-vehicle",
}
# raw id (0..259) -> train id; ids the map does not name are unlabeled
LEARNING_MAP = np.zeros(260, np.uint8)
for _raw, _name in _LEARNING_MAP.items():
    LEARNING_MAP[_raw] = TRAIN_ID[_name]

# raw id -> the SqueezeSeg networks' four classes (motorcyclists count as cyclists there)
_KITTI4 = {10: CAR, 252: CAR, 30: PEDESTRIAN, 254: PEDESTRIAN, 31: CYCLIST, 253: CYCLIST,
           32: CYCLIST, 255: CYCLIST}
KITTI4_OF_RAW = np.zeros(260, np.uint8)
for _raw, _cls in _KITTI4.items():
    KITTI4_OF_RAW[_raw] = _cls

# train id -> the four SqueezeSeg classes, as KITTI4_OF_RAW maps the raw ids behind each
_KITTI4_OF_TRAIN = {"car": CAR, "person": PEDESTRIAN, "bicyclist": CYCLIST, "motorcyclist": CYCLIST}
KITTI4_OF_TRAIN = np.zeros(len(TRAIN_CLASSES), np.uint8)
for _name, _cls in _KITTI4_OF_TRAIN.items():
    KITTI4_OF_TRAIN[TRAIN_ID[_name]] = _cls


def split_label(label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A `.label` array (uint32) -> (semantic raw id uint16, instance uint16)."""
    label = np.asarray(label, np.uint32)
    return (label & 0xFFFF).astype(np.uint16), (label >> 16).astype(np.uint16)


def join_label(semantic: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Raw semantic ids and instance ids -> `.label` values (uint32)."""
    return (np.asarray(instance, np.uint32) << 16) | np.asarray(semantic, np.uint32)


def _wide(table: np.ndarray) -> np.ndarray:
    """The table over every uint16 raw id (0 past its end): a scan's raw ids index it as they
    are, with no range check (a per-scan cost of the per-class return model)."""
    out = np.zeros(1 << 16, table.dtype)
    out[:len(table)] = table
    return out


_LEARNING_WIDE = _wide(LEARNING_MAP)
_KITTI4_WIDE = _wide(KITTI4_OF_RAW)


def _lookup(wide: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """`wide` at each raw id; ids outside it (negative, or past uint16) read entry 0."""
    raw = np.asarray(raw)
    if raw.dtype in (np.uint8, np.uint16):
        return wide.take(raw)
    return wide[np.where((raw >= 0) & (raw < len(wide)), raw, 0)]


def train_ids(raw: np.ndarray) -> np.ndarray:
    """Raw SemanticKITTI ids -> train ids 0..19 (unknown raw ids: 0, unlabeled)."""
    return _lookup(_LEARNING_WIDE, raw)


def kitti4(raw: np.ndarray) -> np.ndarray:
    """Raw SemanticKITTI ids -> the four SqueezeSeg classes (0 unknown, 1 car, 2 pedestrian,
    3 cyclist)."""
    return _lookup(_KITTI4_WIDE, raw)


def kitti4_of_train(train: np.ndarray) -> np.ndarray:
    """Train ids 0..19 -> the four SqueezeSeg classes (ids outside 0..19: 0, unknown)."""
    t = np.asarray(train).astype(np.int64)
    return KITTI4_OF_TRAIN[np.where((t >= 0) & (t < len(KITTI4_OF_TRAIN)), t, 0)]
