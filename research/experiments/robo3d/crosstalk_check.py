"""Where the bundled network puts cars when 200 crosstalk returns are added to a real scan: the
sedan 12 m ahead on fit scan 3 of research/experiments/robo3d/crosstalk.toml, clean and with
crosstalk, predicted side by side (robustness.md).

    SEMANTICKITTI=DIR python research/experiments/robo3d/crosstalk_check.py
"""

from __future__ import annotations

import numpy as np

from falsify.data.real_backgrounds import scanner_for
from falsify.models.runners import load_segmenter
from falsify.world.space import load_space

space = load_space("research/experiments/robo3d/crosstalk.toml")
scanner, net = scanner_for(space), load_segmenter(None)
scans = [scanner.scan(space.make({"x": 0.0, "y": 12.0, "background": 3, "crosstalk": n}))
         for n in (0, 200)]
pred = net.predict(np.stack([s.image for s in scans])).classes
for s, p, what in zip(scans, pred, ("clean", "crosstalk 200"), strict=True):
    label, car = s.image[..., 5] == 1, p == 1
    rows, cols = np.nonzero(car)
    print(f"{what}: pixels changed {int((s.image != scans[0].image).any(-1).sum())}, car IoU "
          f"{(label & car).sum() / max((label | car).sum(), 1):.3f}, predicted car rows "
          f"{np.percentile(rows, 5):.0f}-{np.percentile(rows, 95):.0f}, columns "
          f"{np.percentile(cols, 5):.0f}-{np.percentile(cols, 95):.0f}")
