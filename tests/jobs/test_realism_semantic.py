"""`falsify realism` over SemanticKITTI's classes: per-class point fractions of synthetic sets
written with `--labels semantickitti` and of labelled real sequences, their total variation (a
diagnostic), unchanged four-class statistics, and the page's table."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.cli.realism import realism_text
from falsify.data.scansets import load_sets
from falsify.reports.realism_page import render_realism
from falsify.results.scan_statistics import SetStats
from falsify.semantic import TRAIN_CLASSES, kitti4, kitti4_of_train, train_ids
from falsify.sensor.lidar import load_sensor
from tests.conftest import CONFIGS, KITTI_DIR, ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
SEQUENCE = KITTI_DIR / "semantickitti-mini" / "sequences" / "01"   # a fit sequence
SENSOR = "kitti-hdl64e-front"
EVIL = '<b>&"x'
SK = EVIL   # the semantickitti-labelled set: a name the page must escape
SEMANTIC_KEYS = {"semantic_fraction", "unlabeled_fraction"}

needs_model = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")


def test_train_ids_map_to_the_four_classes_as_raw_ids_do() -> None:
    raw = np.arange(260)
    assert np.array_equal(kitti4_of_train(train_ids(raw)), kitti4(raw))
    named = {c: kitti4_of_train(np.array([TRAIN_CLASSES.index(c)]))[0] for c in TRAIN_CLASSES}
    assert {c: v for c, v in named.items() if v} == {"car": 1, "person": 2, "bicyclist": 3,
                                                     "motorcyclist": 3}
    assert list(kitti4_of_train(np.array([-1, 20, 300]))) == [0, 0, 0]


def _images(labels: np.ndarray) -> np.ndarray:
    """(B, 2, 3, 6) scans: every pixel valid except the last column, labels in channel 5."""
    im = np.zeros((*labels.shape, 6), np.float32)
    im[..., 4] = 5.0
    im[..., -1, 4] = 0.0
    im[..., 5] = labels
    return im


def test_semantic_counts_per_scan_valid_points_only_and_merge() -> None:
    ids = np.array([[[1, 1, 9], [0, 6, 9]], [[9, 9, 9], [7, 0, 1]]])
    sem = SetStats("sem")
    sem.add(_images(kitti4_of_train(ids)), None, semantic=ids)
    table = sem.scan_table("semantic")
    assert table.shape == (2, len(TRAIN_CLASSES))
    assert list(table[0][[0, 1, 6, 9]]) == [1, 2, 1, 0] and table[0].sum() == 4
    assert list(table[1][[0, 7, 9]]) == [1, 1, 2] and table[1].sum() == 4
    with pytest.raises(ValueError, match="some scans but not all"):
        sem.add(_images(kitti4_of_train(ids)), None)
    plain = SetStats("plain")
    plain.add(_images(kitti4_of_train(ids)), None)
    assert not plain.has_semantic and "semantic" not in plain.per_scan
    assert np.array_equal(plain.scan_table("classes"), sem.scan_table("classes"))
    assert sem.merged(sem, "both").has_semantic
    assert not sem.merged(plain, "mixed").has_semantic
    assert not plain.merged(sem, "mixed").has_semantic


# -- the command ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, Path]:
    """The same four scenes written with SemanticKITTI's train ids and with our four classes."""
    if not SEQUENCE.is_dir():
        pytest.skip(f"SemanticKITTI sequence not found at {SEQUENCE} (shared/data/ is beside "
                    "the repo)")
    root = tmp_path_factory.mktemp("semantic")
    out = {"sk": root / SK, "k4": root / "k4"}
    for labels, folder in (("semantickitti", out["sk"]), ("kitti4", out["k4"])):
        code = main(["dataset", str(CONFIGS / "smoke.toml"), "--scans", "4", "--labels", labels,
                     "--max-cars", "3", "--out", str(folder)])
        assert code == 0
    return out


def _realism(args: list[str], out: Path, capsys) -> tuple[dict, str]:
    code = main(["realism", *args, "--real", str(SEQUENCE), "--out", str(out)])
    text = capsys.readouterr()
    assert code == 0, text.err
    return json.loads((out / "realism.json").read_text()), text.out


@pytest.fixture(scope="module")
def both(folders, tmp_path_factory) -> tuple[dict, Path]:
    """Realism of the semantickitti-labelled set, then the four-class one, against sequence 01."""
    out = tmp_path_factory.mktemp("both")
    code = main(["realism", str(folders["sk"]), str(folders["k4"]), "--real", str(SEQUENCE),
                 "--out", str(out)])
    assert code == 0
    return json.loads((out / "realism.json").read_text()), out


def _labelled_fractions(counts: np.ndarray) -> np.ndarray:
    return counts[1:] / counts[1:].sum()


def _ordered(stats: dict) -> list[float]:
    """A set's fractions in train-id order."""
    return [stats["semantic_fraction"][c] for c in TRAIN_CLASSES[1:]]


@needs_model
def test_fractions_match_a_direct_bincount(folders, both) -> None:
    doc, _ = both
    syn, k4 = doc["synthetic"]
    real = doc["real"][0]
    assert (syn["name"], k4["name"], real["name"]) == (SK, "k4", "01")
    for s in (syn, real):
        assert set(s["semantic_fraction"]) == set(TRAIN_CLASSES[1:])   # JSON sorts keys
        assert sum(s["semantic_fraction"].values()) == pytest.approx(1.0, abs=1e-5)
    # synthetic: channel 5 of the npy files is the train id of each valid pixel
    counts = np.zeros(len(TRAIN_CLASSES), np.int64)
    for p in sorted(folders["sk"].glob("*.npy")):
        im = np.load(p)
        counts += np.bincount(im[..., 5][im[..., 4] > 0].astype(np.int64),
                              minlength=len(TRAIN_CLASSES))
    want_syn = _labelled_fractions(counts)
    assert _ordered(syn) == pytest.approx(list(want_syn), abs=1e-6)
    assert syn["unlabeled_fraction"] == pytest.approx(counts[0] / counts.sum(), abs=1e-6)
    # real: the raw ids of the projected points, mapped to train ids
    (scans,) = load_sets([str(SEQUENCE)], load_sensor(SENSOR))
    ids = train_ids(scans.semantic)[scans.images[..., 4] > 0].astype(np.int64)
    counts = np.bincount(ids, minlength=len(TRAIN_CLASSES))
    want_real = _labelled_fractions(counts)
    assert _ordered(real) == pytest.approx(list(want_real), abs=1e-6)
    assert real["unlabeled_fraction"] == pytest.approx(counts[0] / counts.sum(), abs=1e-6)
    assert 0 < real["unlabeled_fraction"] < 0.5
    # the diagnostic distance: total variation of the two, only for pairs that both have it
    tv = doc["distances"][SK]["01"]["semantic_classes"]
    assert tv == pytest.approx(0.5 * np.abs(want_syn - want_real).sum(), abs=1e-5)
    assert "semantic_classes" not in doc["distances"]["k4"]["01"]
    assert set(doc["diagnostic_statistics"]) == {"semantic_classes"}
    assert "semantic_classes" not in doc["statistics"]
    assert "semantic_classes" not in doc["comparison"]["candidates"]["k4"]["closer"]


@needs_model
def test_four_class_statistics_equal_those_of_default_labels(both) -> None:
    doc, _ = both
    syn, k4 = doc["synthetic"]
    assert not SEMANTIC_KEYS & set(k4)
    assert {k: v for k, v in syn.items() if k not in SEMANTIC_KEYS | {"name"}} == \
        {k: v for k, v in k4.items() if k != "name"}
    assert syn["class_fraction"]["car"] > 0
    d_sk, d_k4 = doc["distances"][SK]["01"], doc["distances"]["k4"]["01"]
    assert {k: v for k, v in d_sk.items() if k != "semantic_classes"} == d_k4
    for scan in doc["per_real_scan"]["scans"]:
        assert scan["distances"][SK] == scan["distances"]["k4"]


@needs_model
def test_text_and_page_show_the_classes(both) -> None:
    doc, out = both
    text = realism_text(doc, out)          # what the command prints
    line = next(x for x in text.splitlines() if x.startswith("semantic_classes"))
    assert f"{doc['distances'][SK]['01']['semantic_classes']:.4f}" in line
    assert "—" in line and "diagnostic" in line         # the four-class set has none
    page = (out / "realism.html").read_text()
    assert '<section id="semantic">' in page
    for c in TRAIN_CLASSES[1:]:
        assert f'data-class="{c}"' in page
    assert 'data-class="unlabeled"' in page and 'data-tv="semantic_classes"' in page
    frac = doc["synthetic"][0]["semantic_fraction"]["road"]
    assert f"{frac:.4f}" in page.split('data-class="road"')[1].split("</tr>")[0]
    assert EVIL not in page and "&lt;b&gt;&amp;&quot;x" in page   # the set's name, escaped
    # no set with SemanticKITTI labels: no table
    plain = json.loads(json.dumps(doc))
    for s in (*plain["synthetic"], *plain["real"]):
        for k in SEMANTIC_KEYS:
            s.pop(k, None)
    assert 'id="semantic"' not in render_realism(plain)


@needs_model
def test_sets_without_semantickitti_labels_have_no_table(folders, tmp_path: Path,
                                                         capsys) -> None:
    # a folder without index.json reads as four classes, as an unreadable one does
    for name, index in (("noindex", None), ("badindex", "{not json")):
        folder = tmp_path / name
        shutil.copytree(folders["k4"], folder)
        (folder / "index.json").unlink()
        if index is not None:
            (folder / "index.json").write_text(index)
        doc, text = _realism([str(folder)], tmp_path / f"out-{name}", capsys)
        assert not SEMANTIC_KEYS & set(doc["synthetic"][0])
        assert SEMANTIC_KEYS <= set(doc["real"][0])         # the real sequence has labels
        assert "diagnostic_statistics" not in doc
        assert "semantic_classes" not in doc["distances"][name]["01"]
        assert "semantic_classes" not in text
        page = (tmp_path / f"out-{name}" / "realism.html").read_text()
        assert '<section id="semantic">' in page             # the real column still shows
