"""`falsify realism`: the Fréchet distance against closed forms, histogram distances, the JSON's
fields and determinism, bad inputs, and the page in headless Chromium."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import sqrtm

from falsify.cli import main
from falsify.jobs.realism import REFERENCE
from falsify.reports.realism_page import render_realism
from falsify.results.distances import frechet_distance, frechet_from_samples, wasserstein_hist
from falsify.results.feature_moments import (
    ScanFeatures,
    cell_frechet,
    cell_moments,
    frechet_floor,
    pooled_moments,
)
from falsify.results.scan_statistics import (
    STATISTICS,
    SetStats,
    bootstrap,
    distances,
    per_real_scan,
    profile_distances,
)
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import PlacedCar, Simulator
from tests.conftest import EVALUATION_SEQUENCES, FIT_SEQUENCES, ROOT, assert_offline

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
EVIL = '<b>&"x'


# -- distances ----------------------------------------------------------------------------------
def test_frechet_closed_forms() -> None:
    # 1D: (m1 - m2)² + (s1 - s2)²
    assert frechet_distance([1.0], [[4.0]], [3.0], [[9.0]]) == pytest.approx(4.0 + 1.0)
    # commuting (diagonal) covariances: |mu1 - mu2|² + sum (sqrt a - sqrt b)²
    a, b = np.array([1.0, 4.0, 0.25]), np.array([9.0, 1.0, 0.25])
    assert frechet_distance(np.zeros(3), np.diag(a), np.ones(3), np.diag(b)) == pytest.approx(
        3.0 + ((np.sqrt(a) - np.sqrt(b)) ** 2).sum())
    # general covariances: the textbook formula with scipy's matrix square root
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
    c1, c2 = x @ x.T + 0.1 * np.eye(6), y @ y.T + 0.1 * np.eye(6)
    m1, m2 = rng.normal(size=6), rng.normal(size=6)
    ref = ((m1 - m2) ** 2).sum() + np.trace(c1 + c2 - 2 * np.real(sqrtm(c1 @ c2)))
    assert frechet_distance(m1, c1, m2, c2) == pytest.approx(ref, rel=1e-9)
    assert frechet_distance(m1, c1, m1, c1) == pytest.approx(0.0, abs=1e-9)


def test_frechet_at_extremes() -> None:
    # singular covariances (rank 1, zero): real, finite, non-negative, right value
    v = np.array([[1.0], [2.0], [2.0]])
    c1 = v @ v.T                                   # variance 9 along one axis
    assert frechet_distance(np.zeros(3), c1, np.zeros(3), np.zeros((3, 3))) == pytest.approx(9.0)
    assert frechet_distance(np.zeros(3), c1, np.zeros(3), c1) == pytest.approx(0.0, abs=1e-9)
    # a 512-dimensional set with fewer samples than dimensions (rank-deficient, like 7 scans)
    rng = np.random.default_rng(2)
    f = rng.normal(size=(100, 512))
    cov = np.cov(f, rowvar=False)
    d = frechet_distance(f.mean(0), cov, f.mean(0), cov)
    assert np.isfinite(d) and 0.0 <= d < 1e-6
    big = frechet_distance(np.full(4, 1e6), np.eye(4) * 1e8, np.zeros(4), np.eye(4) * 1e-8)
    assert big == pytest.approx(4e12 + 4 * 1e8, rel=1e-9)


def test_frechet_from_samples_approaches_the_closed_form() -> None:
    rng = np.random.default_rng(3)
    m1, m2 = np.array([0.0, 1.0, -1.0]), np.array([0.5, 0.0, 0.0])
    s1, s2 = np.array([1.0, 2.0, 0.5]), np.array([1.5, 1.0, 0.5])
    x = rng.normal(m1, s1, size=(200_000, 3))
    y = rng.normal(m2, s2, size=(200_000, 3))
    est = frechet_distance(x.mean(0), np.cov(x, rowvar=False), y.mean(0), np.cov(y, rowvar=False))
    exact = ((m1 - m2) ** 2).sum() + ((s1 - s2) ** 2).sum()
    assert est == pytest.approx(exact, abs=0.02)


def test_frechet_in_sample_space_equals_the_full_form() -> None:
    # fewer samples than dimensions on one side, as seven real scans give: the n x n form
    # equals the d x d one (which loses ~1e-8 to the square roots of its null eigenvalues)
    rng = np.random.default_rng(4)
    few = rng.normal(size=(40, 64)) * rng.uniform(0.5, 2.0, 64)
    many = rng.normal(0.3, 1.0, size=(500, 64))
    full = frechet_distance(few.mean(0), np.cov(few, rowvar=False), many.mean(0),
                            np.cov(many, rowvar=False))
    assert frechet_from_samples(few, many) == pytest.approx(full, rel=1e-6)
    assert frechet_from_samples(many, few) == pytest.approx(full, rel=1e-6)
    assert frechet_from_samples(few, few) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError):
        frechet_from_samples(few[:1], many)


# -- the per-position estimator -----------------------------------------------------------------
def clustered(rng: np.random.Generator, scans: int, shift: float = 0.0, dims: int = 8,
              cells: int = 300) -> tuple[ScanFeatures, list[np.ndarray]]:
    """Feature grids as a network gives them: each scan has its own offset (scan-to-scan variety,
    so cells of one scan are not independent), its cells scatter around it; some cells masked."""
    grids, masks, per_scan = [], [], []
    for _ in range(scans):
        offset = rng.normal(0.0, 0.5, dims) + shift
        f = rng.normal(size=(dims, 10, cells // 10)) * rng.uniform(0.5, 1.5, (dims, 1, 1))
        f += offset[:, None, None]
        valid = rng.random((10, cells // 10)) > 0.2
        grids.append(f)
        masks.append(valid)
        per_scan.append(f.transpose(1, 2, 0)[valid])
    moments = [cell_moments(f, m) for f, m in zip(grids, masks, strict=True)]
    feats = ScanFeatures(np.zeros((scans, dims)), np.array([m[0] for m in moments]),
                         np.stack([m[1] for m in moments]), np.stack([m[2] for m in moments]))
    return feats, per_scan


def test_pooled_moments_equal_those_of_all_cells() -> None:
    rng = np.random.default_rng(5)
    feats, cells = clustered(rng, 6)
    idx = np.array([0, 2, 3, 5])
    mu, cov, n = pooled_moments(feats, idx)
    ref = np.concatenate([cells[i] for i in idx])
    assert n == len(ref)
    assert np.allclose(mu, ref.mean(axis=0), atol=1e-12)
    assert np.allclose(cov, np.cov(ref, rowvar=False), atol=1e-5)      # covs kept in float32
    # a cell grid with no valid cell adds nothing; the mask picks the cells
    f = rng.normal(size=(3, 2, 2))
    assert cell_moments(f, np.zeros((2, 2), bool))[0] == 0
    n1, m1, _ = cell_moments(f, np.array([[True, False], [False, True]]))
    assert n1 == 2 and np.allclose(m1, (f[:, 0, 0] + f[:, 1, 1]) / 2)


def test_cell_frechet_self_zero_and_grows_with_a_shift() -> None:
    rng = np.random.default_rng(6)
    feats, _ = clustered(rng, 20)
    assert cell_frechet(feats, feats) == pytest.approx(0.0, abs=1e-6)
    shifted = ScanFeatures(feats.tiles, feats.counts, feats.means + 0.5, feats.covs)
    values = [cell_frechet(feats, ScanFeatures(feats.tiles, feats.counts, feats.means + t,
                                               feats.covs)) for t in (0.25, 0.5, 1.0, 2.0)]
    # a pure mean shift of t in each of d dims: exactly d t²
    assert values == pytest.approx([8 * t * t for t in (0.25, 0.5, 1.0, 2.0)], rel=1e-5)
    assert cell_frechet(feats, shifted) == pytest.approx(values[1])
    assert np.all(np.diff(values) > 0)


def test_split_bias_is_small_against_a_real_difference_and_shrinks_with_scans() -> None:
    """Two samples of one distribution sit closer than two distributions do, and the
    estimator's floor (a subset against the rest) falls as the subset grows: deterministic."""
    rng = np.random.default_rng(7)
    same, _ = clustered(rng, 60)
    other, _ = clustered(rng, 60, shift=0.6)
    floor7 = frechet_floor(same, 7, draws=10, seed=0)
    floor30 = frechet_floor(same, 30, draws=10, seed=0)
    assert floor7 == frechet_floor(same, 7, draws=10, seed=0)          # seeded
    assert floor7["scans"] == 7 and floor7["draws"] == 10
    real_gap = cell_frechet(same, other, np.arange(7), None)           # 7 "real" scans
    assert 0 < floor30["mean"] < floor7["mean"] < 0.35 * real_gap
    assert floor7["max"] >= floor7["mean"]
    assert frechet_floor(same, 59) is None                              # nothing left to split
    # per position beats one mean per scan on the same data: the tile-like estimator with
    # one sample a scan is far noisier between halves of one set
    per_scan = ScanFeatures(same.tiles, np.ones(60, np.int64), same.means,
                            np.zeros_like(same.covs))
    p = np.random.default_rng(0).permutation(60)
    coarse = frechet_from_samples(per_scan.means[p[:7]], per_scan.means[p[7:]])
    assert cell_frechet(same, same, p[:7], p[7:]) < coarse


def test_wasserstein_of_histograms() -> None:
    edges = np.linspace(0.0, 10.0, 11)
    a, b = np.zeros(10), np.zeros(10)
    a[2], b[7] = 5.0, 3.0                     # all mass at 2.5 m against all at 7.5 m
    assert wasserstein_hist(a, b, edges) == pytest.approx(5.0)
    assert wasserstein_hist(a, a * 7, edges) == pytest.approx(0.0)


# -- resampling ---------------------------------------------------------------------------------
def _stats(name: str, scans: int, seed: int, valid_share: float = 0.8,
           shift: float = 0.0) -> SetStats:
    """A SetStats of small random scans (8 x 16 pixels) with 4-dimensional features."""
    rng = np.random.default_rng(seed)
    images = np.zeros((scans, 8, 16, 6), np.float32)
    valid = rng.random((scans, 8, 16)) < valid_share
    images[..., 4] = np.where(valid, rng.uniform(2.0, 80.0, valid.shape) + shift, 0.0)
    images[..., 2] = np.where(valid, rng.normal(-1.0 + shift / 10, 0.5, valid.shape), 0.0)
    images[..., 3] = np.where(valid, rng.uniform(0.0, 1.0, valid.shape), 0.0)
    images[..., 5] = np.where(valid, rng.integers(0, 4, valid.shape), 0)
    feats = ScanFeatures(tiles=rng.normal(shift, 1.0, (scans * 16, 4)),
                         counts=np.full(scans, 30), means=rng.normal(shift, 1.0, (scans, 4)),
                         covs=np.tile(np.eye(4, dtype=np.float32), (scans, 1, 1)))
    st = SetStats(name)
    st.add(images, feats)
    return st


def test_resampling_every_scan_once_gives_the_distances() -> None:
    syn, real = _stats("syn", 12, 1), _stats("real", 5, 2)
    d = distances(syn, real)
    r = distances(syn, real, np.arange(12), np.arange(5))
    assert set(d) == set(r) | {"frechet_tiles"}
    for key, _, _ in STATISTICS:
        assert r[key] == pytest.approx(d[key], rel=1e-9, abs=1e-12), key
    # a resample that repeats scans weighs them: one scan twice against the pair
    twice = distances(syn, real, np.array([0, 0]), np.arange(5))
    once = distances(syn, real, np.array([0]), np.arange(5))
    for key in ("row_valid", "range", "height", "intensity", "classes"):
        assert twice[key] == pytest.approx(once[key], rel=1e-9), key


def test_bootstrap_is_seeded_paired_and_keeps_real_sets_apart() -> None:
    real = _stats("a", 4, 2).merged(_stats("b", 3, 3), "pooled")
    assert list(real.groups) == [0, 0, 0, 0, 1, 1, 1]
    near = _stats("near", 20, 4)                       # drawn like the real scans
    far = _stats("far", 20, 5, valid_share=0.5, shift=20.0)
    out = bootstrap((far, near), real, draws=40)
    assert out == bootstrap((far, near), real, draws=40)  # same seed: same numbers
    assert out != bootstrap((far, near), real, draws=40, seed=1)
    for name in ("far", "near"):
        for key, _, _ in STATISTICS:
            lo, hi = out["intervals"][name][key]
            assert 0.0 <= lo <= hi
    share = out["closer_share"]["near"]
    assert set(share) == {k for k, _, _ in STATISTICS}
    # a world drawn like the real one is closer in every draw on what the far one shifted
    for key in ("row_valid", "range", "height", "frechet"):
        assert share[key] == 1.0, key
    assert 0.0 <= share["intensity"] <= 1.0 and "far" not in out["closer_share"]


def test_per_real_scan_finds_the_scan_a_closer_pool_is_farther_from() -> None:
    """Against each real scan alone: the distances equal those to a one-scan set, and a world
    closer to the pool can still be farther from one real scan (what few real scans make a
    bootstrap hinge on)."""
    near_a, near_b = _stats("a", 1, 2), _stats("b", 2, 3, shift=10.0)
    real = near_a.merged(near_b, "pooled")
    assert real.sources == ["scan 0", "scan 0", "scan 1"]
    like_a = _stats("like a", 30, 4)
    like_b = _stats("like b", 30, 5, shift=10.0)
    rows = per_real_scan((like_a, like_b), real)
    assert [r["real_set"] for r in rows] == [0, 1, 1]
    for k, row in enumerate(rows):
        one = _stats("a", 1, 2) if k == 0 else _stats("b", 2, 3, shift=10.0)
        want = profile_distances(like_b, one, None, np.array([k - 1 if k else 0]))
        for key, value in want.items():
            assert row["distances"]["like b"][key] == pytest.approx(value, abs=1e-6), key
    # the pool is two thirds like b, so like b is closer to it, yet farther from scan 0 alone
    pooled = {n: distances(s, real)["range"] for n, s in (("a", like_a), ("b", like_b))}
    assert pooled["b"] < pooled["a"]
    assert rows[0]["distances"]["like b"]["range"] > rows[0]["distances"]["like a"]["range"]
    assert all(r["distances"]["like b"]["range"] < r["distances"]["like a"]["range"]
               for r in rows[1:])
    assert set(rows[0]["distances"]["like a"]) == {k for k, _, _ in STATISTICS} - {"frechet"}


# -- the command ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sets(tmp_path_factory) -> dict[str, Path]:
    """Three tiny 'dataset' folders: two synthetic worlds and a stand-in real set."""
    root = tmp_path_factory.mktemp("realism")
    sim = Simulator(load_sensor("kitti-hdl64e-front"))
    scans = [sim.render(9100 + i, [PlacedCar("sedan", 8.0 + 4 * i, -1.0 + i, 20.0 * i, 1)])
             for i in range(4)]
    folders = {"old": root / "old", "new": root / EVIL, "real": root / "real"}
    for k, folder in enumerate(folders.values()):
        folder.mkdir()
        for j, scan in enumerate(scans[k: k + 2]):
            image = scan.image.copy()
            if folder.name == "real":                 # drop the top rows: a different profile
                image[:6] = 0
            np.save(folder / f"{j:06d}.npy", image)
    return folders


def run(args: list[str], capsys) -> tuple[int, dict | None, str]:
    code = main(args)
    out = capsys.readouterr()
    return code, (json.loads(out.out) if code == 0 and "--json" in args else None), out.err


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
@pytest.mark.slow
def test_realism_json_fields_and_determinism(sets, tmp_path: Path, capsys) -> None:
    args = ["realism", str(sets["old"]), str(sets["new"]), "--real", str(sets["real"]),
            "--bootstrap", "15", "--out", str(tmp_path / "a"), "--json"]
    code, doc, err = run(args, capsys)
    assert code == 0, err
    assert [s["name"] for s in doc["synthetic"]] == ["old", EVIL]
    assert [r["name"] for r in doc["real"]] == ["real"] and doc["real_pooled"] == "real"
    for s in (*doc["synthetic"], *doc["real"]):
        assert s["scans"] == 2 and len(s["row_valid"]) == 64
        assert sum(s["range_hist"]) == pytest.approx(1.0, abs=1e-5)
        assert sum(s["class_fraction"].values()) == pytest.approx(1.0, abs=1e-5)
        assert s["feature_dims"] == 512 and s["tile_samples"] == 2 * 16
    # a sample per fire9 cell (1 row x 16 columns) with a valid pixel under it
    for name, s in (("old", doc["synthetic"][0]), ("real", doc["real"][0])):
        valid = np.stack([np.load(p)[..., 4] > 0 for p in sorted(sets[name].glob("*.npy"))])
        assert s["feature_samples"] == int(valid.reshape(2, 64, 32, 16).any(axis=3).sum())
    assert doc["real"][0]["feature_samples"] < doc["synthetic"][0]["feature_samples"]
    assert doc["feature"]["estimator"] == "per-position"
    assert all(s["frechet_floor"] is None for s in doc["synthetic"])   # 2 scans: no split
    assert doc["real"][0]["row_valid"][:6] == [0.0] * 6
    keys = [k for k, _, _ in STATISTICS]
    assert set(doc["reference_statistics"]) == {k for k, _, _ in REFERENCE}
    assert set(doc["statistics"]) == set(keys)
    for name in ("old", EVIL):
        d = doc["distances"][name]["real"]
        assert set(d) == set(keys) | {"frechet_tiles"} and all(v >= 0 for v in d.values())
        assert d["row_valid"] > 0.05           # six empty rows of 64
    cand = doc["comparison"]["candidates"][EVIL]
    assert set(cand["closer"]) == set(keys)
    assert cand["closer_on_every_statistic"] == all(cand["closer"].values())
    per = doc["per_real_scan"]
    assert per["real"] == "real" and per["real_sets"] == ["real"]
    assert [r["source"] for r in per["scans"]] == ["000000.npy", "000001.npy"]
    assert per["statistics"] == [k for k in keys if k != "frechet"]
    assert cand["real_scans"] == 2
    for key, closer in cand["closer_on_real_scans"].items():
        assert closer == sum(r["distances"][EVIL][key] < r["distances"]["old"][key]
                             for r in per["scans"]), key
    boot = doc["bootstrap"]
    assert boot["draws"] == 15 and boot["real"] == "real"
    assert set(boot["intervals"]) == {"old", EVIL} and set(boot["closer_share"]) == {EVIL}
    assert all(0.0 <= v <= 1.0 for v in boot["closer_share"][EVIL].values())
    # same inputs and model: the same bytes
    args[-2] = str(tmp_path / "b")
    assert run(args, capsys)[0] == 0
    for f in ("realism.json", "realism.html"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_realism_reference_and_evaluation_sets_are_the_users(sets, tmp_path: Path, capsys,
                                                             kitti_dir) -> None:
    """The reference is the --real sequences, pooled; --evaluation adds held-out sequences beside
    it, reported only: never pooled, never compared."""
    mini = kitti_dir / "semantickitti-mini"
    if not (mini / "sequences" / "08").is_dir():
        pytest.skip(f"{mini}: not present")
    code, doc, err = run(["realism", str(sets["old"]), str(sets["new"]), "--real", str(mini),
                          "--sequences", ",".join(FIT_SEQUENCES), "--evaluation", str(mini),
                          "--evaluation-sequences", ",".join(EVALUATION_SEQUENCES),
                          "--out", str(tmp_path), "--json"], capsys)
    assert code == 0, err
    fit = ["01", "02", "04", "05", "07", "09", "10"]
    assert [r["name"] for r in doc["real"]] == [*fit, "pooled"]
    assert [r["scans"] for r in doc["real"]] == [3] * 7 + [21]
    assert [r["name"] for r in doc["reported"]] == ["00", "03", "06", "08"]
    per = doc["per_real_scan"]
    assert per["real_sets"] == fit and len(per["scans"]) == 21
    for name in ("old", EVIL):
        assert set(doc["distances"][name]) == {*fit, "pooled", "00", "03", "06", "08"}
    # the comparison and the per-scan rows use the fit split alone
    assert doc["comparison"]["real"] == "pooled"
    assert all(r["source"].endswith(".bin") and r["real_set"] < 7 for r in per["scans"])
    # real KITTI is about 85 % valid in the front view, our streets more
    assert 0.75 < doc["real"][-1]["valid_fraction"] < 0.92
    page = (tmp_path / "realism.html").read_text()
    assert "Evaluation split (reported only)" in page and "&lt;" in page


def test_realism_bad_inputs_exit_2(sets, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    empty = tmp_path / "empty"
    empty.mkdir()
    bad = tmp_path / "bad"
    bad.mkdir()
    np.save(bad / "000000.npy", np.zeros((3, 3)))
    wide = tmp_path / "wide"
    wide.mkdir()
    np.save(wide / "000007.npy", np.zeros((64, 2048, 6), np.float32))
    cases = [
        ([str(tmp_path / "missing"), "--real", str(sets["real"])], "missing"),
        ([str(empty), "--real", str(sets["real"])], "no .npy scans"),
        ([str(bad), "--real", str(sets["real"])], "000000.npy"),
        ([str(wide), "--real", str(sets["real"])], "000007.npy"),
        ([str(sets["old"]), "--real", str(tmp_path / "nothing.bin")], "nothing.bin"),
        ([str(sets["old"]), "--real", str(sets["real"]), "--scans", "0"], "--scans"),
        ([str(sets["old"]), "--real", str(sets["real"]), "--bootstrap", "-1"], "--bootstrap"),
        ([str(sets["old"]), "--real", str(sets["real"]), "--model", str(tmp_path / "m.onnx")],
         "m.onnx"),
    ]
    for extra, message in cases:
        code, _, err = run(["realism", *extra, "--out", str(out)], capsys)
        assert code == 2 and message in err, (extra, err)
        assert not out.exists()


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_realism_out_a_file_exits_2_before_the_work(sets, tmp_path: Path, capsys) -> None:
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    code, _, err = run(["realism", str(sets["old"]), "--real", str(sets["real"]),
                        "--bootstrap", "0", "--out", str(afile)], capsys)
    assert code == 2 and f"--out {afile}" in err, err
    assert afile.read_text() == "mine\n"


# -- the page ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def page_doc(sets, tmp_path_factory) -> dict:
    if not BUNDLED.exists():
        pytest.skip("bundled model not trained yet")
    out = tmp_path_factory.mktemp("page")
    assert main(["realism", str(sets["old"]), str(sets["new"]), "--real", str(sets["real"]),
                 "--bootstrap", "5", "--out", str(out)]) == 0
    return json.loads((out / "realism.json").read_text())


def test_page_escapes_and_is_self_contained(page_doc) -> None:
    page = render_realism(page_doc)
    assert EVIL not in page and "&lt;b&gt;&amp;&quot;x" in page
    assert "<script" not in page
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", page)
    assert "Content-Security-Policy" in page
    assert 'id="bootstrap"' in page and page.count("of draws") == len(STATISTICS)
    assert page.count('class="chart"') == 4
    assert page.count('class="series"') == 4 * 3          # 2 synthetic + 1 real per chart


def test_page_lists_at_most_fifty_real_scans(page_doc) -> None:
    """A large real set keeps the page readable: 50 rows, and it says the JSON has the rest."""
    doc = json.loads(json.dumps(page_doc))
    one = doc["per_real_scan"]["scans"][0]
    doc["per_real_scan"]["scans"] = [dict(one, source=f"{i:06d}.bin") for i in range(120)]
    page = render_realism(doc)
    assert page.count("000049.bin") == 1 and "000050.bin" not in page
    assert "The first 50 of 120 real scans are shown" in page


def test_page_in_chromium(browser, page_doc, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    path = tmp_path / "realism.html"
    path.write_text(render_realism(page_doc), encoding="utf-8")
    browser.get(path.as_uri())
    charts = browser.find_elements(By.CSS_SELECTOR, "svg.chart")
    assert len(charts) == 4 and all(c.size["width"] > 300 for c in charts)
    lines = browser.find_elements(By.CSS_SELECTOR, "svg.chart polyline.series")
    assert len(lines) == 12
    # the evil set name is shown as text, not markup
    assert EVIL in browser.find_element(By.ID, "distances").text
    cells = browser.find_elements(By.CSS_SELECTOR, "#distances td[data-stat]")
    assert len(cells) == len(STATISTICS) * 2
    # against each real scan: 2 scans x 2 sets x the statistics but the feature distance
    per = browser.find_elements(By.CSS_SELECTOR, "#per-scan td[data-scan-stat]")
    assert len(per) == 2 * 2 * (len(STATISTICS) - 1)
    marks = browser.find_element(By.ID, "per-scan").text
    assert marks.count("✓") + marks.count("✗") == 2 * (len(STATISTICS) - 1)
    assert_offline(browser)
    shot = tmp_path / "page.png"
    assert browser.save_screenshot(str(shot)) and shot.stat().st_size > 20_000
