"""`falsify gate`'s names as CI dashboards merge them: each run's JUnit suite and classname are its
own (several runs gated in one job do not clash), and no two cells share a name, however close
their coordinates."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.results.store import STORE_NAME
from tests.jobs.test_gate import BLIND, iou_of
from tests.jobs.test_gate_ci import read_junit
from tests.runfixture import write_run


def junit_of(run: Path | str, junit: Path, capsys) -> ET.Element:
    main(["gate", str(run), "--junit", str(junit)])
    capsys.readouterr()
    return read_junit(junit)


def case_ids(suite: ET.Element) -> set[tuple[str, str]]:
    """(classname, name) of each testcase: what GitLab and Jenkins key a test's history by."""
    return {(c.get("classname"), c.get("name")) for c in suite.findall("testcase")}


def test_two_runs_gated_in_one_job_do_not_clash(tmp_path: Path, monkeypatch, capsys) -> None:
    """Before: every suite was "falsify.jobs.gate" and every classname too, so two models' runs
    (both named grid) published the same testcases; after: each is named by its path."""
    monkeypatch.chdir(tmp_path)
    iou = iou_of({BLIND: 0.5})
    suites = {}
    for model in ("squeezeseg", "pointnet"):
        write_run(tmp_path / "runs" / model / "grid", iou=iou)
        suites[model] = junit_of(f"runs/{model}/grid", tmp_path / f"{model}.xml", capsys)
    a, b = suites["squeezeseg"], suites["pointnet"]
    assert a.get("name") == "falsify gate: runs/squeezeseg/grid"
    assert b.get("name") == "falsify gate: runs/pointnet/grid"
    assert {c for c, _ in case_ids(a)} == {"falsify.gate.runs_squeezeseg_grid"}
    assert {c for c, _ in case_ids(b)} == {"falsify.gate.runs_pointnet_grid"}
    assert len(case_ids(a)) == len(case_ids(b)) == 4 and not case_ids(a) & case_ids(b)
    # the same run named another way (./, a trailing /, its store) gets the same names
    for other in ("./runs/squeezeseg/grid/", f"runs/squeezeseg/grid/{STORE_NAME}"):
        again = junit_of(other, tmp_path / "again.xml", capsys)
        assert again.get("name") == a.get("name") and case_ids(again) == case_ids(a)


@pytest.mark.parametrize(("folder", "classname"), [
    ("model.v2 (night)", "falsify.gate.model_v2__night_"),
    ("a&b<c>\x01", "falsify.gate.a_b_c__")], ids=["dots_spaces", "xml_specials"])
def test_a_run_outside_the_working_directory_is_named_by_its_folder(
        folder: str, classname: str, tmp_path: Path, monkeypatch, capsys) -> None:
    """Outside the working directory only the folder's name is kept (a temporary parent's
    name changes between CI jobs); the classname keeps no dot, which Jenkins reads as a
    package, and the file parses whatever the name holds."""
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    run = write_run(tmp_path / folder, iou=iou_of({BLIND: 0.5}))
    suite = junit_of(run, tmp_path / "gate.xml", capsys)
    assert suite.get("name") == "falsify gate: " + folder.replace("\x01", "\\x01")
    assert {c for c, _ in case_ids(suite)} == {classname}


NEAR = """name = "near"
sensor = "kitti-hdl64e-front"
threshold = 0.65
[dims.car_model]
values = ["sedan"]
[dims.x]
values = [-2.0, 10.00001, 10.00002]
[dims.y]
values = [8.0, 14.0]
[dims.background]
values = [0]
"""


def test_cells_a_fifth_decimal_apart_have_their_own_names(tmp_path: Path, capsys) -> None:
    """Before: x = 10.00001 and 10.00002 both printed as 10 (6 significant digits), so two
    blind spots read as one cell in the text and two JUnit testcases had one name; after: they
    get the digits that tell them apart, other values keep their shortest form."""
    run = write_run(tmp_path / "near", NEAR,
                    iou=iou_of({(10.00001, 8.0): 0.4, (10.00002, 8.0): 0.5}))
    junit = tmp_path / "gate.xml"
    assert main(["gate", str(run), "--junit", str(junit)]) == 1
    out = capsys.readouterr().out
    lines = [ln.strip() for ln in out.splitlines() if ln.strip().startswith("cell ")]
    assert lines == ["cell x=10.00001 y=8: mIoU 0.400, 0.250 below the threshold (1 samples)",
                     "cell x=10.00002 y=8: mIoU 0.500, 0.150 below the threshold (1 samples)"]
    names = [c.get("name") for c in read_junit(junit).findall("testcase")]
    assert names == ["cell x=-2 y=8", "cell x=10.00001 y=8", "cell x=10.00002 y=8",
                     "cell x=-2 y=14", "cell x=10.00001 y=14", "cell x=10.00002 y=14"]


def test_axis_texts_are_shortest_unless_digits_are_needed() -> None:
    """Float round-off stays hidden (0.1 + 0.2 reads 0.3); doubles one ulp apart still differ."""
    from falsify.results.miou_maps import axis_texts

    assert list(axis_texts([2.5, -2.0, 0.1 + 0.2, 2.5]).values()) == ["-2", "0.3", "2.5"]
    texts = axis_texts([1.0, 1.0 + 2.0 ** -52])
    assert len(set(texts.values())) == 2 and texts[1.0] == "1"
