"""`falsify bench cells`: a run's cell maps in arrays against one pandas group per cell, on the
same drawn rows, the same bytes; its result makes a row of `bench table`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from falsify.bench.cells import drawn_rows
from falsify.bench.tables import render
from falsify.cli import main
from falsify.results.metrics import Status
from falsify.world.space import load_space
from tests.runfixture import CONFIGS


def test_bench_cells_times_every_map_both_ways_and_compares_them(capsys) -> None:
    assert main(["bench", "cells", "--config", str(CONFIGS / "yaw.toml"), "--samples", "3000",
                 "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["benchmark"] == "cells" and r["samples"] == 3000 and r["identical"] is True
    assert [m["dims"] for m in r["maps"]][0] == ["x", "y"] and len(r["maps"]) == 3
    assert all(m["identical"] and 0 < m["filled"] <= m["cells"] for m in r["maps"])
    assert r["cells"] == sum(m["cells"] for m in r["maps"])
    assert r["s_arrays"] > 0 and r["s_per_group"] > 0
    assert r["speedup"] == pytest.approx(r["s_per_group"] / r["s_arrays"], rel=0.05)
    assert r["machine"]["cpu"] and r["measured_by"].startswith("falsify bench cells --config")
    row = render([r])
    assert "| cell maps | 3 maps, " in row and "the same bytes" in row
    assert f"`{r['measured_by']}`" in row


def test_drawn_rows_cover_the_space_with_undefined_and_invalid_rows() -> None:
    space = load_space(CONFIGS / "yaw.toml")
    rows = drawn_rows(space, 20_000, seed=3)
    assert rows.equals(drawn_rows(space, 20_000, seed=3))
    x = space.dims["x"]
    assert x.lo <= rows["x"].min() < x.lo + 0.1 and x.hi - 0.1 < rows["x"].max() <= x.hi
    share = rows["status"].value_counts(normalize=True)
    assert share[Status.INVALID.value] == pytest.approx(0.05, abs=0.01)
    assert share[Status.UNDEFINED.value] == pytest.approx(0.10, abs=0.01)
    scored = rows["car_iou"].notna().to_numpy()
    assert np.array_equal(scored, (rows["status"] == Status.OK.value).to_numpy())


def test_bench_cells_refuses_options_it_does_not_read_and_bad_values(capsys) -> None:
    assert main(["bench", "cells", "--workers", "4"]) == 2
    assert "--workers: bench cells does not take it; it takes --config, --samples" in \
        capsys.readouterr().err
    assert main(["bench", "cells", "--samples", "0"]) == 2
    assert "--samples: 0 must be between 1 and 1000000" in capsys.readouterr().err
