"""SqueezeSeg's .npy range images (H×W×6: x, y, z, intensity, range, label), ours and KITTI's."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.sensor.scan import CHANNELS

NPY_MAGIC = b"\x93NUMPY"   # the first bytes of every .npy file (NumPy's format.py, NEP 1)


def npy_files(folder: Path) -> list[Path]:
    """The .npy range images of a folder (a `falsify dataset` directory, a run's retraining
    set), sorted: without `predict`'s X.pred.npy and a retraining set's camera arrays
    (X.class.npy, X.instance.npy, X.depth.npy), which lie beside them."""
    from falsify.sensor.camera import CAMERA_FILES

    beside = (".pred.npy", *(f".{name}" for name in CAMERA_FILES if name.endswith(".npy")))
    return sorted(p for p in Path(folder).glob("*.npy") if not p.name.endswith(beside))


def load_scan_npy(path: str | Path) -> np.ndarray:
    """Load an H×W×6 range image (ours or SqueezeSeg's KITTI files), checking shape and values."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            magic = fh.read(len(NPY_MAGIC))
        # np.load alone takes a .npz (a zip) too, whose NpzFile has no shape (AttributeError),
        # and says any other file "contains pickled data"
        if magic != NPY_MAGIC:
            raise FalsifyError(f"{path}: not a .npy file (it does not start with NumPy's "
                               "\\x93NUMPY header); expected an (H, W, 6) range image")
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise FalsifyError(f"{path}: not a readable .npy range image "
                           f"({exc or type(exc).__name__})") from None
    if arr.ndim != 3 or arr.shape[2] != 6:
        raise FalsifyError(f"{path}: shape {arr.shape}, expected (H, W, 6) with channels "
                           f"{', '.join(CHANNELS)}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise FalsifyError(f"{path}: dtype {arr.dtype}, expected real numbers")
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():
        raise FalsifyError(f"{path}: contains NaN or inf")
    return arr
