"""`falsify predict`'s inputs: each scan once, one output per scan, labels checked and named,
and options that would do nothing refused (exit 2, one line, nothing written)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from tests.jobs.test_predict import BUNDLED, synthetic_scans


def random_bin(path: Path, n: int = 2000, seed: int = 0) -> Path:
    """A KITTI .bin of `n` points around the sensor (x, y, z, reflectance float32)."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(-2, 1, n),
                           rng.uniform(0, 1, n)]).astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    pts.tofile(path)
    return path


def refused(argv: list[str], out: Path, capsys) -> str:
    """The one error line of a predict that exits 2 and writes nothing."""
    assert main(["predict", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and not out.exists()
    return err


def test_same_stem_twice_in_a_folder_is_refused(tmp_path, capsys):
    """s.npy beside s.bin would both write s.pred.npy / s.png: one would overwrite the other."""
    folder = tmp_path / "stem"
    folder.mkdir()
    (npy,) = synthetic_scans(folder, 1)
    Path(npy).rename(folder / "s.npy")
    random_bin(folder / "s.bin")
    err = refused([str(folder)], tmp_path / "out", capsys)
    assert str(folder / "s.npy") in err and str(folder / "s.bin") in err


def test_a_scan_named_twice_is_refused(tmp_path, capsys):
    (npy,) = synthetic_scans(tmp_path, 1)
    err = refused([npy, npy], tmp_path / "out", capsys)
    assert f"{npy}: given twice" in err
    link = tmp_path / "link.npy"
    link.symlink_to(npy)
    err = refused([npy, str(link)], tmp_path / "out", capsys)
    assert str(link) in err and npy in err
    err = refused([npy, str(tmp_path)], tmp_path / "out", capsys)   # and in its folder
    assert "given twice" in err


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_sets_of_the_same_name_write_under_out(tmp_path, capsys):
    """Two folders named x are two sets named by their paths; their outputs stay under --out."""
    a, b = tmp_path / "a" / "x", tmp_path / "b" / "x"
    for k, folder in enumerate((a, b)):
        folder.mkdir(parents=True)
        (npy,) = synthetic_scans(folder, 1)
        scan = np.load(npy)
        scan[..., 3] *= 1 + k    # other bytes: a copy would be refused
        np.save(npy, scan)
    out = tmp_path / "out"
    assert main(["predict", str(a), str(b), "--out", str(out), "--json"]) == 0
    json.loads(capsys.readouterr().out)
    assert not list(a.glob("*.pred.npy")) and not list(b.glob("*.pred.npy"))
    assert len(list(out.rglob("syn0.pred.npy"))) == 2


@pytest.mark.parametrize("value", [7, -1, 0.5])
def test_label_outside_the_classes_names_the_file(tmp_path, capsys, value):
    (npy,) = synthetic_scans(tmp_path, 1)
    scan = np.load(npy)
    scan[0, 0, 5] = value
    np.save(npy, scan)
    err = refused([npy], tmp_path / "out", capsys)
    assert npy in err and "allowed class ids 0..3" in err


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_labels_without_a_scan_are_named(tmp_path, capsys):
    """A sequence with three .label and one .bin: the two orphan labels are warned of by name and
    listed in the JSON."""
    seq = tmp_path / "root" / "sequences" / "04"
    bin_ = random_bin(seq / "velodyne" / "000000.bin", n=500)
    (seq / "labels").mkdir()
    for stem in ("000000", "000005", "000009"):
        np.zeros(500, np.uint32).tofile(seq / "labels" / f"{stem}.label")
    assert main(["predict", str(bin_.parents[2]), "--out", str(tmp_path / "o"), "--json"]) == 0
    captured = capsys.readouterr()
    orphans = [str(seq / "labels" / f"{s}.label") for s in ("000005", "000009")]
    assert json.loads(captured.out)["labels_without_scans"] == orphans
    for o in orphans:
        assert o in captured.err


def test_sensor_with_only_npy_scans_is_refused(tmp_path, capsys):
    (npy,) = synthetic_scans(tmp_path, 1)
    err = refused([npy, "--sensor", "vlp16"], tmp_path / "out", capsys)
    assert "--sensor vlp16" in err


def test_backend_with_a_plugin_is_refused(tmp_path, capsys):
    (npy,) = synthetic_scans(tmp_path, 1)
    err = refused([npy, "--model", "falsify.models.pointnet:reference", "--backend", "torch"],
                  tmp_path / "out", capsys)
    assert "--backend torch" in err


def test_help_names_every_folder_an_object_directory_needs(capsys):
    with pytest.raises(SystemExit):
        main(["predict", "--help"])
    assert "image_2/" in capsys.readouterr().out
