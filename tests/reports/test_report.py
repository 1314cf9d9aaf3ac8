"""The HTML report: one cell per grid cell, escaping, size, comparison, determinism, and a headless
Chromium session that hovers and clicks cells and proves the page made no network request."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.jobs.report import render_report, write_report
from tests.conftest import assert_offline
from tests.runfixture import PAPER, SMOKE, write_run

EVIL_NAME = "<script>alert(1)</script>"
EVIL_PATH = '/models/"&<>.onnx'
EVIL_REASON = "<img src=x onerror=alert(2)> & more"
CELL = re.compile(r'<rect class="cell[ "]')


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Small runs over smoke.toml: a hostile-named one, a 'before' run, and a search run."""
    root = tmp_path_factory.mktemp("runs")
    return {
        "evil": write_run(root / "evil", meta={"space_name": EVIL_NAME, "model_path": EVIL_PATH,
                                               "config_path": EVIL_PATH + "/<b>.toml"},
                          invalid_every=3, invalid_reason=EVIL_REASON),
        "before": write_run(root / "before", seed=7,
                            iou=lambda s: 0.4 if float(s["y"]) < 10 else 0.7),
        "search": write_run(root / "search", command="search", seed=3),
    }


def test_one_cell_per_grid_cell_and_sections(runs) -> None:
    page = render_report(runs["evil"], predict=False)
    assert len(CELL.findall(page)) == 4
    for ident in ('id="heatmap"', 'id="distance"', 'id="worst-section"', 'id="cell-table"',
                  "no valid sample", "Blind spots", "Lowest IoU"):
        assert ident in page
    assert 'id="searchpath"' not in page and 'id="diffmap"' not in page
    # each cell carries its data and its tooltip once, as a <title> (read without JS too)
    cells = re.findall(r'<rect class="cell[^>]*><title>x = [^<]*</title></rect>', page)
    assert len(cells) == 4
    for c in cells:
        for attr in ("data-x=", "data-y=", "data-miou=", "data-n="):
            assert attr in c
    assert "data-tip=" not in page


def test_escaping(runs) -> None:
    page = render_report(runs["evil"], predict=False)
    assert "<script>alert" not in page and "<img src=x" not in page and "<b>.toml" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "&quot;&amp;&lt;&gt;" in page
    # the embedded JSON is valid and holds the reason intact, with no raw < > &
    blob = re.search(r'<script type="application/json" id="falsify-data">(.*?)</script>', page,
                     re.S).group(1)
    assert "<" not in blob and ">" not in blob and "&" not in blob
    data = json.loads(blob)
    reasons = {r[data["samples"]["columns"].index("reason")] for r in data["samples"]["rows"]}
    assert EVIL_REASON in reasons
    # only our own two script elements
    assert page.count("<script") == 2


def test_self_contained(runs) -> None:
    page = render_report(runs["evil"], predict=False)
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", page)
    assert "@import" not in page and "url(http" not in page
    assert "Content-Security-Policy" in page
    for src in re.findall(r'<img src="([^"]+)"', page):
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1]).startswith(b"\x89PNG")


def test_deterministic_and_written(runs, tmp_path: Path) -> None:
    a = render_report(runs["evil"], predict=False)
    b = render_report(runs["evil"], predict=False)
    assert a == b
    out = write_report(runs["evil"], tmp_path / "r.html", )
    assert out.read_text(encoding="utf-8") == render_report(runs["evil"])


def test_compare_page(runs) -> None:
    page = render_report(runs["evil"], compare=runs["before"], predict=False)
    assert 'id="diffmap"' in page and 'id="improvement"' in page
    assert len(CELL.findall(page)) == 4                 # the diff map uses its own class
    assert page.count('class="bar"') == 4
    assert page.count('<rect class="dcell') == 4
    assert "Blind spots" in page and "fixed" in page
    assert 'id="compare-differs"' not in page       # the same space: nothing to warn of


def test_compare_across_spaces_says_what_differs(runs, tmp_path: Path, capsys) -> None:
    """Another background set, another dim: the page and --json name each, escaped."""
    text = SMOKE.read_text().replace("values = [0, 1]", "values = [0, 1, 2]") + (
        '[dims.fog]\nvalues = [0.0, 80.0]\n')
    other = write_run(tmp_path / "other", text)
    page = render_report(runs["evil"], compare=other, predict=False)
    assert 'id="compare-differs"' in page
    assert "<li>background: before street 0, street 1, street 2; after street 0, street 1</li>" \
        in page
    assert "<li>dim fog: in the run before only, not after</li>" in page
    assert main(["report", str(runs["evil"]), "--compare", str(other), "--no-predict",
                 "--out", str(tmp_path / "p.html"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["compare_differs"] == [
        "background: before street 0, street 1, street 2; after street 0, street 1",
        "dim fog: in the run before only, not after"]


def test_search_page(runs) -> None:
    page = render_report(runs["search"], predict=False)
    assert 'id="curve"' in page and 'id="searchpath"' in page
    assert page.count('class="step"') == 40             # one dot per evaluation
    assert 'class="minline"' in page


def test_a_real_runs_worst_samples_show_label_and_prediction(tmp_path: Path) -> None:
    """A grid on the bundled network: each worst sample's preview holds the label's pictures and
    the network's prediction of the regenerated scan beside them."""
    run = tmp_path / "run"
    assert main(["grid", str(SMOKE), "--out", str(run), "--quiet"]) == 0
    page = (run / "report.html").read_text(encoding="utf-8")
    assert "Model not loaded" not in page
    assert page.count('alt="range image, label"') == 8       # every sample of the smoke grid
    assert page.count('alt="range image, prediction"') == 8
    assert page.count('alt="bird\'s-eye view, prediction"') == 8


def test_predict_falls_back_to_labels(runs) -> None:
    """The run names a model that is not there: the page says so and shows the labels."""
    page = render_report(runs["evil"], predict=True)
    assert "Model not loaded" in page
    assert 'alt="range image, prediction"' not in page
    assert 'alt="range image, label"' in page


def test_cli(runs, tmp_path: Path, capsys) -> None:
    out = tmp_path / "sub" / "page.html"
    assert main(["report", str(runs["before"]), "--out", str(out), "--no-predict",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["out"] == str(out) and doc["bytes"] == out.stat().st_size
    assert main(["report", str(tmp_path / "missing"), "--no-predict"]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["report", str(runs["before"]), "--compare", str(tmp_path / "nope")]) == 2


@pytest.mark.slow
def test_paper_size(tmp_path: Path) -> None:
    """150 cells × 15 backgrounds = 2,250 rows: one file under 5 MB with 12 previews."""
    run = write_run(tmp_path / "paper", PAPER, undefined_every=37, invalid_every=53)
    out = write_report(run, compare=None, predict=False)
    page = out.read_text(encoding="utf-8")
    assert out == run / "report.html"
    assert len(CELL.findall(page)) == 150
    # A preview each, or the reason there is none: this written run stores rows as ok where the
    # places' streets hold an object (a real run stores those as invalid).
    previews = page.count('alt="range image, label"')
    assert previews >= 9 and previews + page.count("scan not regenerated: car 1") == 12
    assert page.count('class="multiple"') == 15
    assert out.stat().st_size < 5_000_000


# -- headless Chromium ---------------------------------------------------------------------------
COUNT_COLOURS = """
const done = arguments[arguments.length - 1];
const img = new Image();
img.onload = () => {
  const c = document.createElement('canvas');
  c.width = img.width; c.height = img.height;
  const g = c.getContext('2d'); g.drawImage(img, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data, seen = new Set();
  for (let i = 0; i < d.length; i += 4) seen.add((d[i] << 16) | (d[i + 1] << 8) | d[i + 2]);
  done(seen.size);
};
img.onerror = () => done(-1);
img.src = arguments[0];
"""


def test_in_chromium(browser, runs, tmp_path: Path) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    page = write_report(runs["evil"], tmp_path / "report.html", compare=runs["before"])
    browser.get(page.as_uri())
    cells = browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")
    assert len(cells) == 4

    # hover: the tooltip shows the cell's value and sample count
    scored = [c for c in cells if c.get_attribute("data-miou")]
    cell = scored[0]
    ActionChains(browser).move_to_element(cell).perform()
    tip = browser.find_element(By.ID, "tip")
    assert tip.is_displayed()
    assert f"mIoU {cell.get_attribute('data-miou')}" in tip.text
    assert f"{cell.get_attribute('data-n')} sample" in tip.text
    # its <title> moved into the styled tip, so the browser shows no second, native tooltip
    assert cell.get_attribute("data-tip") == tip.text
    assert not cell.find_elements(By.CSS_SELECTOR, "title")

    # click: the table lists that cell's samples (2 per cell in smoke.toml: one per background)
    cell.click()
    table = browser.find_element(By.ID, "cell-table")
    assert table.is_displayed()
    rows = table.find_elements(By.CSS_SELECTOR, "tbody tr")
    assert len(rows) == 2
    x, y = cell.get_attribute("data-x"), cell.get_attribute("data-y")
    assert f"x = {x}, y = {y}" in browser.find_element(By.ID, "cell-title").text
    assert "selected" in cell.get_attribute("class")

    # no network: no resource entries except data: URIs, no http(s) request in the log
    assert_offline(browser)

    # screenshot: saved, and far from blank (count colours with the browser's own decoder)
    shot = tmp_path / "report.png"
    assert browser.save_screenshot(str(shot))
    png = shot.read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 20_000
    browser.get("about:blank")
    uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
    colours = browser.execute_async_script(COUNT_COLOURS, uri)
    assert colours > 50, colours


def test_replay_uses_the_level_of_detail_the_run_scanned_with() -> None:
    from falsify.jobs.report import run_lod

    assert run_lod({"lod": 0, "fidelity": "exact"}) == 0       # the meta's own record wins
    assert run_lod({"fidelity": "fast"}) == 2                   # older runs: today's preset
    assert run_lod({}) == 2 and run_lod({"fidelity": "ultra"}) == 2


def test_an_incomplete_run_says_so(runs, tmp_path: Path, capsys) -> None:
    """A run stopped before its end: a warning above the summary with the command that finishes
    it, the summary's count of what it planned, and the same in `report --json`."""
    from falsify.world.space import load_space

    stopped = write_run(tmp_path / "stopped", samples=load_space(SMOKE).grid()[:5],
                        meta={"planned": 8, "complete": False, "config_path": EVIL_PATH})
    page = render_report(stopped, predict=False)
    warning = re.search(r'<p id="incomplete" class="bad">(.*?)</p>', page, re.S).group(1)
    assert "5 of 8 planned samples are stored" in warning
    assert "<code>falsify grid " in warning and "--resume</code>" in warning
    assert "&amp;&lt;&gt;.onnx" in warning and '"&<>' not in warning   # the path, escaped
    assert "5 of 8 planned (5 valid)" in page
    assert 'id="incomplete"' not in render_report(runs["evil"], predict=False)
    assert main(["report", str(stopped), "--no-predict", "--out", str(tmp_path / "p.html"),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["samples"], doc["planned"], doc["complete"]) == (5, 8, False)


WEATHER_MIOU = """name = "fog"
sensor = "kitti-hdl64e-front"
seed = 0
[dims.car_model]
values = ["sedan"]
[dims.x]
values = [2.0]
[dims.y]
values = [8.0]
[dims.background]
values = [0]
[dims.fog]
values = [0.0, 50.0]
[dims.colour]
values = ["red", "#00ff00"]
"""


def test_weather_dims_and_a_miou_objective_in_the_tables(tmp_path: Path) -> None:
    """Samples that differ only in a weather or camera dim do not read alike in the worst and
    cell tables (their values are listed), and an mIoU run shows no precision or recall (it
    has none; before: its mIoU under both headings)."""
    config = tmp_path / "fog.toml"
    config.write_text(WEATHER_MIOU)
    run = tmp_path / "run"
    assert main(["grid", str(config), "--out", str(run), "--objective", "miou", "--quiet",
                 "--no-report"]) == 0
    page = render_report(run, predict=False)
    worst = page[page.index('id="worst-section"'):]
    assert "<th>other dims</th>" in worst and "<th>other dims</th>" in page[
        page.index('id="cell-table"'):]
    for fog in (0, 50):
        assert f"colour #00ff00, fog {fog}</td>" in worst
    rows = re.findall(r'<td class="num bad">([0-9.]+)</td><td class="num">(.*?)</td>', worst)
    assert len(rows) == 4 and all(pr == "— /<br>—" for _, pr in rows), rows
    blob = json.loads(re.search(r'id="falsify-data">(.*?)</script>', page, re.S).group(1))
    cols, first = blob["samples"]["columns"], blob["samples"]["rows"][0]
    assert first[cols.index("precision")] is None and first[cols.index("recall")] is None
    assert first[cols.index("other")] == "colour red, fog 0"


def test_the_summary_says_why_samples_are_invalid(tmp_path: Path) -> None:
    """The invalid count comes with its commonest reasons, numbers folded, so a run of mostly
    invalid samples says why on its first screen (before: a bare count)."""
    kinds = ["car 1 (sedan) intersects the background's pole {}",
             "car 1 (sedan) intersects the background's sign {}", "<b>odd</b> & {}"]
    run = write_run(tmp_path / "r", invalid_every=1,
                    invalid_reason=lambda i: kinds[min(i % 5, 2)].format(i))
    page = render_report(run, predict=False)
    card = page[page.index("<dt>Invalid samples</dt>"):]
    card = card[:card.index("</dd>")]
    assert card.startswith("<dt>Invalid samples</dt><dd>8<br>")
    assert ("4 &lt;b&gt;odd&lt;/b&gt; &amp; # · 2 car # (sedan) intersects the background&#x27;s "
            "pole # · 2 car # (sedan) intersects the background&#x27;s sign #") in card, card
    assert "<b>" not in card


def test_in_chromium_the_cell_table_lists_other_dims(browser, tmp_path: Path) -> None:
    """Clicked, a cell of a run with weather and camera dims lists them per sample, and an mIoU
    run's precision and recall read as dashes."""
    from selenium.webdriver.common.by import By

    config, run = tmp_path / "fog.toml", tmp_path / "fog"
    config.write_text(WEATHER_MIOU)
    assert main(["grid", str(config), "--out", str(run), "--objective", "miou", "--quiet",
                 "--no-report"]) == 0
    page = write_report(run, tmp_path / "report.html")
    browser.get(page.as_uri())
    browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")[0].click()
    table = browser.find_element(By.ID, "cell-table")
    heads = [th.text for th in table.find_elements(By.CSS_SELECTOR, "thead th")]
    rows = [[td.text for td in tr.find_elements(By.TAG_NAME, "td")]
            for tr in table.find_elements(By.CSS_SELECTOR, "tbody tr")]
    assert heads[-1] == "other dims" and len(rows) == 4
    assert all(len(r) == len(heads) for r in rows), (heads, rows)
    assert {r[heads.index("precision")] for r in rows} == {"\u2014"}, rows
    assert sorted(r[-1] for r in rows) == ["colour #00ff00, fog 0", "colour #00ff00, fog 50",
                                           "colour red, fog 0", "colour red, fog 50"]


def test_cells_a_hundred_thousandth_apart_keep_their_own_labels_and_samples(tmp_path) -> None:
    """Before: x = 20, 20.00001 and 20.00002 all read "20" (6 significant digits), so the three
    columns shared one label and one click-to-list key (each listed all three columns' rows).
    Now each reads as its own value, as the gate names cells (`axis_texts`)."""
    text = SMOKE.read_text().replace("min = -2.0\nmax = 2.0\nstep = 4.0",
                                      "min = 20.0\nmax = 20.00002\nstep = 0.00001")
    by_x = {20.0: 0.3, 20.00001: 0.6, 20.00002: 0.9}

    def iou(s) -> float:
        return by_x[min(by_x, key=lambda x: abs(x - float(s["x"])))]

    run = write_run(tmp_path / "run", text, iou=iou)
    before = write_run(tmp_path / "before", text, iou=lambda s: 0.5)
    page = render_report(run, compare=before, predict=False)
    xs = re.findall(r'<rect class="cell[^>]* data-x="([^"]*)" data-y="8"', page)
    assert xs == ["20", "20.00001", "20.00002"]
    blob = re.search(r'<script type="application/json" id="falsify-data">(.*?)</script>', page,
                     re.S).group(1)
    samples = json.loads(blob)["samples"]
    assert samples["cells"] == {f"{x}|{y}": 2 for x in xs for y in ("8", "14")}
    cols = samples["columns"]
    for row in samples["rows"]:
        x = float(row[cols.index("cell")].split("|")[0])
        assert row[cols.index("iou")] == pytest.approx(by_x[x], abs=0.002)   # from pixel counts
    # the difference map matches each cell with its own column of the run before
    tips = re.findall(r'<rect class="dcell[^>]*><title>([^<]*)</title>', page)
    assert sorted(t.split("\n")[0] for t in tips) == sorted(
        f"x = {x} m, y = {y} m" for x in xs for y in ("8", "14"))
    assert all("0.500 → " in t for t in tips)
