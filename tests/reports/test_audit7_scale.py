"""The report at a user's scale: a run of thousands of rows makes a page whose size stops
growing with its rows (cell lists keep each cell's lowest, plots bin their marks), the store
is read once, and the page still loads, lists and says what it left out in Chromium."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from falsify.jobs.report import render_report
from falsify.reports.run.common import CELL_ROWS, MAX_POINTS
from falsify.reports.run.plots import CURVE_BINS, DENSITY_BINS
from falsify.results.miou_maps import snap
from falsify.results.store import open_run
from falsify.world.space import load_space
from tests.runfixture import SMOKE, random_samples, write_run


def _search_run(path: Path, n: int, seed: int = 0) -> Path:
    """A search run of `n` seeded random samples over smoke.toml's 4 cells, failing nearer
    than y = 10 m."""
    return write_run(path, command="search", seed=seed, iou=lambda s: (float(s["y"]) - 8) / 6
                     + 0.3, samples=random_samples(load_space(SMOKE), n, seed),
                     invalid_every=17)


@pytest.fixture(scope="module")
def big(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("scale")
    return {"small": _search_run(root / "small", MAX_POINTS + 500),
            "large": _search_run(root / "large", 2 * MAX_POINTS + 1000)}


def _blob(page: str) -> dict:
    return json.loads(re.search(r'id="falsify-data">(.*?)</script>', page, re.S).group(1))


def _section(page: str, ident: str) -> str:
    start = page.index(f'<section id="{ident}"')
    return page[start:page.index("</section>", start)]


def test_page_size_stops_growing_with_rows(big) -> None:
    """Over the caps, twice the rows make a page of about the same size (before: each row
    added a click-list row, a distance dot and two search marks, 0.7 KB a row: 34 MB at
    50,000 rows), and the same run renders to the same bytes."""
    small = render_report(big["small"], predict=False)
    large = render_report(big["large"], predict=False)
    assert abs(len(large) - len(small)) < 60_000, (len(small), len(large))
    assert render_report(big["large"], predict=False) == large


def test_cell_lists_keep_each_cells_lowest_and_count_all(big) -> None:
    """Each cell embeds its CELL_ROWS lowest rows, in the table's order (lowest score first,
    undefined and invalid last, ties by evaluation), with every cell's full count beside."""
    page = render_report(big["large"], predict=False)
    blob = _blob(page)["samples"]
    cols, rows = blob["columns"], blob["rows"]
    data = open_run(big["large"])
    assert sum(blob["cells"].values()) == len(data.frame) and blob["per_cell"] == CELL_ROWS
    by_cell: dict[str, list] = {}
    for r in rows:
        by_cell.setdefault(r[cols.index("cell")], []).append(r)
    assert set(by_cell) == set(blob["cells"]) and len(by_cell) == 4
    f = data.frame
    for key, mine in by_cell.items():
        assert len(mine) == min(CELL_ROWS, blob["cells"][key])
        kept = sorted(r[cols.index("eval")] for r in mine)
        x, y = (float(v) for v in key.split("|"))
        cell = f[(snap(f["x"], data.space, "x") == x) & (snap(f["y"], data.space, "y") == y)].copy()
        cell["_none"] = cell["car_iou"].isna()
        want = cell.sort_values(["_none", "car_iou", "eval_index"]).head(CELL_ROWS)
        assert kept == sorted(want["eval_index"].tolist()), key
    # the page says that lists are cut and where every row is
    assert f"A cell lists its {CELL_ROWS} lowest samples" in page
    assert "results.csv" in _section(page, "map-section")


def test_plots_bin_their_marks_over_the_cap(big) -> None:
    """The distance plot draws a box per non-empty bin, the search curve a bar per bin and its
    map the MAX_POINTS lowest evaluations, no path: marks bounded by bins, not rows (before:
    a dot per sample in each, and a polyline through every evaluation)."""
    page = render_report(big["large"], predict=False)
    dist = _section(page, "distance-section")
    assert '<circle class="pt"' not in dist
    assert 0 < dist.count('<rect class="bin"') <= DENSITY_BINS[0] * DENSITY_BINS[1]
    assert "binned" in dist
    search = _section(page, "search-section")
    assert 0 < search.count('<rect class="range"') <= CURVE_BINS
    assert search.count('<circle class="step"') == MAX_POINTS
    assert '<polyline class="path"' not in search and "lowest of the" in search
    # under the caps nothing changes: a dot per sample and the path
    few = write_run(big["large"].parent / "few", command="search")
    page = render_report(few, predict=False)
    valid = len(open_run(few).ok)
    assert _section(page, "distance-section").count('<circle class="pt"') == valid
    assert '<polyline class="path"' in _section(page, "search-section")
    assert 'class="bin"' not in page and 'class="range"' not in page


def test_the_report_reads_the_store_once(big, monkeypatch) -> None:
    """The report's Explain section works on the run the report opened (before: explain
    opened the store again, a second read of every row: 4.7 s and a second copy in memory at
    50,000 rows of 19 classes)."""
    import falsify.results.store as store

    reads = []
    real = store.read_frame

    def counted(path):
        reads.append(path)
        return real(path)

    monkeypatch.setattr(store, "read_frame", counted)
    page = render_report(big["small"], predict=False)
    assert len(reads) == 1, reads
    assert '<table class="small" id="explain-rules">' in _section(page, "explain")


def test_in_chromium_a_large_run_lists_a_cells_lowest(browser, big, tmp_path: Path) -> None:
    """Clicked, a cell of a run of thousands of rows lists its lowest CELL_ROWS and says of
    how many, and the page logs no error."""
    from selenium.webdriver.common.by import By

    from tests.conftest import assert_offline

    path = tmp_path / "report.html"
    path.write_text(render_report(big["large"], predict=False), encoding="utf-8")
    browser.get(path.as_uri())
    cell = [c for c in browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")
            if c.get_attribute("data-miou")][0]
    cell.click()
    rows = browser.find_elements(By.CSS_SELECTOR, "#cell-table tbody tr")
    assert len(rows) == CELL_ROWS
    title = browser.find_element(By.ID, "cell-title").text
    assert re.search(rf"\(the {CELL_ROWS} lowest of \d+ rows, mIoU ", title), title
    assert_offline(browser)
