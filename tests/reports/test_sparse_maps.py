"""A search over a fine grid leaves most cells without a sample. Its maps draw a rect for each
cell that holds one, over one hatched rect for the rest (a rect per cell made a 138 MB page
that Chromium took 45 s to open, for 30,000 samples over 141,000 cells); the arrow keys walk
the drawn cells, skipping the empty ones; the x labels stay apart however narrow the cells."""

from __future__ import annotations

import re
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from falsify.jobs.report import render_report, write_report
from falsify.reports.run.maps import heatmap_section
from falsify.results.store import open_run
from falsify.world.space import load_space
from tests.conftest import assert_offline
from tests.runfixture import write_run

FINE = """name = "fine"
sensor = "kitti-hdl64e-front"
threshold = 0.65
[dims.car_model]
values = ["sedan"]
[dims.x]
min = -20.0
max = 20.0
step = 0.1
[dims.y]
min = 5.0
max = 40.0
step = 0.25
[dims.background]
values = [0, 1]
"""
# A few cells on a 401 x 141 grid: row y = 5 holds x = -20, -19.5 and 3 (invalid only); y = 5.25
# holds x = -19.5; y = 6 holds x = 7.
PLACED = [(-20.0, 5.0, 0.9), (-19.5, 5.0, 0.5), (3.0, 5.0, None), (-19.5, 5.25, 0.7),
          (7.0, 6.0, 0.8)]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sparse")
    (root / "fine.toml").write_text(FINE)
    space = load_space(root / "fine.toml")
    samples = [space.make({"x": x, "y": y, "background": bg}) for x, y, _ in PLACED
               for bg in (0, 1)]
    iou = {(x, y): v for x, y, v in PLACED}
    path = write_run(root / "run", FINE, command="search",
                     samples=samples, iou=lambda s: iou[(s["x"], s["y"])] or 0.5,
                     invalid_every=0)
    # the invalid-only cell: mark its rows invalid in place of scoring them
    import sqlite3
    with sqlite3.connect(path / "results.sqlite") as db:
        db.execute("UPDATE samples SET status = 'invalid', reason = 'cars overlap', "
                   "car_iou = NULL WHERE x = 3.0")
    return path


def test_only_cells_with_a_sample_get_a_rect(run) -> None:
    data = open_run(run)
    cmap = data.cell_map()
    assert cmap.miou.shape == (141, 401) and int(cmap.filled.sum()) == 5
    section = heatmap_section(data, cmap, 0.65)
    cells = re.findall(r'<rect class="cell[^"]*"[^>]*data-x="([^"]+)" data-y="([^"]+)"', section)
    assert cells == [("-20", "5"), ("-19.5", "5"), ("3", "5"), ("-19.5", "5.25"), ("7", "6")]
    assert section.count('class="absent cell-absent"') == 1
    # the invalid-only cell is drawn, hatched, with its count: its rows can be listed
    assert re.search(r'class="cell empty"[^>]*data-x="3"', section)
    page = render_report(run, predict=False)
    assert page.count("<rect") < 200, page.count("<rect")      # 57,000 rect per map before
    assert render_report(run, predict=False) == page


def test_a_full_grid_draws_every_cell_as_before(tmp_path) -> None:
    """Where every cell holds a sample, no hatched underlay is drawn: the page is unchanged."""
    from tests.runfixture import SMOKE
    page = render_report(write_run(tmp_path / "r", SMOKE), predict=False)
    assert 'class="absent' not in page
    assert len(re.findall(r'<rect class="cell', page)) == 4


def test_the_arrow_keys_skip_empty_cells(browser, run) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    page = write_report(run, predict=False)
    browser.get(page.as_uri())
    assert_offline(browser)
    assert len(browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")) == 5

    def key(k: str) -> tuple[str, str]:
        ActionChains(browser).send_keys(k).perform()
        cell = browser.switch_to.active_element
        return cell.get_attribute("data-x"), cell.get_attribute("data-y")

    assert key(Keys.TAB) == ("-20", "5")          # the map's one Tab stop: the nearest row's first
    assert key(Keys.ARROW_RIGHT) == ("-19.5", "5")
    assert key(Keys.ARROW_RIGHT) == ("3", "5")    # 224 empty cells passed over
    assert key(Keys.ARROW_RIGHT) == ("3", "5")    # the row's last: focus stays
    assert key(Keys.HOME) == ("-20", "5")
    assert key(Keys.END) == ("3", "5")
    assert key(Keys.ARROW_UP) == ("3", "5")       # nothing farther in its column
    assert key(Keys.ARROW_LEFT) == ("-19.5", "5")
    assert key(Keys.ARROW_UP) == ("-19.5", "5.25")
    assert key(Keys.ARROW_DOWN) == ("-19.5", "5")
    ActionChains(browser).send_keys(Keys.ENTER).perform()
    title = browser.find_element(By.ID, "cell-title").text
    assert title.startswith("Samples of cell x = -19.5, y = 5 (2 rows")

    # hovering the hatched underlay says there is no sample there
    under = browser.find_element(By.CSS_SELECTOR, "#heatmap .absent")
    ActionChains(browser).move_to_element_with_offset(under, 100, -100).perform()
    assert browser.find_element(By.ID, "tip").text == "no sample in this cell"

    # the x labels under 401 columns of 4 px do not overlap
    boxes = browser.execute_script(
        "var svg = document.getElementById('heatmap'), out = [];"
        "svg.querySelectorAll('text[text-anchor=middle]:not(.axis)').forEach(function (t) {"
        "  var b = t.getBBox(); out.push([b.x, b.x + b.width, t.textContent]); });"
        "return out;")
    xs = [b for b in boxes if re.fullmatch(r"-?\d+(\.\d+)?", b[2])]
    assert len(xs) >= 10
    assert all(a[1] + 2 <= b[0] for a, b in pairwise(xs)), xs[:5]


DENSE = FINE.replace("step = 0.1", "step = 0.8").replace("step = 0.25", "step = 0.7")


def test_a_dense_grids_small_maps_are_one_picture_a_pixel_a_cell(tmp_path, browser) -> None:
    """51 x 51 cells on two streets: each per-background map is a PNG of 51 x 51 pixels in
    the main map's colours (nearest row at the bottom), not 2,601 rects."""
    import base64

    from falsify.images.png import decode_png
    from falsify.reports.charts import viridis_rgb
    from falsify.reports.run.maps import SMALL_MAP_RECTS

    (tmp_path / "dense.toml").write_text(DENSE)
    run = write_run(tmp_path / "run", tmp_path / "dense.toml")
    data = open_run(run)
    page = render_report(run, predict=False)
    pictures = re.findall(r'<image class="mpic"[^>]*href="data:image/png;base64,([^"]+)"',
                          page)
    assert len(pictures) == 2 and 'class="mcell' not in page
    for bg, b64 in zip((0, 1), pictures, strict=True):
        cmap = data.cell_map(data.frame[data.frame["background"] == bg])
        assert cmap.miou.size == 51 * 51 > SMALL_MAP_RECTS
        rgb = decode_png(base64.b64decode(b64))
        assert rgb.shape == (51, 51, 3)
        assert np.array_equal(rgb, viridis_rgb(cmap.miou[::-1]))
    assert len(re.findall(r'<rect class="cell', page)) == 51 * 51   # the main map: all cells
    path = write_report(run, predict=False)
    browser.get(path.as_uri())
    assert_offline(browser)
    size = browser.execute_script(
        "var r = document.querySelector('.mpic').getBoundingClientRect();"
        "return [r.width, r.height];")
    assert size == [84, 96]
