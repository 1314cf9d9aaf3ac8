"""`falsify realism` reads real sets CHUNK scans at a time and, unless it resamples them, folds
each scan's feature moments (1 MB) into the set's as they come, so a sequence of thousands fits
in memory; the statistics are the whole set's. A real scan without labels is named and counts
in every statistic but the classes'."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

import falsify.jobs.realism as realism_job
import falsify.results.feature_moments as feature_moments
from falsify.cli import main
from falsify.data.scansets import load_sets, plan_sets
from falsify.jobs.realism import EncoderFeatures, set_stats
from falsify.results.feature_moments import ScanFeatures, folded, pooled_moments
from falsify.results.scan_statistics import distances
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import PlacedCar, Simulator
from tests.conftest import MINI

SENSOR = "kitti-hdl64e-front"
needs_mini = pytest.mark.skipif(not (MINI / "sequences" / "05").is_dir(),
                                reason=f"no SemanticKITTI at {MINI}")


def _features(rng: np.random.Generator, counts: list[int], c: int = 6) -> ScanFeatures:
    """Per-scan moments of random cells, `counts` cells a scan; and the cells themselves."""
    means, covs = [], []
    for n in counts:
        x = rng.normal(rng.normal(size=c), 1.0 + rng.random(), size=(n, c))
        means.append(x.mean(axis=0) if n else np.zeros(c))
        covs.append(np.cov(x.T).astype(np.float32) if n > 1 else np.zeros((c, c), np.float32))
    return ScanFeatures(rng.normal(size=(2 * len(counts), c)), np.array(counts, np.int64),
                        np.stack(means), np.stack(covs))


def test_pooled_moments_a_few_scans_at_a_time_are_those_of_all_cells(monkeypatch) -> None:
    """Covariances widened POOL_CHUNK scans at a time (here 2): the mean and covariance of the
    cells themselves, for all scans and for a resample with repeats."""
    rng = np.random.default_rng(1)
    cells = [rng.normal(rng.normal(size=4), 1.0, size=(n, 4)) for n in (6, 9, 2, 30, 5)]
    feats = ScanFeatures(np.zeros((5, 4)), np.array([len(c) for c in cells]),
                         np.stack([c.mean(axis=0) for c in cells]),
                         np.stack([np.cov(c.T) for c in cells]).astype(np.float32))
    monkeypatch.setattr(feature_moments, "POOL_CHUNK", 2)
    for idx in (None, np.array([3, 0, 3, 4, 1])):
        chosen = np.concatenate([cells[i] for i in (range(5) if idx is None else idx)])
        mu, cov, n = pooled_moments(feats, idx)
        assert n == len(chosen)
        np.testing.assert_allclose(mu, chosen.mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(cov, np.cov(chosen.T), rtol=1e-6)   # float32 per scan


def test_folded_moments_pool_as_the_scans_do() -> None:
    rng = np.random.default_rng(0)
    parts = [_features(rng, [5, 0, 1, 40]), _features(rng, [3, 17])]   # a blank and a 1-cell scan
    want = pooled_moments(ScanFeatures.concat(parts))
    once = folded(parts)
    step = folded([folded(parts[:1]), parts[1]])   # as SetStats.add folds a batch at a time
    for got in (once, step):
        assert len(got) == 1 and got.counts[0] == 66 and len(got.tiles) == 12
        mu, cov, n = pooled_moments(got)
        assert n == want[2]
        np.testing.assert_allclose(mu, want[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cov, want[1], rtol=1e-9, atol=1e-12)
    blank = folded([_features(rng, [0, 0])])
    assert blank.counts.tolist() == [0] and not blank.means.any() and not blank.covs.any()
    single = folded([_features(rng, [0, 1])])
    assert single.counts.tolist() == [1] and not single.covs.any()


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> tuple[Path, Path]:
    """Two folders of three rendered scans each."""
    root = tmp_path_factory.mktemp("parts-syn")
    sim = Simulator(load_sensor(SENSOR))
    out = []
    for k, name in enumerate(("old", "new")):
        (root / name).mkdir()
        for j in range(3):
            car = PlacedCar("sedan", 7.0 + 3 * j + k, -1.0 + j, 30.0 * j, 1)
            np.save(root / name / f"{j:06d}.npy", sim.render(9300 + 10 * k + j, [car]).image)
        out.append(root / name)
    return out[0], out[1]


def _sequence(root: Path, seq: str, labelled: int | None = None) -> Path:
    """A SemanticKITTI sequence folder of links to the fit split's sequence `seq`, with the
    labels of only its first `labelled` scans (all when None)."""
    src = MINI / "sequences" / seq
    bins = sorted((src / "velodyne").glob("*.bin"))
    (root / "velodyne").mkdir(parents=True)
    (root / "labels").mkdir()
    for k, b in enumerate(bins):
        os.symlink(b, root / "velodyne" / b.name)
        if labelled is None or k < labelled:
            os.symlink(src / "labels" / f"{b.stem}.label", root / "labels" / f"{b.stem}.label")
    return root


@needs_mini
def test_a_set_read_in_parts_has_the_whole_sets_statistics(monkeypatch, tmp_path) -> None:
    sensor = load_sensor(SENSOR)
    seq = _sequence(tmp_path / "05", "05", labelled=2)   # three scans, the last one unlabelled
    (plan,) = plan_sets([str(seq)])
    (whole,) = load_sets([str(seq)], sensor)
    reads = []
    real_read = realism_job.read_part
    monkeypatch.setattr(realism_job, "CHUNK", 2)
    monkeypatch.setattr(realism_job, "read_part", lambda p, files, s: (
        reads.append(len(files)), real_read(p, files, s))[1])
    features = EncoderFeatures()
    a = set_stats("05", whole, features)
    b = set_stats("05", plan, features, sensor=sensor)
    assert reads == [2, 1]
    assert json.dumps(a.to_json()) == json.dumps(b.to_json())
    for key in a.per_scan:
        assert np.array_equal(a.scan_table(key), b.scan_table(key)), key
    assert b.unlabelled == ["000009.bin"] and b.to_json()["unlabelled"] == ["000009.bin"]
    assert b.scan_table("classes")[2].sum() == 0 < b.scan_table("classes")[:2].sum(axis=1).min()
    assert b.scan_table("semantic")[2].sum() == 0

    # folded as read: one row of moments, the same distances to a few decimals' last digit
    c = set_stats("05", plan, features, sensor=sensor, scan_moments=False)
    assert len(c.all_features) == 1 and len(b.all_features) == 3
    syn = set_stats("syn", whole, features)
    near, far = distances(syn, b), distances(syn, c)
    assert near.keys() == far.keys()
    for key in near:
        assert far[key] == pytest.approx(near[key], rel=1e-9, abs=1e-9), key


@needs_mini
def test_a_real_scan_without_labels_is_named_and_counts_no_class(synthetic, tmp_path,
                                                                 capsys) -> None:
    old, new = synthetic
    three = _sequence(tmp_path / "three" / "05", "05", labelled=2)
    two = tmp_path / "two" / "05"
    _sequence(two, "05")
    (two / "velodyne" / "000009.bin").unlink()
    (two / "labels" / "000009.label").unlink()

    def realism(real: Path, out: str, *more: str) -> dict:
        assert main(["realism", str(old), str(new), "--real", str(real), "--out",
                     str(tmp_path / out), "--json", *more]) == 0
        return json.loads(capsys.readouterr().out)

    doc = realism(three, "a", "--bootstrap", "4")
    ref = realism(two, "b")
    got, want = doc["real"][0], ref["real"][0]
    assert got["unlabelled"] == ["000009.bin"] and want["unlabelled"] == []
    assert got["scans"] == 3 and want["scans"] == 2
    # the class fractions are the labelled scans', everything else counts all three
    assert got["class_fraction"] == want["class_fraction"]
    assert got["semantic_fraction"] == want["semantic_fraction"]
    assert got["points"] > want["points"] and got["range_hist"] != want["range_hist"]
    assert doc["distances"]["old"]["05"]["classes"] == ref["distances"]["old"]["05"]["classes"]
    rows = {r["source"]: r["distances"] for r in doc["per_real_scan"]["scans"]}
    assert rows["000009.bin"]["old"]["classes"] is None
    assert rows["000009.bin"]["old"]["range"] is not None
    assert all(rows[s]["new"]["classes"] is not None for s in ("000000.bin", "000005.bin"))
    on = doc["comparison"]["candidates"]["new"]["closer_on_real_scans"]
    assert on["classes"] <= 2 and doc["bootstrap"]["intervals"]["new"]["classes"] is not None
    page = (tmp_path / "a" / "realism.html").read_text()
    assert "000009.bin" in page and "Scans without labels" in page

    assert main(["realism", str(old), "--real", str(three), "--out", str(tmp_path / "c")]) == 0
    assert ("05: 1 of 3 scans without labels, left out of the class statistics (000009.bin)"
            in capsys.readouterr().out)


@needs_mini
def test_a_real_set_without_any_labels_is_refused(synthetic, tmp_path, capsys) -> None:
    seq = _sequence(tmp_path / "07", "07", labelled=0)
    out = tmp_path / "out"
    assert main(["realism", str(synthetic[0]), "--real", str(seq), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "set 07: none of its 3 scans has labels" in err and "000000.bin" in err
    assert not (out / "realism.json").exists()


def test_a_real_scan_of_another_shape_in_a_later_part_is_named(synthetic, tmp_path, monkeypatch,
                                                               capsys) -> None:
    real = tmp_path / "real"
    real.mkdir()
    scans = [np.load(p) for p in sorted(synthetic[0].glob("*.npy"))]
    for k, image in enumerate(scans):
        np.save(real / f"{k:06d}.npy", image)
    np.save(real / "000003.npy", np.concatenate([scans[0], scans[0]], axis=1))   # 64 x 1024
    monkeypatch.setattr(realism_job, "CHUNK", 3)   # alone in the second part
    out = tmp_path / "out"
    assert main(["realism", str(synthetic[0]), "--real", str(real), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "set real: 000003.npy: shape (64, 1024, 6), the network's grid is 64 x 512" in err
    assert not (out / "realism.json").exists()
