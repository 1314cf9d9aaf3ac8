"""The report pages for keyboard, screen-reader, colour-blind, phone and print readers, checked in
headless Chromium: the heat map is one Tab stop that the arrow keys walk, its tooltip shows on
focus, cells keep their accessible name, in-cell values and blind-spot outlines read on every
colour, nothing overflows a 390 px screen, and print cuts no picture."""

from __future__ import annotations

import base64
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.jobs.report import write_report
from falsify.reports.charts import contrast
from falsify.reports.realism_page import render_realism
from falsify.reports.tradeoff_page import write_page
from tests.jobs.test_realism import page_doc, sets  # noqa: F401  (the realism page's fixtures)
from tests.runfixture import SMOKE, write_run

# A 4 x 3 map whose cells span the colour ramp: blind ones (< 0.65) across viridis' dark half,
# and 0.67, where white text on viridis' green read at 2.5:1.
XS, YS = (-4.0, -2.0, 2.0, 4.0), (8.0, 11.0, 14.0)
VALUES = (0.02, 0.2, 0.35, 0.42, 0.5, 0.64, 0.67, 0.7, 0.8, 0.9, 0.95, 1.0)
CONFIG = f"""name = "access"
sensor = "kitti-hdl64e-front"
threshold = 0.65
[dims.car_model]
values = ["sedan"]
[dims.x]
values = {list(XS)}
[dims.y]
values = {list(YS)}
[dims.background]
values = [0]
"""


def _iou(sample) -> float:
    i, j = XS.index(float(sample["x"])), YS.index(float(sample["y"]))
    return VALUES[j * len(XS) + i]


@pytest.fixture(scope="module")
def pages(tmp_path_factory) -> dict[str, Path]:
    """The map run's page, and the README's smoke grid (its own scans, the placed cars' table)
    compared with a written run, in a folder whose long name has no place to break."""
    root = tmp_path_factory.mktemp("access")
    run = write_run(root / "map-run", CONFIG, iou=_iou)
    before = write_run(root / "before", SMOKE, seed=7)
    long = root / ("a_run_folder_whose_name_is_far_wider_than_a_phone_" * 2)
    assert main(["grid", str(SMOKE), "--out", str(long), "--quiet"]) == 0
    return {"map": write_report(run, predict=False),
            "compare": write_report(long, compare=before, predict=False)}


def _key(browser, key: str) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    ActionChains(browser).send_keys(key).perform()


def _shift_tab(browser) -> None:
    """Shift+Tab held together (send_keys presses and releases Shift before the Tab)."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys
    ActionChains(browser).key_down(Keys.SHIFT).send_keys(Keys.TAB).key_up(Keys.SHIFT).perform()


def _active(browser):
    return browser.switch_to.active_element


def test_the_heat_map_is_one_tab_stop_walked_with_the_arrow_keys(browser, pages) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    browser.get(pages["map"].as_uri())
    cells = browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")
    assert len(cells) == len(XS) * len(YS)
    # one Tab reaches the map; a second leaves it (it used to step through every cell)
    _key(browser, Keys.TAB)
    first = _active(browser)
    assert "cell" in first.get_attribute("class")
    assert (first.get_attribute("data-x"), first.get_attribute("data-y")) == ("-4", "8")
    _key(browser, Keys.TAB)
    assert "cell" not in (_active(browser).get_attribute("class") or "")
    _shift_tab(browser)
    assert _active(browser) == first

    # the arrow keys move along the row and to the row drawn above (farther)
    _key(browser, Keys.ARROW_RIGHT)
    assert _active(browser).get_attribute("data-x") == "-2"
    _key(browser, Keys.ARROW_UP)
    cell = _active(browser)
    assert (cell.get_attribute("data-x"), cell.get_attribute("data-y")) == ("-2", "11")
    _key(browser, Keys.END)
    assert _active(browser).get_attribute("data-x") == "4"
    _key(browser, Keys.ARROW_RIGHT)                       # the row's end: focus stays
    cell = _active(browser)
    assert cell.get_attribute("data-x") == "4"
    # Tab away and back returns to the cell last focused
    _key(browser, Keys.TAB)
    _shift_tab(browser)
    assert _active(browser) == cell

    # the tooltip shows on focus, beside the cell, and Escape hides it
    tip = browser.find_element(By.ID, "tip")
    assert tip.is_displayed()
    assert "x = 4 m, y = 11 m" in tip.text and f"mIoU {cell.get_attribute('data-miou')}" in tip.text
    _key(browser, Keys.ESCAPE)
    assert not tip.is_displayed()

    # a ring in black and white marks the focused cell over its neighbours
    ring = browser.find_element(By.ID, "focusring")
    assert ring.get_attribute("visibility") == "visible"
    box = browser.execute_script(
        "const r = document.querySelector('#focusring .inner'), c = arguments[0];"
        "return [+r.getAttribute('x') + 1 - c.getAttribute('x'),"
        " +r.getAttribute('width') - 2 - c.getAttribute('width')]", cell)
    assert box == [0, 0]

    # Enter lists the focused cell's samples
    _key(browser, Keys.ENTER)
    assert "x = 4, y = 11" in browser.find_element(By.ID, "cell-title").text
    assert browser.find_element(By.ID, "cell-table").is_displayed()


def test_screen_readers_get_a_named_group_of_named_buttons(browser, pages) -> None:
    from selenium.webdriver.common.by import By

    browser.get(pages["map"].as_uri())
    svg = browser.find_element(By.ID, "heatmap")
    # a role=img map hid its focusable cells from screen readers
    assert svg.aria_role == "group" and "heat map" in svg.accessible_name
    cell = browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")[0]
    name = cell.accessible_name
    assert cell.aria_role == "button" and name.startswith("x = -4 m, y = 8 m")
    cell.click()       # hovered and clicked: its <title> moved into the tooltip, the name stays
    assert not cell.find_elements(By.CSS_SELECTOR, "title")
    assert cell.accessible_name == name
    assert browser.find_element(By.ID, "cell-title").get_attribute("aria-live") == "polite"
    assert browser.title == "falsify report: access · map-run"


def test_values_in_cells_read_on_every_colour(browser, pages) -> None:
    browser.get(pages["map"].as_uri())
    pairs = browser.execute_script("""
        const out = [];
        for (const t of document.querySelectorAll('#heatmap text.lbl')) {
          const x = +t.getAttribute('x'), y = +t.getAttribute('y');
          const cell = [...document.querySelectorAll('#heatmap .cell')].find(c =>
            x > +c.getAttribute('x') && x < +c.getAttribute('x') + +c.getAttribute('width') &&
            y > +c.getAttribute('y') && y < +c.getAttribute('y') + +c.getAttribute('height'));
          const m = getComputedStyle(t).fill.match(/\\d+/g).map(Number);
          out.push([t.textContent, '#' + m.map(v => v.toString(16).padStart(2, '0')).join(''),
                    cell.getAttribute('fill')]);
        }
        return out;""")
    assert len(pairs) == len(VALUES)
    low = [(v, ink, fill, round(contrast(ink, fill), 2)) for v, ink, fill in pairs
           if contrast(ink, fill) < 4.5]
    assert not low, low                                 # WCAG AA for text


OUTLINE_CONTRAST = """
const done = arguments[arguments.length - 1], boxes = arguments[1], img = new Image();
function lum(p) {
  const v = [p[0], p[1], p[2]].map(x => { x /= 255;
    return x <= 0.03928 ? x / 12.92 : ((x + 0.055) / 1.055) ** 2.4; });
  return 0.2126 * v[0] + 0.7152 * v[1] + 0.0722 * v[2];
}
img.onload = () => {
  const c = document.createElement('canvas'); c.width = img.width; c.height = img.height;
  const g = c.getContext('2d'); g.drawImage(img, 0, 0);
  done(boxes.map(([l, t, w, h, s]) => {
    // the cell's fill at its centre, then every pixel from its left edge 8 px inwards
    const f = lum(g.getImageData(Math.round((l + w / 2) * s), Math.round((t + h / 2) * s) - 8,
                                 1, 1).data);
    let best = 1;
    for (let x = Math.round(l * s); x < Math.round((l + 8) * s); x++) {
      const p = lum(g.getImageData(x, Math.round((t + h / 2) * s), 1, 1).data);
      best = Math.max(best, (Math.max(p, f) + 0.05) / (Math.min(p, f) + 0.05));
    }
    return best;
  }));
};
img.src = arguments[0];
"""


def test_blind_spot_outlines_stand_out_on_every_colour(browser, pages) -> None:
    """Each blind cell's outline holds a pixel at 3:1 or more against the cell's own colour
    (WCAG's non-text contrast); the red alone matched viridis' teal at about 1:1."""
    from selenium.webdriver.common.by import By

    browser.get(pages["map"].as_uri())
    blind = browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell.blind")
    assert len(blind) == sum(v < 0.65 for v in VALUES)
    browser.execute_script("document.getElementById('heatmap').scrollIntoView()")
    boxes = [browser.execute_script(
        "const b = arguments[0].getBoundingClientRect();"
        "return [b.left, b.top, b.width, b.height, devicePixelRatio]", c) for c in blind]
    shot = browser.get_screenshot_as_png()
    browser.get("about:blank")
    uri = "data:image/png;base64," + base64.b64encode(shot).decode("ascii")
    best = browser.execute_async_script(OUTLINE_CONTRAST, uri, boxes)
    assert min(best) >= 3.0, best


OVERFLOW = """
const W = document.documentElement.clientWidth, out = [];
function clipped(el, r) {     // cut by the page's edge or by a box that clips or scrolls it
  if (r.right > W + 1 || r.left < -1) return true;
  for (let p = el.parentElement; p && p !== document.body; p = p.parentElement) {
    if (getComputedStyle(p).overflowX === 'visible') continue;
    const q = p.getBoundingClientRect();
    if (r.right > q.right + 1 || r.left < q.left - 1) return true;
  }
  return false;
}
for (const el of document.querySelectorAll('main img, main svg')) {
  const r = el.getBoundingClientRect();
  if (r.width && clipped(el, r)) out.push(el.id || el.getAttribute('class') || el.alt);
}
return [document.documentElement.scrollWidth, W, out];
"""


def _width(browser, width: int, media: str = "screen") -> None:
    browser.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                            {"width": width, "height": 900, "deviceScaleFactor": 1,
                             "mobile": False})
    browser.execute_cdp_cmd("Emulation.setEmulatedMedia", {"media": media})


@pytest.mark.parametrize("width", [1280, 390])
def test_nothing_overflows_a_laptop_or_a_phone(browser, pages, width: int) -> None:
    """The page never scrolls sideways (wide tables scroll in their own box); charts shrink to
    fit. On a phone the plots, the tables and the run's long folder name overflowed."""
    browser.get(pages["compare"].as_uri())
    _width(browser, width)
    scroll, client, _ = browser.execute_script(OVERFLOW)
    assert scroll <= client, (scroll, client)
    assert browser.execute_script(
        "return [...document.querySelectorAll('main table')].map(t =>"
        " getComputedStyle(t.parentElement).overflowX)") == ["auto"] * 3   # cell, cars, worst


def test_print_cuts_no_chart_or_scan(browser, pages) -> None:
    """Printed (A4's 700 px width), no scan picture or chart is clipped: the worst samples' table
    scrolled sideways, so the printed page cut its range images off; charts and table rows are
    not split across pages, and a tooltip left open does not print."""
    from selenium.webdriver.common.by import By

    browser.get(pages["compare"].as_uri())
    cell = browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")[0]
    cell.click()                                    # its table open, its tooltip showing
    assert browser.find_element(By.ID, "tip").is_displayed()
    _width(browser, 700, "print")
    assert browser.find_elements(By.CSS_SELECTOR, 'img[alt="range image, label"]')
    _, _, cut = browser.execute_script(OVERFLOW)
    assert not cut, cut
    assert browser.execute_script(
        "return [...document.querySelectorAll('main figure, #worst-section tr')]"
        ".every(e => getComputedStyle(e).breakInside === 'avoid')")
    assert browser.execute_script(      # shown as run.js shows it, on the element itself
        "const t = document.getElementById('tip'); t.style.display = 'block';"
        "return getComputedStyle(t).display") == "none"
    pdf = browser.execute_cdp_cmd("Page.printToPDF", {})
    assert base64.b64decode(pdf["data"]).startswith(b"%PDF")


LOW_CONTRAST = """
function lum(c) {
  const m = c.match(/[\\d.]+/g).map(Number);
  const v = m.slice(0, 3).map(x => { x /= 255;
    return x <= 0.03928 ? x / 12.92 : ((x + 0.055) / 1.055) ** 2.4; });
  return [0.2126 * v[0] + 0.7152 * v[1] + 0.0722 * v[2], m.length > 3 ? m[3] : 1];
}
function background(el) {
  for (let p = el; p; p = p.parentElement) {
    const c = getComputedStyle(p).backgroundColor;
    if (lum(c)[1] > 0) return c;
  }
  return 'rgb(255, 255, 255)';
}
const out = [], walk = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
while (walk.nextNode()) {
  const el = walk.currentNode.parentElement;
  if (!walk.currentNode.textContent.trim() || el.closest('svg, script, style')) continue;
  if (!el.getClientRects().length) continue;
  const f = lum(getComputedStyle(el).color)[0], b = lum(background(el))[0];
  const ratio = (Math.max(f, b) + 0.05) / (Math.min(f, b) + 0.05);
  if (ratio < 4.5) out.push([walk.currentNode.textContent.trim().slice(0, 30), ratio]);
}
return out;
"""


def test_body_text_meets_wcag_aa(browser, pages) -> None:
    browser.get(pages["compare"].as_uri())
    assert browser.execute_script(LOW_CONTRAST) == []


TRADEOFF = {
    "config": "configs/smoke.toml", "samples": 40, "limit": None, "model": "/m/net.onnx",
    "model_hash": "ab" * 8, "threshold": 0.65, "threads": 1, "batch": 1,
    "machine": {"cpus": 2, "processor": "x86_64"},
    "reference": {"resolution": "64x512", "lod": 0, "precision": "onnx fp32", "crf": 3,
                  "grid": "the config's", "time_per_sample_ms": 20.0, "blind_spots": 3,
                  "lowest_cell_miou": 0.41},
    "rows": [{"knob": k, "setting": s, "is_reference": ref, "time_per_sample_ms": ms,
              "speedup": None if ms is None else 20.0 / ms, "map_mean_abs_error": err,
              "map_max_abs_error": err, "blind_spot_jaccard": 1.0, "blind_spots": 3,
              "samples": 40, "notes": note, "map_time_s": None if ms is None else ms * 0.04}
             for k, s, ref, ms, err, note in (
                 ("resolution", "64x512", True, 20.0, 0.0, ""),
                 ("resolution", "32x256", False, 8.0, 0.03, ""),
                 ("crf", "0", False, 15.0, 0.01, ""),
                 ("crf", "3", False, None, None, "skipped: missing package torch"))],
    "notes": [],
}


def test_tradeoff_page_on_a_phone_and_its_skipped_rows_readable(browser, tmp_path: Path) -> None:
    """The trade-off page's plot shrinks and its table scrolls in its box on a phone; skipped
    rows were grey at 3.5:1."""
    page = write_page(TRADEOFF, tmp_path / "tradeoff.html")
    browser.get(page.as_uri())
    assert browser.execute_script(LOW_CONTRAST) == []
    _width(browser, 390)
    scroll, client, _ = browser.execute_script(OVERFLOW)
    assert scroll <= client, (scroll, client)


def test_realism_page_on_a_phone(browser, page_doc, tmp_path: Path) -> None:  # noqa: F811
    """The realism page's wide tables scroll in their own box on a phone, its charts shrink, and
    the legend's line samples are hidden from screen readers (each chart is named)."""
    path = tmp_path / "realism.html"
    path.write_text(render_realism(page_doc), encoding="utf-8")
    browser.get(path.as_uri())
    assert browser.execute_script(
        "return [...document.querySelectorAll('svg')].filter(s =>"
        " s.getAttribute('aria-hidden') !== 'true' && !s.getAttribute('aria-label')).length") == 0
    assert browser.execute_script(LOW_CONTRAST) == []
    _width(browser, 390)
    scroll, client, _ = browser.execute_script(OVERFLOW)
    assert scroll <= client, (scroll, client)
