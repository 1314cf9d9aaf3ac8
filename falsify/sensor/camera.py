"""The camera sensor: a pinhole beside the LiDAR (KITTI's left colour camera by default), the
frame it renders, and the pictures and files made from that frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from falsify.errors import ConfigError
from falsify.sensor.calibration import (
    Extrinsic,
    KittiCalib,
    Pinhole,
    pixel_index,
    project_points,
)

# KITTI's left colour camera (P2 of the 2011_09_26 drives): 1242 x 375 pixels, focal 721.5377 px.
KITTI_WIDTH, KITTI_HEIGHT = 1242, 375
KITTI_FOCAL = 721.5377
# KITTI's published 2011_09_26 rig calibration (calib_cam_to_cam.txt, calib_velo_to_cam.txt).
KITTI_P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728],
                     [0.0, 721.5377, 172.854, 0.2163791],
                     [0.0, 0.0, 1.0, 0.002745884]])
KITTI_R0_RECT = np.array([[0.9999239, 0.00983776, -0.007445048],
                          [-0.009869795, 0.9999421, -0.004278459],
                          [0.007402527, 0.004351614, 0.9999631]])
KITTI_TR_VELO_TO_CAM = np.array([[0.007533745, -0.9999714, -0.000616602, -0.004069766],
                                 [0.01480249, 0.0007280733, -0.9998902, -0.07631618],
                                 [0.9998621, 0.00752379, 0.01480755, -0.2717806]])
CAMERA_PRESETS = ("kitti-centre", "kitti-rig")
DEFAULT_CAMERA = "kitti-centre"


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics plus the transform from the LiDAR's frame to the camera's optical frame."""

    name: str
    intrinsics: Pinhole
    extrinsic: Extrinsic
    max_depth: float = 400.0

    @property
    def shape(self) -> tuple[int, int]:
        return (self.intrinsics.height, self.intrinsics.width)

    def scaled(self, factor: float) -> Camera:
        """The same field of view at `factor` times the resolution (tests use small images)."""
        i = self.intrinsics
        w, h = max(1, round(i.width * factor)), max(1, round(i.height * factor))
        sx, sy = w / i.width, h / i.height
        return replace(self, name=f"{self.name}@{w}x{h}",
                       intrinsics=Pinhole(w, h, i.fx * sx, i.fy * sy, i.cx * sx, i.cy * sy))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LiDAR-frame points to (col, row, inside)."""
        u, v, _ = project_points(points, self.intrinsics, self.extrinsic)
        return pixel_index(u, v, self.intrinsics)

    def kitti_calib(self) -> KittiCalib:
        return KittiCalib.for_camera(self.intrinsics, self.extrinsic)


def camera_preset(name: str) -> Camera:
    """`kitti-centre`: KITTI's image size and focal length at the LiDAR's centre, looking along its
    x axis (the paper's set-up); `kitti-rig`: KITTI's real camera 2 with its offset and
    rectification."""
    if name == "kitti-centre":
        intr = Pinhole(KITTI_WIDTH, KITTI_HEIGHT, KITTI_FOCAL, KITTI_FOCAL, KITTI_WIDTH / 2,
                       KITTI_HEIGHT / 2)
        return Camera(name, intr, Extrinsic.shared_centre())
    if name == "kitti-rig":
        calib = KittiCalib((KITTI_P2,) * 4, KITTI_R0_RECT, KITTI_TR_VELO_TO_CAM)
        intr, ext = calib.camera2(KITTI_WIDTH, KITTI_HEIGHT)
        return Camera(name, intr, ext)
    raise ConfigError(f"--camera: unknown camera {name!r}; allowed: {', '.join(CAMERA_PRESETS)}")


@dataclass(frozen=True)
class CameraImage:
    """One camera frame: RGB, per-pixel class and instance, depth along the optical axis (m,
    0 where nothing is hit), and the pixels each car would cover with nothing in front of it."""

    rgb: np.ndarray       # (H, W, 3) uint8
    cls: np.ndarray       # (H, W) uint8
    instance: np.ndarray  # (H, W) int32
    depth: np.ndarray     # (H, W) float32
    unoccluded: dict[int, int]


def class_picture(image: CameraImage) -> np.ndarray:
    """(H, W, 3) uint8 class image: classes in the preview colours, unknown shaded by depth,
    sky dark."""
    from falsify.images.scan_pictures import CLASS_RGB, EMPTY_RGB
    rgb = CLASS_RGB[np.clip(image.cls, 0, 3)].astype(np.float32)
    unknown = image.cls == 0
    rgb[unknown] *= (1.0 - np.clip(image.depth[unknown] / 80.0, 0.0, 0.75))[:, None]
    rgb[image.depth <= 0] = EMPTY_RGB
    return rgb.astype(np.uint8)


def overlay_picture(image: CameraImage, camera: Camera, points: np.ndarray) -> np.ndarray:
    """The paper's figure 1b: LiDAR points (sensor frame) drawn on the RGB image, far first,
    coloured by depth."""
    from falsify.images.overlay import depth_colours, draw_points
    u, v, depth = project_points(points, camera.intrinsics, camera.extrinsic)
    col, row, inside = pixel_index(u, v, camera.intrinsics)
    order = np.flatnonzero(inside)
    order = order[np.argsort(-depth[order], kind="stable")]
    return draw_points(image.rgb.copy(), col[order], row[order], depth_colours(depth[order]),
                       size=2)


CAMERA_FILES = ("image.png", "class.png", "class.npy", "instance.npy", "depth.npy")


def camera_files(image: CameraImage, prefix: str = "") -> dict[str, bytes]:
    """The files that hold one camera frame: RGB and class PNGs, class, instance and depth."""
    from falsify.fileio import npy_bytes
    from falsify.images.png import encode_png

    data = (encode_png(image.rgb), encode_png(class_picture(image)), npy_bytes(image.cls),
            npy_bytes(image.instance), npy_bytes(image.depth))
    return {prefix + name: d for name, d in zip(CAMERA_FILES, data, strict=True)}
