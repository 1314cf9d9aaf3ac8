"""Is the inserted car easier because it returns too many points? The instance faithfulness of
insertion_faithfulness.md with the return model's return probability scaled by K on inserted
objects only (the real scans are read as recorded), for the bundled network on the fit split.
A diagnosis, not a fit: K is one number for every material and range.

    SEMANTICKITTI=DIR python research/experiments/faithfulness_dropout.py [K ...]
    (K defaults to 1 0.8 0.6)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from falsify.jobs.instance_faithfulness import run_instance_faithfulness
from falsify.models.runners import load_segmenter
from falsify.sensor.lidar import load_sensor
from falsify.sensor.returns import ReturnModel

FIT = ["01", "02", "04", "05", "07", "09", "10"]
ORIGINAL = ReturnModel.p_return

for k in [float(a) for a in sys.argv[1:]] or [1.0, 0.8, 0.6]:
    ReturnModel.p_return = lambda self, i, k=k: k * ORIGINAL(self, i)
    r = run_instance_faithfulness([Path(os.environ["SEMANTICKITTI"])], FIT,
                                  load_sensor("kitti-hdl64e-front"), load_segmenter(None))
    cars = [row for row in r.rows if row.cls == "car"]
    c = r.classes["car"]
    ratio = float(np.median([row.inserted_points / row.real_points for row in cars]))
    lo, hi = c.ci95
    print(f"K {k:.2f}: cars {c.pooled.cars}, pooled IoU real {c.pooled.real.iou:.3f} inserted "
          f"{c.pooled.inserted.iou:.3f}, mean inserted - real {c.pooled.iou_difference.mean:+.3f}"
          f" ({lo:+.3f} .. {hi:+.3f}), median pixels inserted / real {ratio:.2f}")
ReturnModel.p_return = ORIGINAL
