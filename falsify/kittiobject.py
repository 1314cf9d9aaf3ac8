"""KITTI 3D object frames (velodyne .bin, label_2 boxes, calib) as labelled range images.

A frame's points are labelled from its 3D boxes: inside a `Car` box is car (and a `Pedestrian`
or `Cyclist` box its class); inside a `Van`, `Truck`, `Tram` or `Misc` box, or seen by the left
camera inside a `DontCare` rectangle (DontCare has no 3D box, only a 2D image region), a point
is ignored: it counts for no class. Points the left camera does not see (outside image_2) are
ignored too: KITTI labels only what is in that image. label_2 boxes live in the rectified
camera frame; they are mapped into the Velodyne frame with the inverse of R0_rect · Tr_velo_to_cam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.scan import Scan, image_from_points
from falsify.sensor import Sensor

# label_2 type -> our class id; types in IGNORED count for no class.
LABELLED = {"Car": 1, "Pedestrian": 2, "Person_sitting": 2, "Cyclist": 3}
IGNORED = ("Van", "Truck", "Tram", "Misc", "DontCare")
# Marks an ignored point in the label channel until the image is split into labels and mask.
_IGNORE_ID = 255


@dataclass(frozen=True)
class Box:
    """One label_2 object: type, 2D image box (pixels), 3D size and bottom centre (camera)."""

    kind: str
    bbox: tuple[float, float, float, float]          # left, top, right, bottom
    size: tuple[float, float, float]                 # h, w, l in metres
    location: tuple[float, float, float]             # bottom centre, rectified camera frame
    rotation_y: float                                # about the camera's y (down) axis

    @property
    def has_3d(self) -> bool:
        return min(self.size) > 0


@dataclass(frozen=True)
class Calib:
    """The matrices a frame needs: P2 (3x4), R0_rect (3x3), Tr_velo_to_cam (3x4)."""

    p2: np.ndarray
    r0_rect: np.ndarray
    tr_velo_to_cam: np.ndarray

    @property
    def velo_to_rect(self) -> np.ndarray:
        """4x4: a Velodyne point (homogeneous) into the rectified camera frame."""
        r0 = np.eye(4)
        r0[:3, :3] = self.r0_rect
        tr = np.eye(4)
        tr[:3, :] = self.tr_velo_to_cam
        return r0 @ tr

    @property
    def rect_to_velo(self) -> np.ndarray:
        return np.linalg.inv(self.velo_to_rect)


@dataclass(frozen=True)
class ObjectFrame:
    """A labelled frame: the range image (label channel 0 where ignored) and the ignore mask."""

    name: str
    scan: Scan
    ignore: np.ndarray        # (H, W) bool
    boxes: tuple[Box, ...]


def read_calib(path: Path) -> Calib:
    """Parse a KITTI calib file; FalsifyError naming the file and key when one is missing."""
    values: dict[str, np.ndarray] = {}
    try:
        text = path.read_text()
    except OSError as exc:
        raise FalsifyError(f"{path}: cannot read ({exc.strerror})") from None
    for line in text.splitlines():
        if ":" not in line:
            continue
        key, rest = line.split(":", 1)
        try:
            values[key.strip()] = np.array([float(v) for v in rest.split()], np.float64)
        except ValueError:
            raise FalsifyError(f"{path}: key {key.strip()!r} holds a non-number") from None
    need = {"P2": 12, "R0_rect": 9, "Tr_velo_to_cam": 12}
    for key, n in need.items():
        if key not in values or values[key].size != n:
            raise FalsifyError(f"{path}: key {key!r} with {n} numbers is required "
                               f"(keys found: {', '.join(values) or 'none'})")
    return Calib(values["P2"].reshape(3, 4), values["R0_rect"].reshape(3, 3),
                 values["Tr_velo_to_cam"].reshape(3, 4))


def read_labels(path: Path) -> list[Box]:
    """Parse a label_2 file (15 fields per object)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise FalsifyError(f"{path}: cannot read ({exc.strerror})") from None
    boxes = []
    for n, line in enumerate(text.splitlines(), 1):
        f = line.split()
        if not f:
            continue
        if len(f) < 15:
            raise FalsifyError(f"{path}:{n}: expected 15 fields (type, truncation, occlusion, "
                               f"alpha, 2D box, h w l, x y z, rotation_y), got {len(f)}")
        try:
            v = [float(x) for x in f[1:15]]
        except ValueError:
            raise FalsifyError(f"{path}:{n}: a numeric field is not a number") from None
        if f[0] not in LABELLED and f[0] not in IGNORED:
            allowed = ", ".join([*LABELLED, *IGNORED])
            raise FalsifyError(f"{path}:{n}: unknown object type {f[0]!r}; allowed: {allowed}")
        boxes.append(Box(f[0], tuple(v[3:7]), tuple(v[7:10]), tuple(v[10:13]), v[13]))
    return boxes


def box_frame_velo(box: Box, calib: Calib) -> tuple[np.ndarray, np.ndarray]:
    """The box in the Velodyne frame: centre (3,) and half-axes (3, 3) as columns (length,
    height, width), so that a point p is inside when |solve(axes, p - centre)| <= 1."""
    h, w, length = box.size
    c, s = math.cos(box.rotation_y), math.sin(box.rotation_y)
    rot_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    # camera frame: y points down, the location is the bottom centre
    centre_rect = np.asarray(box.location) + rot_y @ np.array([0.0, -h / 2, 0.0])
    axes_rect = rot_y @ np.diag([length / 2, h / 2, w / 2])
    m = calib.rect_to_velo
    centre = m[:3, :3] @ centre_rect + m[:3, 3]
    return centre, m[:3, :3] @ axes_rect


def box_corners_velo(box: Box, calib: Calib) -> np.ndarray:
    """(8, 3) corners of the box in the Velodyne frame."""
    centre, axes = box_frame_velo(box, calib)
    signs = np.array([[a, b, d] for a in (-1, 1) for b in (-1, 1) for d in (-1, 1)], float)
    return centre + signs @ axes.T


def points_in_box(points: np.ndarray, box: Box, calib: Calib) -> np.ndarray:
    """Bool per Velodyne-frame point: inside the box's 3D volume (boundary included)."""
    centre, axes = box_frame_velo(box, calib)
    local = np.linalg.solve(axes, (np.asarray(points, np.float64)[:, :3] - centre).T)
    return (np.abs(local) <= 1.0 + 1e-9).all(axis=0)


def points_in_image_box(points: np.ndarray, box: Box, calib: Calib) -> np.ndarray:
    """Bool per Velodyne point: in front of the left camera and projected (P2) into the box's
    2D rectangle; how a DontCare region, which has no 3D extent, selects points."""
    pts = np.asarray(points, np.float64)[:, :3]
    rect = (calib.velo_to_rect @ np.c_[pts, np.ones(len(pts))].T)
    uvw = calib.p2 @ rect
    front = uvw[2] > 0.1
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
    left, top, right, bottom = box.bbox
    return front & (u >= left) & (u <= right) & (v >= top) & (v <= bottom)


def label_points(points: np.ndarray, boxes: list[Box], calib: Calib,
                 image_size: tuple[int, int] | None = None) -> np.ndarray:
    """Class id per point (0 outside every box); _IGNORE_ID where an ignored box holds it or,
    given the image's (width, height), where the left camera does not see the point.

    An ignored region wins over a labelled box, so a car point inside a DontCare rectangle
    counts for nothing rather than for car."""
    cls = np.zeros(len(points), np.uint8)
    if image_size is not None:
        whole = Box("DontCare", (0.0, 0.0, float(image_size[0]), float(image_size[1])),
                    (-1.0, -1.0, -1.0), (0.0, 0.0, 0.0), 0.0)
        cls[~points_in_image_box(points, whole, calib)] = _IGNORE_ID
    for box in boxes:
        if box.kind in LABELLED and box.has_3d:
            cls[points_in_box(points, box, calib)] = LABELLED[box.kind]
    for box in boxes:
        if box.kind in IGNORED:
            inside = (points_in_box(points, box, calib) if box.has_3d
                      else points_in_image_box(points, box, calib))
            cls[inside] = _IGNORE_ID
    return cls


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    try:
        with path.open("rb") as fh:
            head = fh.read(24)
    except OSError as exc:
        raise FalsifyError(f"{path}: cannot read ({exc.strerror})") from None
    if len(head) < 24 or not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        raise FalsifyError(f"{path}: not a PNG image")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def is_object_dir(path: Path) -> bool:
    return (path / "velodyne").is_dir() and (path / "label_2").is_dir()


def frame_names(root: Path) -> list[str]:
    """Frame ids (NNNNNN) with a velodyne scan in an object directory, sorted."""
    return sorted(p.stem for p in (root / "velodyne").glob("*.bin"))


def read_object_frame(root: Path, name: str, sensor: Sensor) -> ObjectFrame:
    """One frame of a KITTI object directory, projected with `sensor` and labelled from boxes."""
    bin_path = root / "velodyne" / f"{name}.bin"
    calib_path = root / "calib" / f"{name}.txt"
    label_path = root / "label_2" / f"{name}.txt"
    image_path = root / "image_2" / f"{name}.png"
    for p in (calib_path, label_path, image_path):
        if not p.is_file():
            raise FalsifyError(f"{p}: missing (a KITTI object frame needs velodyne/, calib/, "
                               "label_2/ and image_2/ files of the same name)")
    try:
        raw = np.fromfile(bin_path, dtype=np.float32)
    except OSError as exc:
        raise FalsifyError(f"{bin_path}: cannot read ({exc.strerror})") from None
    if raw.size == 0 or raw.size % 4:
        raise FalsifyError(f"{bin_path}: expected N x 4 float32 (x, y, z, reflectance), "
                           f"got {raw.size} values")
    pts = raw.reshape(-1, 4)
    pts = pts[np.isfinite(pts).all(axis=1)]
    calib = read_calib(calib_path)
    boxes = read_labels(label_path)
    cls = label_points(pts[:, :3], boxes, calib, png_size(image_path))
    scan = image_from_points(sensor, pts[:, :3], cls, np.zeros(len(pts), np.int32),
                             intensity=pts[:, 3])
    image = scan.image
    ignore = image[..., 5] == _IGNORE_ID
    image[..., 5][ignore] = 0
    return ObjectFrame(name, Scan(image, scan.instance), ignore, tuple(boxes))
