"""The `calib` jobs: how well LiDAR points land on their objects in the camera image.

On a KITTI object directory (real or exported by us), the points inside each labelled 3D box are
projected with the frame's calib file and counted inside that object's 2D box. On our own
scenes, each car point of a scan is projected with the camera's calibration and counted on car
pixels of the camera's class image.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from falsify.data.kitti_object import frames, in_rect, read_calib, read_labels, read_velodyne
from falsify.errors import FalsifyError
from falsify.images.overlay import (
    BOX_RGB,
    DONTCARE_RGB,
    INSIDE_RGB,
    OUTSIDE_RGB,
    depth_colours,
    draw_box,
    draw_points,
)
from falsify.images.png import encode_png, png_size, read_png
from falsify.owned_files import FileList
from falsify.sensor.calibration import KITTI_PIXEL_SHIFT


@dataclass(frozen=True)
class ObjectCheck:
    """One labelled object: how many of the points in its 3D box project into the image, and
    how many of those land in its 2D box (points beyond the image's edges cannot be judged)."""

    frame: str
    index: int
    type: str
    points_in_box: int
    inside_2d: int
    outside_image: int

    @property
    def fraction(self) -> float | None:
        return None if self.points_in_box == 0 else self.inside_2d / self.points_in_box


@dataclass(frozen=True)
class CalibReport:
    """Per-object and pooled fractions of in-box points inside their 2D boxes."""

    directory: str
    frames: list[str]
    objects: list[ObjectCheck]
    overlays: list[str] = field(default_factory=list)

    def pooled(self, types: tuple[str, ...] | None = None) -> dict:
        objs = [o for o in self.objects if types is None or o.type in types]
        n = sum(o.points_in_box for o in objs)
        k = sum(o.inside_2d for o in objs)
        return {"objects": len(objs), "points_in_boxes": n, "inside_2d": k,
                "outside_image": sum(o.outside_image for o in objs),
                "fraction": None if n == 0 else round(k / n, 5)}

    def to_json(self) -> dict:
        types = sorted({o.type for o in self.objects})
        return {"directory": self.directory, "frames": self.frames,
                "pooled": self.pooled(), "by_type": {t: self.pooled((t,)) for t in types},
                "objects": [{"frame": o.frame, "index": o.index, "type": o.type,
                             "points_in_box": o.points_in_box, "inside_2d": o.inside_2d,
                             "outside_image": o.outside_image,
                             "fraction": None if o.fraction is None else round(o.fraction, 5)}
                            for o in self.objects],
                "overlays": self.overlays}


# The overlays a `calib --out` wrote into its folder (name → SHA-256), so that the next run into
# it removes those of frames it does not hold, and nothing else.
OVERLAYS = FileList("calib-overlays.json", "overlays", "falsify calib")


def check_kitti_dir(directory: str | Path, out: str | Path | None) -> CalibReport:
    """Project every frame's points with its calib; write one overlay PNG per frame to `out`,
    with their list (OVERLAYS), removing the overlays an earlier run listed there."""
    directory = Path(directory)
    listed = {} if out is None else OVERLAYS.read(Path(out))   # refused before any read
    ids = frames(directory)
    if out is not None:
        OVERLAYS.check_targets(Path(out), [f"{fid}.png" for fid in ids], listed)
    objects: list[ObjectCheck] = []
    pictures: list[tuple[Path, bytes]] = []
    for fid in ids:
        calib = read_calib(directory / "calib" / f"{fid}.txt")
        labels = read_labels(directory / "label_2" / f"{fid}.txt")
        pts = read_velodyne(directory / "velodyne" / f"{fid}.bin")
        img_path = directory / "image_2" / f"{fid}.png"
        rgb = read_png(img_path) if out is not None else None
        w, h = png_size(img_path)
        rect = calib.velo_to_rect(pts[:, :3])
        u, v, depth = calib.rect_to_image(rect)
        # KITTI pixel k spans [k - 0.5, k + 0.5): the image is [-0.5, w - 0.5) x [-0.5, h - 0.5).
        in_image = np.isfinite(u) & (u >= -KITTI_PIXEL_SHIFT) & (u < w - KITTI_PIXEL_SHIFT) \
            & (v >= -KITTI_PIXEL_SHIFT) & (v < h - KITTI_PIXEL_SHIFT)
        flags = np.zeros(len(pts), np.int8)  # 0 not in a box, 1 inside its 2D box, 2 outside
        for k, obj in enumerate(labels):
            if obj.type == "DontCare":
                continue
            inb = obj.contains(rect) & (depth > 0)
            judged = inb & in_image
            ok = judged & in_rect(u, v, obj.box2d)
            objects.append(ObjectCheck(fid, k, obj.type, int(judged.sum()), int(ok.sum()),
                                       int((inb & ~in_image).sum())))
            flags[ok] = 1
            flags[judged & ~ok] = 2
        if rgb is not None:
            col = np.floor(np.nan_to_num(u, nan=-1) + KITTI_PIXEL_SHIFT).astype(np.int64)
            row = np.floor(np.nan_to_num(v, nan=-1) + KITTI_PIXEL_SHIFT).astype(np.int64)
            seen = np.isfinite(u) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            far_first = np.flatnonzero(seen & (flags == 0))
            far_first = far_first[np.argsort(-depth[far_first], kind="stable")]
            draw_points(rgb, col[far_first], row[far_first],
                        depth_colours(depth[far_first]), size=1)
            for obj in labels:
                draw_box(rgb, obj.box2d, DONTCARE_RGB if obj.type == "DontCare" else BOX_RGB)
            for flag, colour in ((1, INSIDE_RGB), (2, OUTSIDE_RGB)):
                sel = np.flatnonzero(seen & (flags == flag))
                draw_points(rgb, col[sel], row[sel], colour, size=2)
            pictures.append((Path(out) / f"{fid}.png", encode_png(rgb)))
    if out is not None:   # written only once every frame has been read
        OVERLAYS.replace(Path(out), {p.name: data for p, data in pictures}, listed,
                         {"directory": str(directory)})
    return CalibReport(str(directory), ids, objects, [str(p) for p, _ in pictures])


# -- our scenes -------------------------------------------------------------------------------
def car_points_on_car_pixels(points: np.ndarray, cls: np.ndarray, camera, class_image
                             ) -> tuple[int, int, int]:
    """(car points, of them inside the image, of those on car pixels) for one scan."""
    car = points[cls == 1]
    col, row, inside = camera.project(car)
    on = class_image[row[inside], col[inside]] == 1
    return len(car), int(inside.sum()), int(on.sum())


@dataclass(frozen=True)
class SceneAgreement:
    """Car points on car pixels over samples of a space (median of per-sample fractions)."""

    config: str
    camera: str
    samples: int
    scored: int
    median: float | None
    minimum: float | None
    pooled: float | None
    per_sample: list[dict]

    def to_json(self) -> dict:
        return {"config": self.config, "camera": self.camera, "samples": self.samples,
                "scored": self.scored, "median": self.median, "minimum": self.minimum,
                "pooled": self.pooled, "per_sample": self.per_sample}


def scene_agreement(config: str | Path, samples: int = 100, camera: str = "kitti-centre"
                    ) -> SceneAgreement:
    """Render `samples` evenly spaced grid samples of a space with scan and camera and score them;
    samples without a car point inside the image are not scored (counted in `per_sample`)."""
    from falsify.sensor.camera import camera_preset
    from falsify.sensor.lidar import load_sensor
    from falsify.sensor.render import CameraRenderer
    from falsify.sensor.simulator import InvalidSample, Simulator
    from falsify.world.space import load_space

    if samples < 1:
        raise FalsifyError(f"--samples: {samples} must be >= 1")
    space = load_space(config)
    space.require_streets("calib on our scenes")
    cam = camera_preset(camera)
    sim = Simulator(load_sensor(space.sensor), space.user_cars,
                    background_source=space.background_source())
    renderer = CameraRenderer(sim, cam)
    grid = space.grid()
    picked = [grid[i * len(grid) // samples] for i in range(min(samples, len(grid)))]
    rows, fractions = [], []
    total_in, total_on = 0, 0
    for s in picked:
        try:
            scan = sim.scan(s)
            image = renderer.render_sample(s)
        except InvalidSample:
            rows.append({"sample": s.as_dict(), "status": "invalid"})
            continue
        pts = scan.points
        n, inside, on = car_points_on_car_pixels(pts[:, :3], pts[:, 5], cam, image.cls)
        frac = None if inside == 0 else on / inside
        rows.append({"sample": s.as_dict(), "car_points": n, "in_image": inside,
                     "on_car_pixels": on,
                     "fraction": None if frac is None else round(frac, 5)})
        if frac is not None:
            fractions.append(frac)
            total_in += inside
            total_on += on
    return SceneAgreement(
        str(config), cam.name, len(picked), len(fractions),
        None if not fractions else round(statistics.median(fractions), 5),
        None if not fractions else round(min(fractions), 5),
        None if total_in == 0 else round(total_on / total_in, 5), rows)
