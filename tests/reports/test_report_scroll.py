"""Tables in scroll boxes for keyboard and screen-reader users, checked in headless Chromium: each
box is a Tab stop (browsers before Chromium 130, and Safari, scroll only what is focusable) named
for its table, so a reader hears what the stop is, and the arrow keys then scroll it; no table
has a column heading without a name."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import assert_offline
from tests.reports.test_report_access import TRADEOFF, _key, _width, pages  # noqa: F401
from tests.reports.test_report_explain import evil  # noqa: F401  (the explain section's run)


def scroll_boxes(browser) -> list[tuple[int, str, str]]:
    """Each .scroll box's tab index, and the role and name Chromium's accessibility tree gives
    it (WebDriver's computed role and label, what a screen reader is told)."""
    from selenium.webdriver.common.by import By

    boxes = browser.find_elements(By.CSS_SELECTOR, ".scroll")
    assert boxes
    return [(int(b.get_attribute("tabIndex")), b.aria_role, b.accessible_name) for b in boxes]


def test_every_scroll_box_is_a_named_tab_stop(browser, pages, evil, tmp_path: Path  # noqa: F811
                                              ) -> None:
    """Before: plain <div class="scroll">, role generic, no name, tab index -1; after: a
    region named for its table, tab index 0, on the run, compare and trade-off pages. The
    box of a cell's samples is no empty stop: it shows once a cell is picked."""
    from selenium.webdriver.common.by import By

    from falsify.reports.tradeoff_page import write_page

    explain = tmp_path / "explain.html"
    explain.write_text(evil[1], encoding="utf-8")
    names = {}
    for key, page in (("compare", pages["compare"]), ("explain", explain),
                      ("tradeoff", write_page(TRADEOFF, tmp_path / "tradeoff.html"))):
        browser.get(page.as_uri())
        if key != "tradeoff":
            cell_box = browser.find_element(By.CSS_SELECTOR, "#cell-samples .scroll")
            assert not cell_box.is_displayed()
            browser.find_elements(By.CSS_SELECTOR, "#heatmap .cell")[0].click()
            assert cell_box.is_displayed()
        boxes = scroll_boxes(browser)
        assert all(t == 0 and role == "region" and name for t, role, name in boxes), boxes
        names[key] = [name for _, _, name in boxes]
        assert_offline(browser)
    assert names["compare"][0] == "Samples of the selected cell"
    assert names["compare"][-1].startswith("The ") and names["compare"][-1].endswith(" samples")
    assert names["explain"][1:3] == ["Rules where samples fail", "Sensitivity"]
    assert names["tradeoff"] == ["Speed and map error per setting"]


def test_a_wide_table_is_reached_by_tab_and_scrolled_by_the_arrow_keys(
        browser, pages) -> None:  # noqa: F811
    """On a phone the worst samples' table is wider than its box: Tab reaches the box, then
    the right arrow scrolls it (Chromium 130+ focuses such a box by itself, so this guards the
    behaviour rather than the attributes, which the test above checks)."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.wait import WebDriverWait

    browser.get(pages["compare"].as_uri())
    _width(browser, 390)
    box = browser.find_element(By.CSS_SELECTOR, "#worst-section .scroll")
    assert browser.execute_script("return arguments[0].scrollWidth > arguments[0].clientWidth",
                                  box)
    for _ in range(80):
        _key(browser, Keys.TAB)
        if browser.switch_to.active_element == box:
            break
    else:
        raise AssertionError("Tab never reached the worst samples' scroll box")
    assert browser.execute_script("return arguments[0].scrollLeft", box) == 0
    for _ in range(3):
        _key(browser, Keys.ARROW_RIGHT)
    # the arrows scroll smoothly, over several frames: wait for it (or fail after 10 s)
    WebDriverWait(browser, 10).until(
        lambda b: b.execute_script("return arguments[0].scrollLeft", box) > 0)


def test_the_sensitivity_bar_column_has_a_hidden_name(browser, evil, tmp_path: Path  # noqa: F811
                                                      ) -> None:
    """Before: its heading was an empty <th>, a column a screen reader announces as nothing;
    after: it is named, the name visually hidden (the bars speak for themselves on screen)."""
    from selenium.webdriver.common.by import By

    page = tmp_path / "explain.html"
    page.write_text(evil[1], encoding="utf-8")
    browser.get(page.as_uri())
    heads = browser.find_elements(By.CSS_SELECTOR, "#explain-sensitivity thead th")
    assert [h.accessible_name for h in heads] == ["dim", "share", "share, as a bar"]
    label = heads[2].find_element(By.CSS_SELECTOR, "span")
    width, height = browser.execute_script(
        "const r = arguments[0].getBoundingClientRect(); return [r.width, r.height]", label)
    assert width <= 1 and height <= 1
