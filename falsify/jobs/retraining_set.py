"""The retraining set of a run: the scans of its valid samples in the blind-spot cells (or in
cells or rows chosen otherwise), re-cast by replay, with index.csv: as SqueezeSeg's range
images, or as SemanticKITTI's .bin and .label files, what a user's own trainer reads."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Collection

import numpy as np
import pandas as pd

from falsify.data.velodyne import SEMANTICKITTI_SEQUENCE, semantickitti_paths, write_kitti
from falsify.errors import ConfigError
from falsify.fileio import write_bytes, write_npy
from falsify.results.miou_maps import CellMap, snap
from falsify.results.replay import Replay
from falsify.results.store import RunData

# How a retraining set is written: "npy", SqueezeSeg's 64 x 512 x 6 range images named for the
# sample (NNNNNN.npy, our four classes in the label channel); "semantickitti", each scan's
# points as sequences/00/velodyne/NNNNNN.bin and its raw SemanticKITTI ids and instances as
# labels/NNNNNN.label (RangeNet++'s, SalsaNext's and most point networks' loaders read these).
RETRAIN_FORMATS = ("npy", "semantickitti")


def check_retrain_format(fmt: str) -> None:
    if fmt not in RETRAIN_FORMATS:
        raise ConfigError(f"--retrain-format: {fmt!r} is not one of {list(RETRAIN_FORMATS)}")


def write_retraining_set(data: RunData, cmap: CellMap, threshold: float, lod: int = 2,
                         camera: str | None = None,
                         cells: Collection[tuple] | None = None,
                         select: Callable[[pd.DataFrame], np.ndarray] | None = None,
                         fmt: str = "npy") -> int:
    """Scans of every valid sample in a blind-spot cell (or in `cells`, (a, b) pairs, when
    given: a control set; or the rows `select` marks among the valid ones), in the layout
    `fmt` names (RETRAIN_FORMATS), plus index.csv (each scan's file, sample and score); with a
    camera preset, each scan's camera files beside it (semantickitti: its RGB image as the
    sequence's image_2/NNNNNN.png, the other camera files in camera/)."""
    check_retrain_format(fmt)
    space, frame = data.space, data.frame
    out = data.path / "retrain"
    if out.exists():
        shutil.rmtree(out)
    blind = (set(cells) if cells is not None
             else {(c.a, c.b) for c in cmap.blind_spots(threshold)})
    if (not blind and select is None) or not len(frame):
        return 0
    ok = data.ok.copy()
    ok["_a"], ok["_b"] = snap(ok["x"], space, "x"), snap(ok["y"], space, "y")
    chosen = (ok[select(ok)] if select is not None else
              ok[[(a, b) in blind for a, b in zip(ok["_a"], ok["_b"], strict=True)]])
    if not len(chosen):
        return 0
    replay = Replay(space, lod=lod)
    renderer = None
    if camera is not None:
        from falsify.sensor.camera import camera_files, camera_preset
        from falsify.sensor.render import CameraRenderer
        renderer = CameraRenderer(replay.sim, camera_preset(camera))
    rows = []
    sequence = out / "sequences" / SEMANTICKITTI_SEQUENCE
    for _, row in chosen.iterrows():
        sample, scan = replay.scan(row)
        stem = f"{int(row['eval_index']):06d}"
        if fmt == "npy":
            name = f"{stem}.npy"
            write_npy(out / name, scan.image)
        else:
            bin_path, label_path = semantickitti_paths(out, int(row["eval_index"]))
            write_kitti(scan, bin_path, label_path)
            name = bin_path.relative_to(out).as_posix()
        if renderer is not None:
            files = camera_files(renderer.render_sample(sample), f"{stem}.")
            for fname, blob in files.items():
                if fmt == "npy":
                    write_bytes(out / fname, blob)
                elif fname == f"{stem}.image.png":
                    write_bytes(sequence / "image_2" / f"{stem}.png", blob)
                else:
                    write_bytes(sequence / "camera" / fname, blob)
        rows.append({"file": name, "eval_index": int(row["eval_index"]),
                     **{d: plain_value(row[d]) for d in space.dims},
                     data.score_column: float(row[data.score_column])})
    write_bytes(out / "index.csv", pd.DataFrame(rows).to_csv(index=False).encode())
    return len(rows)


def plain_value(v):
    """A stored dim value as a JSON value: numpy scalars to Python values, integral floats of
    integer dims kept as stored."""
    if isinstance(v, np.generic):
        return v.item()
    return v
