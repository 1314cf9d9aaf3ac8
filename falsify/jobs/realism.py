"""How close synthetic scans are to real ones: per-statistic distances, each one scalar where
lower is closer, so "closer on every statistic" can be read off the result.

Statistics of a set (valid points only unless said): the valid fraction of each row, histograms
of range, height (sensor-frame z) and intensity, the fraction of points per class, and the
network's encoder features. Distances: mean absolute difference of the row profiles, the
1-Wasserstein (earth mover's) distance between histograms in their own unit, total variation
between class fractions, and the Fréchet distance between Gaussians fitted to the features (the
range-image analogue of FID).

Features are the bundled SqueezeSeg's fire9 activations (the end of its encoder), read with ONNX
Runtime from the model's graph cut at that tensor (so no torch is needed and the features come
from exactly the network that is scored). The reported Fréchet distance is per position: every
cell of the 64 x 32 fire9 grid (one beam by 16 columns of the input) with at least one valid
input pixel under it is a sample, about 1,900 a scan, so seven real scans give some 13,000
samples of a 512-dimensional Gaussian instead of 112. Its mean and covariance are pooled from
per-scan sums, so no set's cells are held in memory.

Why per position, measured (realism2, 7 real scans, 200-scan synthetic sets, both bundled
networks): the estimator's value between two halves of one distribution (real 4 vs 3 scans, 7
synthetic scans vs the other 193) divided by its synthetic-vs-real value was 0.22 (new network)
and 0.09 (old network) per position, 0.27 and 0.12 with the 16 tile means per scan it replaced;
projecting on the top 8-64 principal components changed neither (the variance sits in a few
components), and an unbiased distance of scan-level means alone was unbiased but three times as
noisy against the signal. The bias that remains comes from scan-to-scan variety (cells of one
scan are not independent), so it shrinks only with more real scans: each synthetic set's
`frechet_floor` gives the same estimator between a random real-set-sized subset of that set and
the rest, the distance two samples of one world already show. The tile estimator
(TILE_ROWS x TILE_COLS means a scan) stays in the result as `frechet_tiles`, outside the
statistics compared. The distance is biased by the sample counts: compare worlds only at the
same scan counts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from falsify.data.scansets import ScanSet
from falsify.errors import FalsifyError
from falsify.results.metrics import CLASSES
from falsify.semantic import TRAIN_CLASSES, kitti4_of_train, train_ids

RANGE_EDGES = np.linspace(0.0, 120.0, 61)       # m, 2 m bins
HEIGHT_EDGES = np.linspace(-4.0, 6.0, 101)      # m (sensor frame z), 0.1 m bins
INTENSITY_EDGES = np.linspace(0.0, 1.0, 51)
HISTOGRAMS = (("range", 4, RANGE_EDGES), ("height", 2, HEIGHT_EDGES),
              ("intensity", 3, INTENSITY_EDGES))   # statistic, scan channel, bins
BOOTSTRAP_SEED = 0
BOOTSTRAP_LEVELS = (5.0, 95.0)   # percentiles of the resampled distances reported
FEATURE_TENSOR = "/fire9/Concat_output_0"
TILE_ROWS, TILE_COLS = 4, 4
CELL_MIN_VALID = 1       # valid input pixels under a fire9 cell for it to be a feature sample
FLOOR_DRAWS = 10         # random subsets behind each synthetic set's frechet_floor
CHUNK = 16
# One scalar distance per statistic, lower is closer: (key, what it is, unit).
STATISTICS = (
    ("row_valid", "per-row valid fraction: mean |difference| over rows", "fraction"),
    ("range", "range histogram: 1-Wasserstein distance", "m"),
    ("height", "height (z) histogram: 1-Wasserstein distance", "m"),
    ("intensity", "intensity histogram: 1-Wasserstein distance", "intensity"),
    ("classes", "per-class point fractions: total variation", "fraction"),
    ("frechet", "Fréchet distance of fire9 encoder features, per position "
     "(every fire9 cell with a valid input pixel)", "feature units²"),
)
# Against each real scan alone: all but the feature distance, whose estimator is biased by the
# sample count and meaningless on one scan.
PER_SCAN_STATISTICS = tuple(k for k, _, _ in STATISTICS if k != "frechet")
# Reported beside the statistics, not compared: the estimator `frechet` replaced.
REFERENCE = (
    ("frechet_tiles", f"Fréchet distance of fire9 features mean-pooled over {TILE_ROWS}x"
     f"{TILE_COLS} tiles a scan (the first estimator)", "feature units²"),
)
# Reported only between sets that both carry SemanticKITTI labels, and never compared.
DIAGNOSTIC = (
    ("semantic_classes", f"per-class point fractions over SemanticKITTI's "
     f"{len(TRAIN_CLASSES) - 1} classes (unlabeled points left out): total variation",
     "fraction"),
)


@dataclass
class ScanFeatures:
    """fire9 features of a batch of B scans: the tile means and, per scan, the moments of its
    valid cells (count, mean, covariance about its own mean), from which any union of scans'
    mean and covariance is pooled exactly (`pooled_moments`)."""

    tiles: np.ndarray           # (B * TILE_ROWS * TILE_COLS, C) float64
    counts: np.ndarray          # (B,) valid cells per scan
    means: np.ndarray           # (B, C) float64
    covs: np.ndarray            # (B, C, C) float32, ddof 1 (zeros for a scan with one cell)

    def __len__(self) -> int:
        return len(self.counts)

    @staticmethod
    def concat(parts: list[ScanFeatures]) -> ScanFeatures:
        return ScanFeatures(*(np.concatenate([getattr(p, k) for p in parts])
                              for k in ("tiles", "counts", "means", "covs")))


def cell_moments(f: np.ndarray, valid: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """(count, mean, covariance) of the (C, h, w) feature grid `f` over the cells where the
    (h, w) mask `valid` holds."""
    cells = f.transpose(1, 2, 0)[valid].astype(np.float64)
    n = len(cells)
    if n == 0:
        return 0, np.zeros(f.shape[0]), np.zeros((f.shape[0],) * 2, np.float32)
    mu = cells.mean(axis=0)
    x = cells - mu
    cov = x.T @ x / (n - 1) if n > 1 else np.zeros((len(mu),) * 2)
    return n, mu, cov.astype(np.float32)


def pooled_moments(feats: ScanFeatures, idx: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean, covariance (ddof 1) and count of all valid cells of the scans `idx` (all if None):
    the parallel-axis sum of each scan's own covariance and its mean's offset."""
    idx = np.arange(len(feats)) if idx is None else np.asarray(idx)
    n = feats.counts[idx].astype(np.float64)
    total = n.sum()
    if total < 2:
        raise ValueError("the Fréchet distance needs at least 2 feature samples per set")
    mu = (n[:, None] * feats.means[idx]).sum(axis=0) / total
    off = feats.means[idx] - mu
    scatter = np.einsum("b,bij->ij", np.maximum(n - 1, 0), feats.covs[idx].astype(np.float64))
    scatter += (off * n[:, None]).T @ off
    return mu, scatter / (total - 1), int(total)


def cell_frechet(a: ScanFeatures, b: ScanFeatures, ia: np.ndarray | None = None,
                 ib: np.ndarray | None = None) -> float:
    """The per-position Fréchet distance between the valid cells of scans `ia` of `a` and
    scans `ib` of `b` (all scans when None)."""
    ma, ca, _ = pooled_moments(a, ia)
    mb, cb, _ = pooled_moments(b, ib)
    return frechet_distance(ma, ca, mb, cb)


def frechet_floor(feats: ScanFeatures, scans: int, draws: int = FLOOR_DRAWS,
                  seed: int = 0) -> dict | None:
    """The per-position Fréchet distance between `scans` random scans of one set and the rest
    of it, over `draws` seeded draws: what sampling alone gives at a real set's scan count.
    None when the set has too few scans to leave two behind."""
    if scans < 1 or len(feats) < scans + 2:
        return None
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(draws):
        p = rng.permutation(len(feats))
        values.append(cell_frechet(feats, feats, p[:scans], p[scans:]))
    return {"scans": scans, "draws": draws, "seed": seed,
            "mean": round(float(np.mean(values)), 6), "max": round(float(np.max(values)), 6)}


class EncoderFeatures:
    """fire9 features of a SqueezeSeg ONNX model: its graph cut at FEATURE_TENSOR (with the
    `onnx` package) and run in ONNX Runtime; per scan its tile means and valid-cell moments."""

    def __init__(self, path: str | Path | None = None, threads: int | None = 2) -> None:
        from falsify.models.runners import BUNDLED_ONNX
        from falsify.models.spec import load_spec, model_hash, spec_path_for

        self.path = Path(path) if path is not None else BUNDLED_ONNX
        spec_path = spec_path_for(self.path)
        if not self.path.is_file():
            raise FalsifyError(f"model file {self.path} not found")
        self.spec = load_spec(spec_path)
        self.model_hash = model_hash(self.path, spec_path)
        try:
            import onnx
            import onnx.shape_inference
            import onnx.utils
        except ImportError:
            raise FalsifyError("falsify realism reads encoder features with the onnx package: "
                               "pip install 'onnx>=1.15'") from None
        from falsify.models.runners import cpu_session

        try:
            graph = onnx.load(str(self.path))
            names = {o for n in graph.graph.node for o in n.output}
            if FEATURE_TENSOR not in names:
                raise FalsifyError(f"model {self.path}: no tensor {FEATURE_TENSOR!r} (realism "
                                   "needs a SqueezeSeg exported by models.export)")
            graph = onnx.shape_inference.infer_shapes(graph)
            cut = onnx.utils.Extractor(graph).extract_model([self.spec.input_name],
                                                            [FEATURE_TENSOR])
        except FalsifyError:
            raise
        except Exception as exc:  # onnx raises its own types
            raise FalsifyError(f"model {self.path}: cannot cut the graph at "
                               f"{FEATURE_TENSOR} ({exc})") from None
        self.session = cpu_session(cut.SerializeToString(), threads)

    def __call__(self, scans: np.ndarray) -> ScanFeatures:
        """(B, H, W, 6) scans -> their ScanFeatures. A fire9 cell is a sample when at least
        CELL_MIN_VALID of the input pixels it stands for (H / h rows by W / w columns) hold a
        return."""
        from falsify.models.runners import check_scans
        from falsify.models.spec import normalise

        a = check_scans(scans, self.spec, self.path)
        x, _, _ = normalise(a, self.spec.channels, self.spec.mean, self.spec.std)
        # one frame per run: 37 ms/frame on the 2-core EPYC against 60 at a batch of 16
        f = np.concatenate([self.session.run([FEATURE_TENSOR],
                                             {self.spec.input_name: x[i:i + 1]})[0]
                            for i in range(len(x))])
        b, c, h, w = f.shape
        if h % TILE_ROWS or w % TILE_COLS:
            raise FalsifyError(f"model {self.path}: fire9 grid {h}x{w} does not split into "
                               f"{TILE_ROWS}x{TILE_COLS} tiles")
        H, W = a.shape[1:3]
        if H % h or W % w:
            raise FalsifyError(f"model {self.path}: fire9 grid {h}x{w} does not divide the "
                               f"input {H}x{W}")
        t = f.reshape(b, c, TILE_ROWS, h // TILE_ROWS, TILE_COLS,
                      w // TILE_COLS).mean(axis=(3, 5), dtype=np.float64)
        valid = (a[..., 4] > 0).reshape(b, h, H // h, w, W // w).sum(axis=(2, 4))
        moments = [cell_moments(f[i], valid[i] >= CELL_MIN_VALID) for i in range(b)]
        return ScanFeatures(t.transpose(0, 2, 3, 1).reshape(-1, c),
                            np.array([m[0] for m in moments], np.int64),
                            np.stack([m[1] for m in moments]),
                            np.stack([m[2] for m in moments]))


@dataclass
class SetStats:
    """Statistics of one set of scans, kept per scan so any resample of them can be scored:
    the valid fraction of each row, histogram counts (HISTOGRAMS), class counts and, for sets
    labelled with SemanticKITTI's classes, counts per train id ("semantic", index 0 unlabeled);
    `groups` tells which real set each scan came from; `features` holds one ScanFeatures a
    batch."""

    name: str
    scans: int = 0
    points: int = 0
    sums: np.ndarray = field(default_factory=lambda: np.zeros(3))   # range, z, intensity
    features: list[ScanFeatures] = field(default_factory=list, repr=False)
    floor: dict | None = None           # frechet_floor, set by compare for synthetic sets
    per_scan: dict[str, list[np.ndarray]] = field(default_factory=dict, repr=False)
    groups: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    sources: list[str] = field(default_factory=list, repr=False)   # file name per scan
    _joined: ScanFeatures | None = field(default=None, repr=False, compare=False)
    _tables: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def add(self, images: np.ndarray, features: ScanFeatures | None,
            sources: list[str] | None = None, semantic: np.ndarray | None = None) -> None:
        """Add (B, H, W, 6) scans and their features (`sources`: the file of each scan;
        `semantic`: their (B, H, W) SemanticKITTI train ids, for a set labelled with them)."""
        valid = images[..., 4] > 0
        if (semantic is not None) != self.has_semantic and self.scans:
            raise ValueError(f"set {self.name}: SemanticKITTI ids for some scans but not all")
        table: dict[str, list[np.ndarray]] = {key: [] for key, _, _ in HISTOGRAMS}
        table["classes"] = []
        if semantic is not None:
            ids = np.clip(np.asarray(semantic).astype(np.int64), 0, len(TRAIN_CLASSES) - 1)
            table["semantic"] = [np.bincount(t[v], minlength=len(TRAIN_CLASSES))
                                 for t, v in zip(ids, valid, strict=True)]
        for im, v in zip(images, valid, strict=True):
            pts = im[v].astype(np.float64)
            for key, channel, edges in HISTOGRAMS:
                table[key].append(_hist(pts[:, channel], edges))
            cls = np.clip(pts[:, 5].astype(np.int64), 0, len(CLASSES) - 1)
            table["classes"].append(np.bincount(cls, minlength=len(CLASSES)))
            self.points += len(pts)
            self.sums += pts[:, [4, 2, 3]].sum(axis=0)
        self.per_scan.setdefault("row_valid", []).append(valid.mean(axis=2).astype(np.float64))
        for key, values in table.items():
            self.per_scan.setdefault(key, []).append(np.stack(values).astype(np.float64))
        self._tables = {}
        self.groups = np.concatenate([self.groups, np.zeros(len(images), np.int64)])
        self.sources += (list(sources) if sources is not None
                         else [f"scan {self.scans + i}" for i in range(len(images))])
        self.scans += len(images)
        if features is not None:
            self.features.append(features)
            self._joined = None

    def merged(self, other: SetStats, name: str) -> SetStats:
        out = SetStats(name)
        out.scans, out.points = self.scans + other.scans, self.points + other.points
        out.sums = self.sums + other.sums
        out.features = [*self.features, *other.features]
        # a table only one of the two has (SemanticKITTI counts) is left out of the union
        out.per_scan = {k: [*self.per_scan[k], *other.per_scan[k]] for k in self.per_scan
                        if k in other.per_scan}
        out.groups = np.concatenate([self.groups, other.groups + self.groups.max(initial=-1) + 1])
        out.sources = [*self.sources, *other.sources]
        return out

    def scan_table(self, key: str, idx: np.ndarray | None = None) -> np.ndarray:
        """(scans, K) per-scan values of one statistic (see `add`), of the scans `idx` if given
        (indices may repeat: a bootstrap draw)."""
        if key not in self._tables:  # joined once per key, then kept until the next add
            self._tables[key] = np.concatenate(self.per_scan[key])
        table = self._tables[key]
        return table if idx is None else table[idx]

    def counts(self, key: str) -> np.ndarray:
        """A histogram's (or the classes') counts over all scans."""
        return self.scan_table(key).sum(axis=0)

    @property
    def has_semantic(self) -> bool:
        """Whether the set counts points per SemanticKITTI train class."""
        return "semantic" in self.per_scan

    @property
    def row_valid(self) -> np.ndarray:
        return self.scan_table("row_valid").mean(axis=0)

    @property
    def all_features(self) -> ScanFeatures:
        """Every scan's features in one ScanFeatures (joined once, then kept)."""
        if self._joined is None:
            self._joined = ScanFeatures.concat(self.features)
        return self._joined

    def as_dict(self) -> dict:
        feats = self.all_features
        _, cov, cells = pooled_moments(feats)
        semantic = {}
        if self.has_semantic:
            counts = self.counts("semantic")
            semantic = {"semantic_fraction": dict(zip(TRAIN_CLASSES[1:], _floats(_norm(counts[1:])),
                                                      strict=True)),
                        "unlabeled_fraction": round(float(_norm(counts)[0]), 6)}
        return {
            "name": self.name, "scans": self.scans, "points": self.points,
            "valid_fraction": float(self.row_valid.mean()),
            "row_valid": _floats(self.row_valid),
            "range_hist": _floats(_norm(self.counts("range"))),
            "height_hist": _floats(_norm(self.counts("height"))),
            "intensity_hist": _floats(_norm(self.counts("intensity"))),
            "class_fraction": dict(zip(CLASSES, _floats(_norm(self.counts("classes"))),
                                       strict=True)),
            "mean_range": float(self.sums[0] / max(self.points, 1)),
            "mean_height": float(self.sums[1] / max(self.points, 1)),
            "mean_intensity": float(self.sums[2] / max(self.points, 1)),
            "feature_samples": cells, "feature_dims": int(feats.means.shape[1]),
            # total variance of the per-position features: Tr of their covariance
            "feature_trace": round(float(np.trace(cov)), 6),
            "tile_samples": len(feats.tiles),
            "frechet_floor": self.floor,
            **semantic,
        }


def frechet_distance(mu1: np.ndarray, cov1: np.ndarray, mu2: np.ndarray,
                     cov2: np.ndarray) -> float:
    """|mu1 - mu2|² + Tr(S1 + S2 - 2 (S1 S2)^½) for two Gaussians.

    Tr (S1 S2)^½ is the sum of the square roots of the eigenvalues of S1^½ S2 S1^½ (symmetric,
    positive semi-definite), which stays real and stable where S1 or S2 is singular."""
    mu1, mu2 = np.asarray(mu1, np.float64), np.asarray(mu2, np.float64)
    cov1, cov2 = np.atleast_2d(cov1).astype(np.float64), np.atleast_2d(cov2).astype(np.float64)
    w, v = np.linalg.eigh((cov1 + cov1.T) / 2)
    root = (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T
    m = root @ cov2 @ root
    cross = np.sqrt(np.clip(np.linalg.eigvalsh((m + m.T) / 2), 0.0, None)).sum()
    d = float(((mu1 - mu2) ** 2).sum() + np.trace(cov1) + np.trace(cov2) - 2.0 * cross)
    return max(d, 0.0)


def frechet_from_samples(a: np.ndarray, b: np.ndarray) -> float:
    """The Fréchet distance between Gaussians fitted to two sample sets (rows are samples).

    When the smaller set has n <= d samples, Tr (S_a S_b)^½ is computed in its n x n sample
    space: the nonzero eigenvalues of S_b^½ S_s S_b^½ are those of X_s S_b X_sᵀ / (n - 1), with
    X_s the centred smaller set. Same value, no d x d square root (112 x 112 instead of
    512 x 512 for seven real scans)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    small, big = (a, b) if len(a) <= len(b) else (b, a)
    n = len(small)
    if n < 2:
        raise ValueError("the Fréchet distance needs at least 2 samples per set")
    if n - 1 >= small.shape[1]:
        return frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0),
                                np.cov(b, rowvar=False))
    xs = small - small.mean(axis=0)
    cov_big = np.cov(big, rowvar=False)
    m = xs @ cov_big @ xs.T / (n - 1)
    cross = np.sqrt(np.clip(np.linalg.eigvalsh((m + m.T) / 2), 0.0, None)).sum()
    d = float(((a.mean(0) - b.mean(0)) ** 2).sum() + (xs ** 2).sum() / (n - 1)
              + np.trace(cov_big) - 2.0 * cross)
    return max(d, 0.0)


def wasserstein_hist(a: np.ndarray, b: np.ndarray, edges: np.ndarray) -> float:
    """1-Wasserstein distance between two histograms on the same bins (in the bins' unit)."""
    ca, cb = np.cumsum(_norm(a)), np.cumsum(_norm(b))
    return float((np.abs(ca - cb) * np.diff(edges)).sum())


def profile_distances(syn: SetStats, real: SetStats, i_syn: np.ndarray | None = None,
                      i_real: np.ndarray | None = None) -> dict[str, float]:
    """The PER_SCAN_STATISTICS (all but the feature distance) between the scans `i_syn` of
    `syn` and `i_real` of `real` (all when None; indices may repeat)."""
    out = {"row_valid": float(np.abs(syn.scan_table("row_valid", i_syn).mean(0)
                                     - real.scan_table("row_valid", i_real).mean(0)).mean())}
    for key, _, edges in HISTOGRAMS:
        out[key] = wasserstein_hist(syn.scan_table(key, i_syn).sum(0),
                                    real.scan_table(key, i_real).sum(0), edges)
    a, b = syn.scan_table("classes", i_syn).sum(0), real.scan_table("classes", i_real).sum(0)
    out["classes"] = float(0.5 * np.abs(_norm(a) - _norm(b)).sum())
    return out


def semantic_distance(syn: SetStats, real: SetStats) -> float | None:
    """Total variation between two sets' fractions of labelled points over SemanticKITTI's
    19 classes (DIAGNOSTIC); None unless both sets carry SemanticKITTI labels."""
    if not (syn.has_semantic and real.has_semantic):
        return None
    a, b = syn.counts("semantic")[1:], real.counts("semantic")[1:]
    return float(0.5 * np.abs(_norm(a) - _norm(b)).sum())


def per_real_scan(synthetic: tuple[SetStats, ...], real: SetStats) -> list[dict]:
    """Each synthetic set against each real scan alone, on PER_SCAN_STATISTICS. With a few
    real scans a resample of them is one of few combinations, so a set that is farther from one
    real scan is farther on every draw that scan dominates: this shows which scan that is."""
    return [{"source": real.sources[k], "real_set": int(real.groups[k]),
             "distances": {s.name: {key: round(v, 6) for key, v in
                                    profile_distances(s, real, None, np.array([k])).items()}
                           for s in synthetic}}
            for k in range(real.scans)]


def distances(syn: SetStats, real: SetStats, i_syn: np.ndarray | None = None,
              i_real: np.ndarray | None = None) -> dict[str, float]:
    """One scalar per statistic (STATISTICS), lower is closer, between the scans `i_syn` of
    `syn` and `i_real` of `real` (all when None; indices may repeat: a bootstrap draw); between
    whole sets also the REFERENCE ones."""
    out = profile_distances(syn, real, i_syn, i_real)
    out["frechet"] = cell_frechet(syn.all_features, real.all_features, i_syn, i_real)
    if i_syn is None and i_real is None:
        out["frechet_tiles"] = frechet_from_samples(syn.all_features.tiles,
                                                    real.all_features.tiles)
    return out


def bootstrap(synthetic: tuple[SetStats, ...], real: SetStats, draws: int,
              seed: int = BOOTSTRAP_SEED) -> dict:
    """How far sampling alone moves each distance: `draws` seeded resamples, each drawing every
    synthetic set's scans and the real scans (within each real set, so a pooled set keeps its
    make-up) with replacement. Per synthetic set the BOOTSTRAP_LEVELS percentiles of each
    distance; per later set the share of draws in which it is closer than the first, with both
    measured against the same real draw (a paired comparison)."""
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(real.groups == g) for g in np.unique(real.groups)]
    values = {s.name: {k: [] for k, _, _ in STATISTICS} for s in synthetic}
    for _ in range(draws):
        i_real = np.concatenate([rng.choice(g, len(g)) for g in groups])
        for s in synthetic:
            d = distances(s, real, rng.integers(0, s.scans, s.scans), i_real)
            for k in values[s.name]:
                values[s.name][k].append(d[k])
    lo, hi = BOOTSTRAP_LEVELS
    out = {"draws": draws, "seed": seed, "levels": list(BOOTSTRAP_LEVELS), "real": real.name,
           "intervals": {n: {k: [round(float(np.percentile(v, lo)), 6),
                                 round(float(np.percentile(v, hi)), 6)] for k, v in d.items()}
                         for n, d in values.items()},
           "closer_share": {}}
    if synthetic:
        base = values[synthetic[0].name]
        for s in synthetic[1:]:
            out["closer_share"][s.name] = {
                k: round(float(np.mean(np.less(values[s.name][k], base[k]))), 6) for k in base}
    return out


@dataclass(frozen=True)
class Realism:
    """Synthetic sets against real sets: statistics of each, and distances per pair."""

    model: str
    model_hash: str
    synthetic: tuple[SetStats, ...]
    real: tuple[SetStats, ...]          # each real set, then (if several) all pooled, last
    distances: dict[str, dict[str, dict[str, float]]]   # synthetic name -> real name -> stat
    resampled: dict | None = None       # `bootstrap` against the pooled real scans, if asked
    per_scan: list[dict] = field(default_factory=list)   # `per_real_scan`, pooled real scans
    reported: tuple[SetStats, ...] = ()  # real sets only reported on (the evaluation split):
    #                                      their distances are given, never pooled or compared

    @property
    def pooled_real(self) -> SetStats:
        return self.real[-1]

    @property
    def real_sets(self) -> tuple[SetStats, ...]:
        """The real sets as given (without the pooled one, when there are several)."""
        return self.real[:-1] if len(self.real) > 1 else self.real

    def comparison(self) -> dict | None:
        """With two or more synthetic sets: is each later one closer to the pooled real scans
        than the first on each statistic?"""
        if len(self.synthetic) < 2:
            return None
        base = self.synthetic[0].name
        ref = self.pooled_real.name
        out = {"baseline": base, "real": ref, "candidates": {}}
        for s in self.synthetic[1:]:
            closer = {k: self.distances[s.name][ref][k] < self.distances[base][ref][k]
                      for k, _, _ in STATISTICS}
            # on how many of the real scans, each alone, it is closer than the first
            per_scan = {k: sum(d["distances"][s.name][k] < d["distances"][base][k]
                               for d in self.per_scan) for k in PER_SCAN_STATISTICS}
            out["candidates"][s.name] = {"closer": closer,
                                         "closer_on_every_statistic": all(closer.values()),
                                         "closer_on_real_scans": per_scan,
                                         "real_scans": len(self.per_scan)}
        return out

    def as_dict(self) -> dict:
        return {
            "model": self.model, "model_hash": self.model_hash,
            "feature": {
                "tensor": FEATURE_TENSOR,
                "estimator": "per-position",
                "samples": f"every fire9 cell with >= {CELL_MIN_VALID} valid input pixel(s) "
                           "under it",
                "why": "chosen by measured split bias: the distance between two halves of one "
                       "set over the synthetic-vs-real distance was 0.22 / 0.09 (new / old "
                       "network) per position against 0.27 / 0.12 for tile means; principal "
                       "component projection changed neither",
                "floor": f"frechet_floor: {FLOOR_DRAWS} draws of as many scans as the pooled "
                         "real set against the rest of the same synthetic set",
                "tiles": [TILE_ROWS, TILE_COLS],
                "pooling": "frechet_tiles only: mean over each tile of the fire9 grid"},
            "statistics": {k: {"what": w, "unit": u} for k, w, u in STATISTICS},
            "reference_statistics": {k: {"what": w, "unit": u} for k, w, u in REFERENCE},
            "bins": {"range": _floats(RANGE_EDGES), "height": _floats(HEIGHT_EDGES),
                     "intensity": _floats(INTENSITY_EDGES)},
            **({"diagnostic_statistics": {k: {"what": w, "unit": u} for k, w, u in DIAGNOSTIC}}
               if any(k in d for rs in self.distances.values() for d in rs.values()
                      for k, _, _ in DIAGNOSTIC) else {}),
            "synthetic": [s.as_dict() for s in self.synthetic],
            "real": [s.as_dict() for s in self.real],
            "real_pooled": self.pooled_real.name,
            "reported": [s.as_dict() for s in self.reported],
            # 6 decimals: bytes that do not move with the BLAS's last-bit rounding
            "distances": {s: {r: {k: round(v, 6) for k, v in d.items()} for r, d in rs.items()}
                          for s, rs in self.distances.items()},
            "comparison": self.comparison(),
            **({"bootstrap": self.resampled} if self.resampled is not None else {}),
            "per_real_scan": {"real": self.pooled_real.name,
                              "statistics": list(PER_SCAN_STATISTICS),
                              # `real_set` of each scan indexes these
                              "real_sets": [r.name for r in self.real_sets],
                              "scans": self.per_scan},
        }


def set_stats(name: str, images_or_set, features: EncoderFeatures,
              labels: str = "kitti4") -> SetStats:
    """Statistics of a ScanSet or of a list of .npy paths (read CHUNK at a time). A ScanSet
    with SemanticKITTI ids, or .npy scans whose label channel holds train ids (`labels`
    "semantickitti", as `falsify dataset --labels semantickitti` writes), also gets the
    per-class table; such .npy labels are turned into our four classes for everything else."""
    stats = SetStats(name)
    if isinstance(images_or_set, ScanSet):
        n, sources = len(images_or_set), [Path(src).name for src in images_or_set.sources]
        sem = images_or_set.semantic
        chunks = ((images_or_set.images[i:i + CHUNK],
                   None if sem is None else train_ids(sem[i:i + CHUNK]))
                  for i in range(0, n, CHUNK))
    else:
        paths = list(images_or_set)
        n, sources = len(paths), [p.name for p in paths]
        chunks = (_split_labels(np.stack([_checked(p, features) for p in paths[i:i + CHUNK]]),
                                labels) for i in range(0, n, CHUNK))
    for i, (images, semantic) in zip(range(0, n, CHUNK), chunks, strict=True):
        stats.add(images, features(images), sources[i:i + len(images)], semantic)
    return stats


def _split_labels(images: np.ndarray, labels: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Scans with our four classes in channel 5, and their train ids when the channel held
    SemanticKITTI's (`labels` "semantickitti"; else None and the scans as they are)."""
    if labels != "semantickitti":
        return images, None
    ids = images[..., 5].astype(np.int64)
    images = images.copy()
    images[..., 5] = kitti4_of_train(ids)
    return images, ids


def compare(synthetic: dict[str, list[Path]], real: list[ScanSet],
            features: EncoderFeatures, pooled_name: str = "pooled",
            bootstrap_draws: int = 0, labels: dict[str, str] | None = None,
            reported: list[ScanSet] = ()) -> Realism:
    """Statistics of each synthetic set (name -> .npy paths; `labels`: name -> what their
    label channel holds, "kitti4" when not named) and real set, and the distance of each
    synthetic set to each real set and to all real sets pooled; with `bootstrap_draws`, also
    how much of each distance sampling alone could move (`bootstrap`). Pairs that both carry
    SemanticKITTI labels also get the DIAGNOSTIC distance. `reported` real sets (evaluation
    data) get their distances too, but are neither pooled nor compared with."""
    if not real:
        raise FalsifyError("realism needs at least one real set")
    real_stats = [set_stats(s.name, s, features) for s in real]
    all_real = tuple(real_stats)
    if len(real_stats) > 1:
        pooled = real_stats[0]
        for s in real_stats[1:]:
            pooled = pooled.merged(s, pooled_name)
        all_real = (*real_stats, pooled)
    labels = labels or {}
    syn_stats = tuple(set_stats(name, paths, features, labels.get(name, "kitti4"))
                      for name, paths in synthetic.items())
    for s in syn_stats:
        s.floor = frechet_floor(s.all_features, all_real[-1].scans)
    shown = tuple(set_stats(s.name, s, features) for s in reported)
    dist = {s.name: {r.name: distances(s, r) for r in (*all_real, *shown)} for s in syn_stats}
    for s in syn_stats:
        for r in (*all_real, *shown):
            tv = semantic_distance(s, r)
            if tv is not None:
                dist[s.name][r.name]["semantic_classes"] = tv
    resampled = (bootstrap(syn_stats, all_real[-1], bootstrap_draws) if bootstrap_draws > 0
                 else None)
    return Realism(features.spec.name, features.model_hash, syn_stats, all_real, dist,
                   resampled, per_real_scan(syn_stats, all_real[-1]), shown)


def _checked(path: Path, features: EncoderFeatures) -> np.ndarray:
    """A .npy scan in the network's grid, or FalsifyError naming the file."""
    from falsify.data.range_npy import load_scan_npy

    image = load_scan_npy(path)
    want = (features.spec.height, features.spec.width)
    if image.shape[:2] != want:
        raise FalsifyError(f"{path}: shape {image.shape}, the network's grid is "
                           f"{want[0]} x {want[1]} (use the KITTI front preset's dataset)")
    return image


def _hist(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Counts with out-of-range values clipped into the end bins (so no point is lost)."""
    v = np.clip(values, edges[0], edges[-1])
    return np.histogram(v, bins=edges)[0].astype(np.float64)


def _norm(counts: np.ndarray) -> np.ndarray:
    total = counts.sum()
    return counts / total if total > 0 else np.zeros_like(counts, np.float64)


def _floats(a: np.ndarray) -> list[float]:
    return [round(float(x), 6) for x in a]
