"""The report says a thing once: a class name the user's spec gives is escaped once (the placed
object's table printed `&amp;amp;` for a class named with an ampersand), a grid's run card names
its command once."""

from __future__ import annotations

from pathlib import Path

from falsify.results.store import open_run
from reports.run.maps import inserted_section
from tests.runfixture import write_run


def test_the_objective_class_is_escaped_once(tmp_path: Path) -> None:
    run = write_run(tmp_path / "run", meta={"objective": "bus&<tram>"})
    data = open_run(run)
    data.frame["inserted_iou"] = data.frame["car_iou"]
    data.frame["inserted_recall"] = data.frame["car_iou"]
    html = inserted_section(data, 0.65)
    assert "mean bus&amp;&lt;tram&gt; IoU" in html
    assert "&amp;amp;" not in html and "<tram>" not in html


def test_the_run_card_names_a_grid_once(tmp_path: Path) -> None:
    """A grid's run card read "grid · grid · seed 0" (its command and its algorithm)."""
    from reports.run.summary import summary_section

    data = open_run(write_run(tmp_path / "run", meta={"algorithm": "grid"}))
    html = summary_section(data, data.cell_map(), 0.65)
    card = html.split("<dt>Run</dt><dd>")[1].split("</dd>")[0]
    assert card == "grid · seed 0"
