"""Audit 7: `explain` judges a car's dims only on samples that hold that car; the report's
click-through title counts "1 row"; a config's relative user mesh resolves from its own folder
whatever the working directory."""

from __future__ import annotations

import itertools
import json
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.jobs.explain import explain_run, format_text
from falsify.jobs.report import render_report
from falsify.reports.explain_page import explain_section
from falsify.results.explain import holds
from falsify.results.store import open_run
from falsify.world.space import Sample, parse_space
from tests.runfixture import ROOT, SMOKE, write_run

# One or two cars; car 2's dims are pinned to their first value (x_2 = -12, y_2 = 5) when
# count is 1 (Space.make).
TWO_CARS = """
name = "two-cars"
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.65

[dims.car_model]
values = ["sedan"]

[dims.x]
min = -4.0
max = 4.0
step = 4.0

[dims.y]
min = 6.0
max = 18.0
step = 6.0

[dims.yaw]
values = [0.0]

[dims.count]
values = [1, 2]

[dims.x_2]
min = -12.0
max = 12.0
step = 12.0

[dims.y_2]
min = 5.0
max = 15.0
step = 5.0

[dims.background]
values = [0, 1]
"""


def _samples() -> list[Sample]:
    """18 one-car samples over (x, y, background), 12 two-car ones over (x, y, x_2), y_2 = 10."""
    space = parse_space(tomllib.loads(TWO_CARS))
    one = [space.make({"count": 1, "x": x, "y": y, "background": b})
           for x, y, b in itertools.product((-4, 0, 4), (6, 12, 18), (0, 1))]
    two = [space.make({"count": 2, "x": x, "y": y, "x_2": x2, "y_2": 10})
           for x, y, x2 in itertools.product((-4, 4), (6, 18), (-12, 0, 12))]
    return one + two


def _one_car_fails(s: Sample) -> float:
    """One car fails from 12 m on; two cars fail when car 2 stands at x_2 = -12 (its pinned
    default, so a test on x_2 over every sample would also catch the one-car failures)."""
    if s.count == 1:
        return 0.4 if float(s["y"]) >= 12 else 0.85
    return 0.4 if float(s["x_2"]) <= -12 else 0.85


def _two_cars_fail(s: Sample) -> float:
    """Car 2 at x_2 = 12 fails (4 samples), and one one-car sample."""
    if s.count == 1:
        return 0.4 if (s["x"], s["y"], s["background"]) == (-4.0, 6.0, 0) else 0.85
    return 0.4 if float(s["x_2"]) >= 12 else 0.85


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Search runs (so clusters are printed) written with the real store API."""
    root = tmp_path_factory.mktemp("audit7-explain")
    return {name: write_run(root / name, TWO_CARS, command="search", iou=fn, samples=_samples())
            for name, fn in (("one", _one_car_fails), ("two", _two_cars_fail))}


def test_rules_on_car_2_cover_only_samples_holding_it(runs) -> None:
    """Before: `x_2 <= -12 and y >= 12: 14 of 14` (12 of them one-car samples, their x_2 the
    pinned default). After: the one-car region by count and y, and car 2's own region."""
    data = open_run(runs["one"])
    e = explain_run(runs["one"]).explanation
    assert [r.text() for r in e.rules] == ["count == 1 and y >= 12", "x_2 <= -12"]
    ok = data.ok.reset_index(drop=True)
    for rule in e.rules:
        cover = np.logical_and.reduce([c.mask(ok[c.dim]) & holds(data.space, ok, c.dim)
                                       for c in rule.conditions])
        assert rule.support == int(cover.sum())
        if any(c.dim.endswith("_2") for c in rule.conditions):
            assert set(ok["count"][cover].astype(int)) == {2}


def test_sensitivity_of_car_2_dims_is_judged_on_two_car_samples(runs) -> None:
    """Before: y_2 explained 0.107 of the variance (exactly count's share: its pinned 5 against
    the two-car samples' 10) and x_2 0.415. After: y_2 takes one value where car 2 stands, so it
    explains nothing and is not listed; x_2's share is its between-group sum of squares over the
    12 two-car samples against the run's total (0.357), not count's effect passed off as its."""
    s = explain_run(runs["one"]).explanation.sensitivity
    assert "y_2" not in s
    ok = open_run(runs["one"]).ok
    iou, two = ok["car_iou"].astype(float), ok[ok["count"].astype(int) == 2]
    between = sum(len(g) * (g.mean() - two["car_iou"].mean()) ** 2
                  for _, g in two["car_iou"].astype(float).groupby(two["x_2"]))
    assert s["x_2"] == pytest.approx(between / (len(iou) * iou.var(ddof=0)), rel=1e-9)
    assert s["x_2"] == pytest.approx(0.357, abs=1e-3)
    assert s["count"] == pytest.approx(0.107, abs=1e-3)


def test_cluster_centres_show_car_2_only_where_most_samples_hold_it(runs, capsys) -> None:
    """A cluster of 12 one-car and 4 two-car failures showed `x_2=-12.0, y_2=6.25` (the pinned
    defaults mixed in); now no car-2 dim. A cluster of 4 two-car failures and 1 one-car showed
    `x_2=7.2, y_2=9.0`; now x_2 = 12, the mean over the samples holding car 2 (y_2, 10 on all
    of them, varies only through its pinned default and is left out)."""
    mostly_one = explain_run(runs["one"], clusters=1).explanation.clusters
    assert len(mostly_one) == 1 and mostly_one[0].size == 16
    assert mostly_one[0].centre == {"x": 0.0, "y": 14.25, "count": 1, "background": 0}
    mostly_two = explain_run(runs["two"], clusters=1).explanation.clusters
    assert mostly_two[0].size == 5
    assert mostly_two[0].centre["x_2"] == 12.0
    assert "y_2" not in mostly_two[0].centre   # 10 wherever car 2 stands: it explains nothing
    assert mostly_two[0].centre["count"] == 2
    # the command's text and JSON, and the report's section, say the same
    assert main(["explain", str(runs["one"]), "--clusters", "1"]) == 0
    text = capsys.readouterr().out
    assert "16 samples, mean 0.400: x=0.0, y=14.25, count=1, background=0" in text
    assert "x_2=" not in text.split("clusters of failing samples:")[1]
    assert main(["explain", str(runs["two"]), "--clusters", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["clusters"][0]["centre"]["x_2"] == 12.0
    data = open_run(runs["one"])
    result = explain_run(runs["one"], clusters=1)
    assert format_text(result) == text.rstrip("\n")
    page = explain_section(data, result.explanation)
    clusters_html = page[page.index('id="explain-clusters"'):]
    assert "x_2" not in clusters_html and "y_2" not in clusters_html


def test_one_car_runs_explain_as_before(tmp_path: Path, monkeypatch) -> None:
    """Where every sample holds every car (smoke.toml, one car), rules, sensitivity and
    clusters are exactly those of judging each dim on every sample, the behaviour before."""
    run = write_run(tmp_path / "smoke", SMOKE, command="search", seed=3)
    now = explain_run(run, threshold=0.8, clusters=3).explanation
    import falsify.results.explain as module

    monkeypatch.setattr(module, "holds", lambda space, frame, name: np.ones(len(frame), bool))
    assert explain_run(run, threshold=0.8, clusters=3).explanation == now
    assert now.failing and now.clusters


# --- 2: the click-through title says "1 row" -------------------------------------------------

RUN_JS = ROOT / "reports" / "assets" / "run.js"


def test_rows_text_is_singular_for_one_at_text_level() -> None:
    """run.js's rowsText(n), run in Node where it is installed: "1 row", "2 rows"."""
    node = shutil.which("node")
    match = re.search(r"function rowsText\(n\) \{.*?\}", RUN_JS.read_text())
    assert match, "run.js lost rowsText"
    assert "+ ' rows'" not in RUN_JS.read_text().replace(match.group(0), "")
    if node is None:
        pytest.skip("node is not installed")
    script = match.group(0) + "; console.log([0, 1, 2, 25].map(rowsText).join('|'));"
    out = subprocess.run([node, "-e", script], capture_output=True, text=True, timeout=30)
    assert out.stdout.strip() == "0 rows|1 row|2 rows|25 rows", out.stderr


def test_in_chromium_a_cell_of_one_sample_says_1_row(browser, tmp_path: Path) -> None:
    """Before: "(1 rows, mIoU ...)"; after: "(1 row, mIoU ...)"."""
    from selenium.webdriver.common.by import By

    from tests.conftest import assert_offline

    space = parse_space(tomllib.loads(SMOKE.read_text()))
    one_per_cell = [s for s in space.grid() if s["background"] == 0]
    run = write_run(tmp_path / "run", SMOKE, samples=one_per_cell)
    page = tmp_path / "report.html"
    page.write_text(render_report(run, predict=False), encoding="utf-8")
    browser.get(page.as_uri())
    browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")[0].click()
    title = browser.find_element(By.ID, "cell-title").text
    assert re.search(r"\(1 row, mIoU [\d.]+\)$", title), title
    assert len(browser.find_elements(By.CSS_SELECTOR, "#cell-table tbody tr")) == 1
    assert_offline(browser)


# --- 3: a relative user mesh resolves from the config's folder ---------------------------------

MINE = """
name = "mine"
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.65

[car_models.mine]
file = "mesh.glb"

[dims.car_model]
values = ["mine", "sedan"]

[dims.x]
values = [0.0]

[dims.y]
values = [10.0]

[dims.yaw]
values = [0.0]

[dims.count]
values = [1]

[dims.background]
values = [0]
"""


@pytest.mark.parametrize("given", ["absolute", "relative"])
def test_a_relative_user_mesh_is_found_from_another_directory(tmp_path: Path, monkeypatch,
                                                              given: str) -> None:
    """`falsify grid` from another directory finds `mesh.glb` beside the config, places it (a
    box far larger than the sedan: many more car points), and a report written later from yet
    another directory still rebuilds its scans (before: 'scan not regenerated: ../cfg/mine.toml:
    car_models.mine.file ../cfg/mesh.glb: not found' when the config was named relatively)."""
    trimesh = pytest.importorskip("trimesh")
    folder, elsewhere, later = tmp_path / "cfg", tmp_path / "elsewhere", tmp_path / "later"
    for d in (folder, elsewhere, later):
        d.mkdir()
    trimesh.creation.box(extents=(8.0, 4.0, 3.0)).export(folder / "mesh.glb")
    (folder / "mine.toml").write_text(MINE)
    monkeypatch.chdir(elsewhere)
    config = str(folder / "mine.toml") if given == "absolute" else "../cfg/mine.toml"
    run = tmp_path / "run"
    assert main(["grid", config, "--out", str(run), "--quiet", "--no-report"]) == 0
    data = open_run(run)
    assert data.space.user_cars["mine"].file.resolve() == (folder / "mesh.glb").resolve()
    rows = data.frame.set_index("car_model")
    assert list(rows["status"]) == ["ok", "ok"]
    assert rows.loc["mine", "label_points"] > 1.5 * rows.loc["sedan", "label_points"]
    monkeypatch.chdir(later)
    page = render_report(run)
    assert "not regenerated" not in page and "mine" in page


def test_retrain_rules_cover_only_rows_holding_the_rules_car() -> None:
    """`retrain --selection rules` carried a rule on x_2 over to one-car rows whose pinned
    x_2 happened to meet it."""
    from falsify.jobs.retrain_selection import covered
    from falsify.results.explain import Condition, Rule

    space = parse_space(tomllib.loads(TWO_CARS), source="two-cars.toml")
    rule = Rule((Condition("x_2", "<=", -12.0),), 4, 4, 1.0, 0.4, 0.8, 0.1)
    rows = pd.DataFrame({"count": [1, 2, 2], "x": [0.0] * 3, "y": [6.0] * 3,
                         "x_2": [-12.0, -12.0, 12.0], "background": [0, 0, 1]})
    assert covered([rule], space, rows).tolist() == [False, True, False]
