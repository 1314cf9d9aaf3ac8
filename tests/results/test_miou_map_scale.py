"""The cell map of a large run is computed per cell in arrays, not per pandas group: it must give
the bytes the per-group computation gives (`bench cells`' naive path), on grid and searched
rows, numeric and categorical axes, missing and invalid values, and rows off the axes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from falsify.bench.cells import per_group_map
from falsify.results.miou_maps import miou_map
from falsify.world.space import load_space
from tests.runfixture import SMOKE

SPACE = """name = "s"
sensor = "kitti-hdl64e-front"
[dims.car_model]
values = ["sedan", "suv", "van"]
[dims.x]
min = -10.0
max = 10.0
step = 0.5
[dims.y]
min = 5.0
max = 30.0
step = 0.25
[dims.background]
values = [0, 3, 7]
"""


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize(("a", "b"), [("x", "y"), ("car_model", "y"), ("x", "background")])
def test_a_large_runs_map_is_the_per_group_maps_bytes(tmp_path, seed, a, b) -> None:
    cfg = tmp_path / "s.toml"
    cfg.write_text(SPACE)
    space = load_space(cfg)
    rng = np.random.default_rng(seed)
    n = 8_000
    iou = rng.random(n)
    iou[rng.random(n) < 0.1] = np.nan                           # undefined
    status = np.where(np.isnan(iou), "undefined", "ok").astype(object)
    status[rng.random(n) < 0.05] = "invalid"
    x = rng.uniform(-12, 12, n)                                 # searched: off the grid too
    x[: n // 2] = np.round(x[: n // 2] * 2) / 2                 # and on it
    frame = pd.DataFrame({
        "x": x, "y": rng.uniform(3, 33, n),
        "car_model": rng.choice(["sedan", "suv", "van", "bus"], n),   # "bus" is on no axis
        "background": rng.choice([0, 3, 7, 9], n),                    # 9 neither
        "status": status, "car_iou": [None if np.isnan(v) else v for v in iou],
    })
    got = miou_map(frame, space, a, b, "car_iou")
    want = per_group_map(frame, space, a, b, "car_iou")
    assert got.miou.tobytes() == want.miou.tobytes()
    for name in ("samples", "undefined", "invalid"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert np.isfinite(got.miou).sum() > 0.5 * got.miou.size


def test_the_smoke_maps_edge_rows_match_too() -> None:
    """No row, a row outside every cell, and a cell of invalid samples only."""
    space = load_space(SMOKE)
    empty = pd.DataFrame({"x": [], "y": [], "status": [], "car_iou": []})
    assert np.isnan(miou_map(empty, space).miou).all()
    frame = pd.DataFrame({"x": [-2.0, 2.0, 2.0], "y": [8.0, 14.0, 14.0],
                          "status": ["invalid", "ok", "undefined"],
                          "car_iou": [None, 0.5, None]})
    got = miou_map(frame, space)
    want = per_group_map(frame, space, "x", "y", "car_iou")
    assert got.miou.tobytes() == want.miou.tobytes()
    assert (got.invalid[0, 0], got.samples[1, 1], got.undefined[1, 1]) == (1, 1, 1)
