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

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from falsify.data.scansets import ScanSet, SetPlan, plan_name, plan_semantic, read_part
from falsify.errors import FalsifyError
from falsify.results.feature_moments import (
    FLOOR_DRAWS,
    ScanFeatures,
    cell_moments,
    frechet_floor,
)
from falsify.results.scan_statistics import (
    DIAGNOSTIC,
    HEIGHT_EDGES,
    INTENSITY_EDGES,
    PER_SCAN_STATISTICS,
    RANGE_EDGES,
    STATISTICS,
    SetStats,
    bootstrap,
    distances,
    per_real_scan,
    rounded_floats,
    semantic_distance,
)
from falsify.semantic import kitti4_of_train, train_ids
from falsify.sensor.lidar import Sensor

FEATURE_TENSOR = "/fire9/Concat_output_0"
TILE_ROWS, TILE_COLS = 4, 4   # tile means a scan: the `frechet_tiles` reference estimator
CELL_MIN_VALID = 1       # valid input pixels under a fire9 cell for it to be a feature sample
CHUNK = 16
# Reported beside the statistics, not compared: the estimator `frechet` replaced.
REFERENCE = (
    ("frechet_tiles", f"Fréchet distance of fire9 features mean-pooled over {TILE_ROWS}x"
     f"{TILE_COLS} tiles a scan (the first estimator)", "feature units²"),
)


class EncoderFeatures:
    """fire9 features of a SqueezeSeg ONNX model: its graph cut at FEATURE_TENSOR (with the
    `onnx` package) and run in ONNX Runtime; per scan its tile means and valid-cell moments."""

    def __init__(self, path: str | Path | None = None, threads: int | None = 2) -> None:
        from falsify.models.runners import BUNDLED_ONNX
        from falsify.models.spec import load_paired_spec, model_hash

        self.path = Path(path) if path is not None else BUNDLED_ONNX
        if not self.path.is_file():
            raise FalsifyError(f"model file {self.path} not found")
        spec_path, self.spec = load_paired_spec(self.path, "onnx")   # the spec's own graph
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
            # (a scan without labels has no class distance, and is not counted on it)
            per_scan = {k: sum(d["distances"][s.name][k] is not None
                               and d["distances"][base][k] is not None
                               and d["distances"][s.name][k] < d["distances"][base][k]
                               for d in self.per_scan) for k in PER_SCAN_STATISTICS}
            out["candidates"][s.name] = {"closer": closer,
                                         "closer_on_every_statistic": all(closer.values()),
                                         "closer_on_real_scans": per_scan,
                                         "real_scans": len(self.per_scan)}
        return out

    def to_json(self) -> dict:
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
            "bins": {"range": rounded_floats(RANGE_EDGES), "height": rounded_floats(HEIGHT_EDGES),
                     "intensity": rounded_floats(INTENSITY_EDGES)},
            **({"diagnostic_statistics": {k: {"what": w, "unit": u} for k, w, u in DIAGNOSTIC}}
               if any(k in d for rs in self.distances.values() for d in rs.values()
                      for k, _, _ in DIAGNOSTIC) else {}),
            "synthetic": [s.to_json() for s in self.synthetic],
            "real": [s.to_json() for s in self.real],
            "real_pooled": self.pooled_real.name,
            "reported": [s.to_json() for s in self.reported],
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


def set_stats(name: str, source: ScanSet | SetPlan | list[Path], features: EncoderFeatures,
              labels: str = "kitti4", sensor: Sensor | None = None,
              scan_moments: bool = True,
              on_scans: Callable[[int], None] | None = None) -> SetStats:
    """Statistics of a ScanSet, a planned set (read CHUNK scans at a time with `sensor`, so a
    sequence of thousands fits in memory) or a list of .npy paths (also CHUNK at a time). A real
    set with SemanticKITTI ids, or .npy scans whose label channel holds train ids (`labels`
    "semantickitti", as `falsify dataset --labels semantickitti` writes), also gets the
    per-class table; such .npy labels are turned into our four classes for everything else. A
    real scan without labels counts no class (`SetStats.unlabelled`). Without `scan_moments`
    the feature moments are folded as they come (a set compared whole, never resampled).
    `on_scans` hears how many more scans are done after each part."""
    stats = SetStats(name, scan_moments=scan_moments)
    if isinstance(source, ScanSet):
        parts = (_source_part(source, i, i + CHUNK) for i in range(0, len(source), CHUNK))
    elif isinstance(source, SetPlan):
        if sensor is None:
            raise ValueError("a planned set is read with a sensor")
        has_semantic = plan_semantic(source)
        parts = (_real_part(read_part(source, list(source.files[i:i + CHUNK]), sensor),
                            has_semantic) for i in range(0, len(source.files), CHUNK))
    else:
        paths = list(source)
        parts = ((*_split_labels(np.stack([_checked(p, features)
                                           for p in paths[i:i + CHUNK]]), labels),
                  [p.name for p in paths[i:i + CHUNK]], None)
                 for i in range(0, len(paths), CHUNK))
    want = (features.spec.height, features.spec.width)
    for images, semantic, sources, labelled in parts:
        if images.shape[1:3] != want:   # a part's scans share one shape: its first names it
            raise FalsifyError(f"set {name}: {sources[0]}: shape {images.shape[1:]}, the "
                               f"network's grid is {want[0]} x {want[1]} (real scans: the "
                               "--sensor that projects them; .npy: the KITTI front preset's)")
        stats.add(images, features(images), sources, semantic, labelled)
        if on_scans is not None:
            on_scans(len(images))
    return stats


def _source_part(scans: ScanSet, start: int, stop: int
                ) -> tuple[np.ndarray, np.ndarray | None, list[str], np.ndarray]:
    """Scans `start:stop` of a real set as `SetStats.add` takes them: images, SemanticKITTI
    train ids (None without them), file names, and which were labelled."""
    sem = scans.semantic
    return (scans.images[start:stop], None if sem is None else train_ids(sem[start:stop]),
            [Path(src).name for src in scans.sources[start:stop]],
            scans.labelled()[start:stop])


def _real_part(scans: ScanSet, semantic: bool
               ) -> tuple[np.ndarray, np.ndarray | None, list[str], np.ndarray]:
    """A part of a planned set as the whole set would hold it: SemanticKITTI ids for every
    scan (zeros for one without labels) when the set has them (`plan_semantic`), else none."""
    if not semantic:
        scans = replace(scans, semantic=None)
    elif scans.semantic is None:   # a part of unlabelled scans only
        scans = replace(scans, semantic=np.zeros(scans.images.shape[:3], np.uint16))
    return _source_part(scans, 0, len(scans))


def _split_labels(images: np.ndarray, labels: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Scans with our four classes in channel 5, and their train ids when the channel held
    SemanticKITTI's (`labels` "semantickitti"; else None and the scans as they are)."""
    if labels != "semantickitti":
        return images, None
    ids = images[..., 5].astype(np.int64)
    images = images.copy()
    images[..., 5] = kitti4_of_train(ids)
    return images, ids


def compare(synthetic: dict[str, list[Path]], real: list[ScanSet | SetPlan],
            features: EncoderFeatures, pooled_name: str = "pooled",
            bootstrap_draws: int = 0, labels: dict[str, str] | None = None,
            reported: list[ScanSet | SetPlan] = (), sensor: Sensor | None = None,
            on_scans: Callable[[int], None] | None = None) -> Realism:
    """Statistics of each synthetic set (name -> .npy paths; `labels`: name -> what their
    label channel holds, "kitti4" when not named) and real set (read or planned: then read
    CHUNK scans at a time with `sensor`), and the distance of each synthetic set to each real
    set and to all real sets pooled; with `bootstrap_draws`, also how much of each distance
    sampling alone could move (`bootstrap`). Pairs that both carry SemanticKITTI labels also
    get the DIAGNOSTIC distance. `reported` real sets (evaluation data) get their distances
    too, but are neither pooled nor compared with. Real scans without labels are named and
    counted in every statistic but the classes'. `on_scans` hears each part read, of every
    set."""
    if not real:
        raise FalsifyError("realism needs at least one real set")
    resampled_real = bootstrap_draws > 0   # else each real scan's 1 MB of moments is folded
    real_stats = [_real_stats(s, features, sensor, resampled_real, on_scans) for s in real]
    all_real = tuple(real_stats)
    if len(real_stats) > 1:
        pooled = real_stats[0]
        for s in real_stats[1:]:
            pooled = pooled.merged(s, pooled_name)
        all_real = (*real_stats, pooled)
    labels = labels or {}
    syn_stats = tuple(set_stats(name, paths, features, labels.get(name, "kitti4"),
                                on_scans=on_scans) for name, paths in synthetic.items())
    shown = tuple(_real_stats(s, features, sensor, False, on_scans) for s in reported)
    for s in (*real_stats, *syn_stats, *shown):
        check_comparable(s)
    for s in syn_stats:
        s.floor = frechet_floor(s.all_features, all_real[-1].scans)
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


def _real_stats(source: ScanSet | SetPlan, features: EncoderFeatures, sensor: Sensor | None,
                scan_moments: bool, on_scans: Callable[[int], None] | None) -> SetStats:
    name = source.name if isinstance(source, ScanSet) else plan_name(source)
    return set_stats(name, source, features, sensor=sensor, scan_moments=scan_moments,
                     on_scans=on_scans)


def check_comparable(stats: SetStats) -> None:
    """FalsifyError naming a set whose scans hold too little to compare: no valid point (scans
    blanked by dense fog, or empty files), fewer than two feature cells for its Fréchet
    distance (it was a ValueError traceback), or no labelled scan for its class fractions."""
    if stats.unlabelled and len(stats.unlabelled) == stats.scans:
        raise FalsifyError(f"set {stats.name}: none of its {stats.scans} scans has labels "
                           "(x.label beside x.bin or in ../labels/); realism compares class "
                           f"fractions, so it needs them (first: {stats.unlabelled[0]})")
    cells = int(stats.all_features.counts.sum())
    if stats.points == 0 or cells < 2:
        what = ("no valid point (range > 0)" if stats.points == 0 else
                f"{cells} feature cell, and its Fréchet distance needs 2")
        raise FalsifyError(f"set {stats.name}: its {stats.scans} scans hold {what}; nothing to "
                           "compare (blank scans, or dense fog throughout?)")


def _checked(path: Path, features: EncoderFeatures) -> np.ndarray:
    """A .npy scan in the network's grid, or FalsifyError naming the file."""
    from falsify.data.range_npy import load_scan_npy

    image = load_scan_npy(path)
    want = (features.spec.height, features.spec.width)
    if image.shape[:2] != want:
        raise FalsifyError(f"{path}: shape {image.shape}, the network's grid is "
                           f"{want[0]} x {want[1]} (use the KITTI front preset's dataset)")
    return image
