"""The retraining set of a run: the scans of its valid samples in the blind-spot cells (or in
cells or rows chosen otherwise), re-cast by replay in SqueezeSeg's layout, with index.csv."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Collection

import numpy as np
import pandas as pd

from falsify.fileio import write_bytes, write_npy
from falsify.results.miou_maps import CellMap, snap
from falsify.results.replay import Replay
from falsify.results.store import RunData


def write_retraining_set(data: RunData, cmap: CellMap, threshold: float, lod: int = 2,
                         camera: str | None = None,
                         cells: Collection[tuple] | None = None,
                         select: Callable[[pd.DataFrame], np.ndarray] | None = None) -> int:
    """Scans of every valid sample in a blind-spot cell (or in `cells`, (a, b) pairs, when
    given: a control set; or the rows `select` marks among the valid ones), in SqueezeSeg's
    layout, plus index.csv; with a camera preset, each scan's camera files beside it."""
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
    for _, row in chosen.iterrows():
        sample, scan = replay.scan(row)
        name = f"{int(row['eval_index']):06d}.npy"
        write_npy(out / name, scan.image)
        if renderer is not None:
            for fname, blob in camera_files(renderer.render_sample(sample), name[:-3]).items():
                write_bytes(out / fname, blob)
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
