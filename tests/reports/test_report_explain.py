"""The report's Explain section: a run's built-in failing rule with its numbers, escaping,
determinism, a one-line note when there is nothing to explain, Chromium with no fetch."""

from __future__ import annotations

import html
import re
from pathlib import Path

import pytest

from falsify.errors import FalsifyError
from falsify.jobs.explain import explain_run
from falsify.jobs.report import explain_report, render_report
from falsify.reports.run import ReportInput, render
from falsify.results.explain import Explanation
from falsify.results.store import open_run
from falsify.world.space import load_space
from tests.conftest import assert_offline
from tests.runfixture import SMOKE, write_run

EVIL = '<b>&"van'
EVIL_ESCAPED = "&lt;b&gt;&amp;&quot;van"
# 9 x-values x 8 y-values x 2 car models x 2 backgrounds = 288 samples; the van fails far away.
CONFIG = f"""name = '<b>&"cfg'
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.65

[car_models.'{EVIL}']
file = "van.obj"

[dims.car_model]
values = ["sedan", '{EVIL}']

[dims.x]
min = -4.0
max = 4.0
step = 1.0

[dims.y]
min = 6.0
max = 20.0
step = 2.0

[dims.yaw]
values = [0.0]

[dims.count]
values = [1]

[dims.background]
values = [0, 1]
"""
SECTION = re.compile(r'<section id="explain">.*?</section>', re.S)


def failing_van(sample) -> float:
    """The built-in blind spot: the van at y >= 14 (IoU 0.3); everything else scores 0.9."""
    return 0.3 if sample["car_model"] == EVIL and float(sample["y"]) >= 14 else 0.9


@pytest.fixture(scope="module")
def evil(tmp_path_factory) -> tuple[Path, str]:
    """A grid run with a hostile car model and config name, and its report (no predictions)."""
    run = write_run(tmp_path_factory.mktemp("explain") / "evil", CONFIG, iou=failing_van)
    return run, render_report(run, predict=False)


def section(page: str) -> str:
    found = SECTION.findall(page)
    assert len(found) == 1
    return found[0]


def cheap_page(run: Path) -> str:
    """The report without replayed scans: every section but the worst samples' previews."""
    data = open_run(run)
    return render(ReportInput(data, explanation=explain_report(data)))


def test_the_built_in_rule_with_its_numbers(evil) -> None:
    run, page = evil
    ids = re.findall(r'<section id="([^"]+)"', page)
    assert ids.index("map-section") < ids.index("explain") < ids.index("distance-section")
    sec = section(page)
    rows = re.findall(r'<tr><td class="num">(\d+)</td><td><code>(.*?)</code></td>'
                      r'<td class="num">(\d+)</td><td class="num">(\d+)</td>'
                      r'<td class="num">([\d.]+)</td><td class="num">([\d.]+)</td></tr>', sec)
    assert len(rows) == 1
    _, text, support, failing, precision, mean = rows[0]
    assert set(text.split(" and ")) == {f"car_model == {EVIL_ESCAPED}", "y &gt;= 14"}
    assert (support, failing, precision, mean) == ("72", "72", "1.000", "0.300")
    assert "72 of 288 valid samples have car IoU below 0.650" in sec
    # the same rule, word for word, as `falsify explain RUN` finds it
    assert [r.text() for r in explain_run(run).explanation.rules] == [html.unescape(text)]
    assert 'id="explain-sensitivity"' in sec
    assert 'id="explain-clusters"' not in sec             # grid runs: no clusters (as the CLI)


def test_user_strings_are_escaped(evil) -> None:
    _, page = evil
    assert '<b>&"' not in page and "<b>" not in page
    assert EVIL_ESCAPED in section(page)
    assert "&lt;b&gt;&amp;&quot;cfg" in page


def test_deterministic(evil) -> None:
    run, page = evil
    a, b = cheap_page(run), cheap_page(run)
    assert a == b and section(a) == section(page)


def test_search_run_has_clusters(tmp_path: Path) -> None:
    run = write_run(tmp_path / "search", command="search", seed=3,
                    iou=lambda s: 0.3 if float(s["y"]) < 10 else 0.9)
    sec = section(cheap_page(run))
    assert 'id="explain-clusters"' in sec and 'id="explain-rules"' in sec
    e = explain_report(open_run(run))
    assert isinstance(e, Explanation) and e.clusters
    assert sum(c.size for c in e.clusters) == e.failing
    assert sec.count("<tr>", sec.index('id="explain-clusters"')) == len(e.clusters) + 1


@pytest.mark.parametrize("case", ["none failing", "too few", "error"])
def test_no_explanation_is_one_line(tmp_path: Path, monkeypatch, case: str) -> None:
    if case == "none failing":
        run = write_run(tmp_path / "run", iou=lambda s: 0.9)
        want = "No valid sample has car IoU below the threshold 0.650"
    elif case == "too few":
        run = write_run(tmp_path / "run", samples=load_space(SMOKE).grid()[:2],
                        iou=lambda s: 0.1)
        want = "Too few valid samples to explain (2;"
    else:
        run = write_run(tmp_path / "run")

        def broken(*args, **kwargs):
            raise FalsifyError("<i>broken</i>")
        monkeypatch.setattr("falsify.jobs.report.explain_data", broken)
        want = "could not be explained (&lt;i&gt;broken&lt;/i&gt;)"
    sec = section(cheap_page(run))
    assert want in sec and sec.count('<p class="note">') == 1 and "<table" not in sec


def test_in_chromium(browser, evil, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    run, page = evil
    path = tmp_path / "report.html"
    path.write_text(page, encoding="utf-8")
    browser.get(path.as_uri())
    sec = browser.find_element(By.ID, "explain")
    browser.execute_script("arguments[0].scrollIntoView()", sec)
    assert sec.is_displayed()
    rule = browser.find_element(By.CSS_SELECTOR, "#explain-rules tbody tr code")
    assert rule.is_displayed()
    assert rule.text == explain_run(run).explanation.rules[0].text()
    bars = browser.find_elements(By.CSS_SELECTOR, "#explain-sensitivity td.sbar span")
    assert bars and max(b.size["width"] for b in bars) > 0
    assert_offline(browser)


def test_real_background_names_are_escaped() -> None:
    """On real backgrounds a background's index is followed by its scan's name, escaped."""
    from types import SimpleNamespace

    from falsify.reports.explain_page import explain_section
    from falsify.results.explain import Cluster, Condition, Rule

    names = ["scan-a", '<b>&"scan']
    space = SimpleNamespace(real_backgrounds=tuple(names), background_name=lambda i: names[i])
    rule = Rule((Condition("background", "==", 1),), 10, 9, 0.9, 0.9, 0.2, 0.1)
    e = Explanation(0.65, 20, 9, (rule,), {"background": 0.5},
                    (Cluster({"x": 1.5, "background": 1}, 9, 0.2),))
    sec = explain_section(SimpleNamespace(space=space), e)   # type: ignore[arg-type]
    assert "<b>" not in sec
    assert "<code>background == 1 (&lt;b&gt;&amp;&quot;scan)</code>" in sec
    assert "x = 1.5, background = 1 (&lt;b&gt;&amp;&quot;scan)" in sec
