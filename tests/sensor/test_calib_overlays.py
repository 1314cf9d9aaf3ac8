"""`falsify calib --out` rerun on other frames into the same folder: the earlier run's overlays,
which would read as this run's, are removed; nothing else is, a user's own file or an overlay
the user has since changed included. Real KITTI object frames."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from falsify.cli import main

OVERLAY_LIST = "calib-overlays.json"   # the list of the overlays calib wrote in --out

KINDS = (("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt"), ("image_2", "png"))


@pytest.fixture
def kitti_object(kitti_dir: Path) -> Path:
    d = kitti_dir / "object"
    if not (d / "calib").is_dir():
        pytest.skip(f"KITTI object frames not found at {d}")
    return d


def subset(src: Path, dest: Path, ids: list[str]) -> Path:
    """A KITTI object directory of some of `src`'s frames (links to its files)."""
    for sub, ext in KINDS:
        (dest / sub).mkdir(parents=True)
        for i in ids:
            (dest / sub / f"{i}.{ext}").symlink_to(src / sub / f"{i}.{ext}")
    return dest


def calib(directory: Path, out: Path, capsys) -> tuple[int, str]:
    code = main(["calib", str(directory), "--out", str(out), "--json"])
    return code, capsys.readouterr().err


def test_a_rerun_on_other_frames_leaves_only_its_own_overlays(kitti_object: Path,
                                                              tmp_path: Path, capsys) -> None:
    """Before: the second run's folder held 000000.png and 000001.png from the first beside
    its own 000002.png; after: only the second run's overlay, and the user's files."""
    first = subset(kitti_object, tmp_path / "first", ["000000", "000001"])
    second = subset(kitti_object, tmp_path / "second", ["000002"])
    out = tmp_path / "overlays"
    assert calib(first, out, capsys)[0] == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["000000.png", "000001.png"]
    # the user's own picture, and an overlay the user has since replaced with their own
    (out / "notes.png").write_bytes(b"mine")
    (out / "000001.png").write_bytes(b"edited by hand")
    assert calib(second, out, capsys)[0] == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "000001.png", "000002.png", OVERLAY_LIST, "notes.png"]
    assert (out / "000001.png").read_bytes() == b"edited by hand"
    assert (out / "notes.png").read_bytes() == b"mine"
    listed = json.loads((out / OVERLAY_LIST).read_text())["overlays"]
    assert list(listed) == ["000002.png"]
    # the same frames again: their overlays are rewritten, nothing removed
    assert calib(second, out, capsys)[0] == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "000001.png", "000002.png", OVERLAY_LIST, "notes.png"]


@pytest.mark.parametrize("text", ["{not json", '{"overlays": ["000000.png"]}'],
                         ids=["not_json", "not_a_list_of_overlays"])
def test_a_broken_overlay_list_is_refused_before_anything_is_written(
        text: str, kitti_object: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "overlays"
    out.mkdir()
    (out / OVERLAY_LIST).write_text(text)
    (out / "000009.png").write_bytes(b"mine")
    code, err = calib(subset(kitti_object, tmp_path / "one", ["000000"]), out, capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and f"--out {out / OVERLAY_LIST}:" in lines[0]
    assert sorted(p.name for p in out.iterdir()) == ["000009.png", OVERLAY_LIST]


# -- a file calib did not write is never overwritten (an exported object directory: no data) ---
@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """Two frames of our own scenes as a KITTI object directory."""
    d = tmp_path_factory.mktemp("exported") / "object"
    smoke = Path(__file__).resolve().parents[2] / "configs" / "smoke.toml"
    assert main(["dataset", str(smoke), "--out", str(d), "--scans", "2",
                 "--format", "kitti-object"]) == 0
    return d


def test_out_on_the_directorys_own_images_is_refused_and_they_stay(exported: Path, tmp_path,
                                                                   capsys) -> None:
    """Before: `--out DIR/image_2` replaced the frames' camera images with overlays, exit 0."""
    images = {p.name: p.read_bytes() for p in (exported / "image_2").iterdir()}
    code, err = calib(exported, exported / "image_2", capsys)
    assert code == 2 and "000000.png is there and is not a file `falsify calib` wrote" in err
    assert {p.name: p.read_bytes() for p in (exported / "image_2").iterdir()} == images


def test_a_users_file_named_as_an_overlay_is_refused_and_its_own_rerun_is_not(
        exported: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "overlays"
    assert calib(exported, out, capsys)[0] == 0
    assert calib(exported, out, capsys)[0] == 0          # its own overlays: rewritten
    (out / "000001.png").write_bytes(b"edited by hand")  # now the user's
    code, err = calib(exported, out, capsys)
    assert code == 2 and "000001.png is there and is not a file `falsify calib` wrote" in err
    assert (out / "000001.png").read_bytes() == b"edited by hand"
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "000000.png").write_bytes(b"mine")          # never listed
    assert calib(exported, fresh, capsys)[0] == 2
    assert sorted(p.name for p in fresh.iterdir()) == ["000000.png"]


def test_a_run_stopped_before_its_first_overlay_is_rerun_not_refused(exported: Path,
                                                                     tmp_path: Path) -> None:
    """Before: the list naming the new overlays' bytes was written while the last run's
    overlays still stood, so a run stopped there was refused on its rerun (its own file 'changed
    since'). Now the last run's overlays go first; the rerun writes the new ones."""
    from tests.cli.test_outputs_kills import falsify, killed
    swapped = tmp_path / "swapped"        # the same frame names, each with the other's files
    for sub, ext in KINDS:
        (swapped / sub).mkdir(parents=True)
        for mine, theirs in (("000000", "000001"), ("000001", "000000")):
            (swapped / sub / f"{mine}.{ext}").symlink_to(exported / sub / f"{theirs}.{ext}")
    out = tmp_path / "overlays"
    falsify(["calib", str(exported), "--out", str(out)])
    first = {p.name: p.read_bytes() for p in out.glob("*.png")}
    killed(["calib", str(swapped), "--out", str(out)], ["000000.png", "000001.png"], 1)
    assert not any(p.read_bytes() == first.get(p.name) for p in out.glob("*.png"))
    falsify(["calib", str(swapped), "--out", str(out)])
    again = {p.name: p.read_bytes() for p in out.glob("*.png")}
    assert sorted(again) == ["000000.png", "000001.png"]
    assert again["000000.png"] != first["000000.png"]
