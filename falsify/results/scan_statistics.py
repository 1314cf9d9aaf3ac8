"""Statistics of a set of scans kept per scan (row validity, histograms of range, height and
intensity, class counts, encoder feature moments), and the distances between two sets, each one
scalar where lower is closer, whole or under a seeded bootstrap of their scans."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from falsify.results.distances import (
    frechet_from_samples,
    normalised,
    total_variation,
    wasserstein_hist,
)
from falsify.results.feature_moments import (
    ScanFeatures,
    cell_frechet,
    folded,
    pooled_moments,
)
from falsify.results.metrics import CLASSES
from falsify.semantic import TRAIN_CLASSES

RANGE_EDGES = np.linspace(0.0, 120.0, 61)       # m, 2 m bins
HEIGHT_EDGES = np.linspace(-4.0, 6.0, 101)      # m (sensor frame z), 0.1 m bins
INTENSITY_EDGES = np.linspace(0.0, 1.0, 51)
HISTOGRAMS = (("range", 4, RANGE_EDGES), ("height", 2, HEIGHT_EDGES),
              ("intensity", 3, INTENSITY_EDGES))   # statistic, scan channel, bins
BOOTSTRAP_SEED = 0
BOOTSTRAP_LEVELS = (5.0, 95.0)   # percentiles of the resampled distances reported
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
# Reported only between sets that both carry SemanticKITTI labels, and never compared.
DIAGNOSTIC = (
    ("semantic_classes", f"per-class point fractions over SemanticKITTI's "
     f"{len(TRAIN_CLASSES) - 1} classes (unlabeled points left out): total variation",
     "fraction"),
)


@dataclass
class SetStats:
    """Statistics of one set of scans, kept per scan so any resample of them can be scored:
    the valid fraction of each row, histogram counts (HISTOGRAMS), class counts and, for sets
    labelled with SemanticKITTI's classes, counts per train id ("semantic", index 0 unlabeled);
    `groups` tells which real set each scan came from; `features` holds one ScanFeatures a
    batch, or with `scan_moments` False all of them `folded` into one (a set only compared
    whole). A scan without labels counts no class: its sources are in `unlabelled`."""

    name: str
    scans: int = 0
    points: int = 0
    sums: np.ndarray = field(default_factory=lambda: np.zeros(3))   # range, z, intensity
    features: list[ScanFeatures] = field(default_factory=list, repr=False)
    floor: dict | None = None           # frechet_floor, set by compare for synthetic sets
    per_scan: dict[str, list[np.ndarray]] = field(default_factory=dict, repr=False)
    groups: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    sources: list[str] = field(default_factory=list, repr=False)   # file name per scan
    unlabelled: list[str] = field(default_factory=list)   # sources whose labels were not found
    scan_moments: bool = True   # keep each scan's feature moments (for resampling them)
    _joined: ScanFeatures | None = field(default=None, repr=False, compare=False)
    _tables: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def add(self, images: np.ndarray, features: ScanFeatures | None,
            sources: list[str] | None = None, semantic: np.ndarray | None = None,
            labelled: np.ndarray | None = None) -> None:
        """Add (B, H, W, 6) scans and their features (`sources`: the file of each scan;
        `semantic`: their (B, H, W) SemanticKITTI train ids, for a set labelled with them;
        `labelled`: (B,) False for a scan whose labels were not found, all True if None)."""
        valid = images[..., 4] > 0
        labelled = (np.ones(len(images), bool) if labelled is None
                    else np.asarray(labelled, bool))
        sources = (list(sources) if sources is not None
                   else [f"scan {self.scans + i}" for i in range(len(images))])
        if (semantic is not None) != self.has_semantic and self.scans:
            raise ValueError(f"set {self.name}: SemanticKITTI ids for some scans but not all")
        table: dict[str, list[np.ndarray]] = {key: [] for key, _, _ in HISTOGRAMS}
        table["classes"] = []
        if semantic is not None:
            ids = np.clip(np.asarray(semantic).astype(np.int64), 0, len(TRAIN_CLASSES) - 1)
            table["semantic"] = [np.bincount(t[v], minlength=len(TRAIN_CLASSES)) * known
                                 for t, v, known in zip(ids, valid, labelled, strict=True)]
        for im, v, known in zip(images, valid, labelled, strict=True):
            pts = im[v].astype(np.float64)
            for key, channel, edges in HISTOGRAMS:
                table[key].append(clipped_hist(pts[:, channel], edges))
            cls = np.clip(pts[:, 5].astype(np.int64), 0, len(CLASSES) - 1)
            table["classes"].append(np.bincount(cls, minlength=len(CLASSES)) * known)
            self.points += len(pts)
            self.sums += pts[:, [4, 2, 3]].sum(axis=0)
        self.per_scan.setdefault("row_valid", []).append(valid.mean(axis=2).astype(np.float64))
        for key, values in table.items():
            self.per_scan.setdefault(key, []).append(np.stack(values).astype(np.float64))
        self._tables = {}
        self.groups = np.concatenate([self.groups, np.zeros(len(images), np.int64)])
        self.sources += sources
        self.unlabelled += [src for src, known in zip(sources, labelled, strict=True)
                            if not known]
        self.scans += len(images)
        if features is not None:
            self.features.append(features)
            if not self.scan_moments:
                self.features = [folded(self.features)]
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
        out.unlabelled = [*self.unlabelled, *other.unlabelled]
        out.scan_moments = self.scan_moments and other.scan_moments
        if not out.scan_moments:
            out.features = [folded(out.features)]
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
            self.features = [self._joined]   # one copy, not the batches and their join too
        return self._joined

    def to_json(self) -> dict:
        feats = self.all_features
        _, cov, cells = pooled_moments(feats)
        semantic = {}
        if self.has_semantic:
            counts = self.counts("semantic")
            shares = rounded_floats(normalised(counts[1:]))
            semantic = {"semantic_fraction": dict(zip(TRAIN_CLASSES[1:], shares, strict=True)),
                        "unlabeled_fraction": round(float(normalised(counts)[0]), 6)}
        return {
            "name": self.name, "scans": self.scans, "points": self.points,
            "valid_fraction": float(self.row_valid.mean()),
            "row_valid": rounded_floats(self.row_valid),
            "range_hist": rounded_floats(normalised(self.counts("range"))),
            "height_hist": rounded_floats(normalised(self.counts("height"))),
            "intensity_hist": rounded_floats(normalised(self.counts("intensity"))),
            "class_fraction": dict(zip(CLASSES, rounded_floats(normalised(self.counts("classes"))),
                                       strict=True)),
            "mean_range": float(self.sums[0] / max(self.points, 1)),
            "mean_height": float(self.sums[1] / max(self.points, 1)),
            "mean_intensity": float(self.sums[2] / max(self.points, 1)),
            "feature_samples": cells, "feature_dims": int(feats.means.shape[1]),
            # total variance of the per-position features: Tr of their covariance
            "feature_trace": round(float(np.trace(cov)), 6),
            "tile_samples": len(feats.tiles),
            "frechet_floor": self.floor,
            # scans whose labels were not found: no class counted, all else kept
            "unlabelled": list(self.unlabelled),
            **semantic,
        }

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
    # NaN where either side holds unlabelled scans only: no class fraction to compare
    out["classes"] = total_variation(a, b) if a.sum() > 0 and b.sum() > 0 else math.nan
    return out


def semantic_distance(syn: SetStats, real: SetStats) -> float | None:
    """Total variation between two sets' fractions of labelled points over SemanticKITTI's
    19 classes (DIAGNOSTIC); None unless both sets carry SemanticKITTI labels."""
    if not (syn.has_semantic and real.has_semantic):
        return None
    a, b = syn.counts("semantic")[1:], real.counts("semantic")[1:]
    return total_variation(a, b)


def per_real_scan(synthetic: tuple[SetStats, ...], real: SetStats) -> list[dict]:
    """Each synthetic set against each real scan alone, on PER_SCAN_STATISTICS. With a few
    real scans a resample of them is one of few combinations, so a set that is farther from one
    real scan is farther on every draw that scan dominates: this shows which scan that is."""
    return [{"source": real.sources[k], "real_set": int(real.groups[k]),
             "distances": {s.name: {key: round(v, 6) if math.isfinite(v) else None
                                    for key, v in
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
    if len(real.all_features) != real.scans:
        raise ValueError(f"set {real.name}: its feature moments were folded; resampling "
                         "needs them per scan (SetStats.scan_moments)")
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(real.groups == g) for g in np.unique(real.groups)]
    values = {s.name: {k: [] for k, _, _ in STATISTICS} for s in synthetic}
    undefined = {s.name: 0 for s in synthetic}
    for _ in range(draws):
        i_real = np.concatenate([rng.choice(g, len(g)) for g in groups])
        real_ok = _cells(real, i_real) >= 2
        for s in synthetic:
            i_syn = rng.integers(0, s.scans, s.scans)
            if real_ok and _cells(s, i_syn) >= 2:
                d = distances(s, real, i_syn, i_real)
            else:   # a draw of blank scans only: no Fréchet distance, no distance at all
                d = dict.fromkeys(values[s.name], math.nan)
                undefined[s.name] += 1
            for k in values[s.name]:
                values[s.name][k].append(d[k])
    out = {"draws": draws, "seed": seed, "levels": list(BOOTSTRAP_LEVELS), "real": real.name,
           "undefined_draws": undefined,
           "intervals": {n: {k: _interval(v) for k, v in d.items()} for n, d in values.items()},
           "closer_share": {}}
    if synthetic:
        base = values[synthetic[0].name]
        for s in synthetic[1:]:
            out["closer_share"][s.name] = {k: _share_closer(values[s.name][k], base[k])
                                           for k in base}
    return out


def _cells(stats: SetStats, idx: np.ndarray) -> int:
    """Valid feature cells in the scans `idx` of a set (with repeats)."""
    return int(stats.all_features.counts[idx].sum())


def _interval(values: list[float]) -> list[float] | None:
    """The BOOTSTRAP_LEVELS percentiles of the defined draws; None when no draw is defined."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return None
    lo, hi = BOOTSTRAP_LEVELS
    return [round(float(np.percentile(v, lo)), 6), round(float(np.percentile(v, hi)), 6)]


def _share_closer(values: list[float], base: list[float]) -> float | None:
    """The share of draws, defined for both sets, in which `values` is below `base`."""
    a, b = np.asarray(values, np.float64), np.asarray(base, np.float64)
    both = np.isfinite(a) & np.isfinite(b)
    return round(float(np.mean(a[both] < b[both])), 6) if both.any() else None


def clipped_hist(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Counts with out-of-range values clipped into the end bins (so no point is lost)."""
    v = np.clip(values, edges[0], edges[-1])
    return np.histogram(v, bins=edges)[0].astype(np.float64)

def rounded_floats(a: np.ndarray) -> list[float]:
    """Values as JSON floats rounded to 6 decimals."""
    return [round(float(x), 6) for x in a]
