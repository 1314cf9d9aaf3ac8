"""A class name the user's spec gives is escaped once on the page: the placed object's table
printed `&amp;amp;` for a class named with an ampersand (escaped twice)."""

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
