"""Fit a world profile on labelled real scans (`falsify fit-world`), and describe any labelled
scan set the same way, so a world and the real places it is fitted on are compared statistic by
statistic.

Per scan, from SemanticKITTI labels in the front 90 degrees (what the range-image networks see):
- the road plane z = a x + b y + c, least squares on road and parking points within FIT_RANGE,
  refitted once on the points within INLIER_M of the first fit; pitch = atan(a), roll = atan(b),
  the sensor's height above it = |c| / sqrt(1 + a^2 + b^2) (point-to-plane distance), and its
  roughness, the inliers' residual standard deviation;
- cars: SemanticKITTI car and moving-car instances with at least MIN_CAR_POINTS points within
  CAR_RANGE;
- the share of points on vegetation, trunks and terrain, and on cars.

The fit reads only fit data: a held-out scan (falsify.data.holdout: a split manifest, or a
SemanticKITTI root's official split) or a scan without SemanticKITTI labels is refused by name.
`describe` reads any labelled set, for reporting.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from falsify.data.holdout import check_each_once, check_not_held_out
from falsify.data.velodyne import read_bin
from falsify.errors import FalsifyError
from falsify.semantic import RAW_ID, split_label
from falsify.world.places import BANDS_M, GROUPS, Place
from falsify.world.profile import PARKED_KEEP_GRID, WorldProfile
from falsify.world.real_scans import real_scans

FIT_RANGE = 30.0        # m: road points nearer than this fix the plane
CAR_RANGE = 60.0        # m: cars counted within this range
MIN_CAR_POINTS = 20     # an instance with fewer points is not counted as a car
MIN_ROAD_POINTS = 50    # fewer road points in front and the plane is not fitted
INLIER_M = 0.15         # m: points this close to the first plane are refitted
ROAD_IDS = (RAW_ID["road"], RAW_ID["parking"])
CAR_IDS = (RAW_ID["car"], RAW_ID["moving-car"])
GREEN_IDS = (RAW_ID["vegetation"], RAW_ID["trunk"], RAW_ID["terrain"])
QUANTILES = (5, 25, 50, 75, 95)
STAT_KEYS = ("pitch_deg", "roll_deg", "height_m", "roughness_m", "cars_front",
             "green_share", "car_share")
BASE_SCANS = 48          # training scenes of the world itself the base is measured on
BASE_SEED = 11


@dataclass(frozen=True)
class SceneStats:
    """What one scan shows of its place (see the module docstring)."""

    name: str
    pitch_deg: float
    roll_deg: float
    height_m: float
    roughness_m: float
    cars_front: int
    green_share: float
    car_share: float


def ground_plane(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[float, float, float,
                                                                        float]:
    """(a, b, c, residual std) of z = a x + b y + c: least squares, then once more on the points
    within INLIER_M of the first fit (kerb tops and cars' wheels left out)."""
    a_mat = np.stack([x, y, np.ones_like(x)], axis=1).astype(np.float64)
    zz = z.astype(np.float64)
    coef = np.linalg.lstsq(a_mat, zz, rcond=None)[0]
    keep = np.abs(a_mat @ coef - zz) < INLIER_M
    if keep.sum() >= 3:
        coef = np.linalg.lstsq(a_mat[keep], zz[keep], rcond=None)[0]
    res = a_mat[keep] @ coef - zz[keep] if keep.sum() >= 3 else a_mat @ coef - zz
    return float(coef[0]), float(coef[1]), float(coef[2]), float(res.std())


def scene_stats(name: str, points: np.ndarray, labels: np.ndarray) -> SceneStats:
    """The statistics of one scan from its points (N, >=3: x, y, z) and .label values (N,);
    FalsifyError naming the scan when it shows too few road points to fit the plane."""
    sem, inst = split_label(labels)
    x, y, z = (points[:, k].astype(np.float64) for k in range(3))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    front = ok & (x > 0) & (np.abs(y) <= x)
    dist = np.hypot(x, y)
    road = front & np.isin(sem, ROAD_IDS) & (dist < FIT_RANGE)
    if road.sum() < MIN_ROAD_POINTS:
        raise FalsifyError(f"{name}: {int(road.sum())} road points within {FIT_RANGE:g} m in "
                           f"front (need {MIN_ROAD_POINTS}): the road plane cannot be fitted")
    a, b, c, rough = ground_plane(x[road], y[road], z[road])
    car = front & np.isin(sem, CAR_IDS) & (dist < CAR_RANGE)
    ids, counts = np.unique(inst[car], return_counts=True)
    n_front = max(int(front.sum()), 1)
    return SceneStats(
        name=name,
        pitch_deg=math.degrees(math.atan(a)),
        roll_deg=math.degrees(math.atan(b)),
        height_m=abs(c) / math.sqrt(1.0 + a * a + b * b),
        roughness_m=rough,
        cars_front=int((counts >= MIN_CAR_POINTS).sum()),
        green_share=float(np.isin(sem[front], GREEN_IDS).sum() / n_front),
        car_share=float(car.sum() / n_front),
    )


# SemanticKITTI's classes in each of the place's groups (falsify.world.places.GROUPS).
GROUP_IDS: dict[str, tuple[int, ...]] = {
    "road": ("road", "parking", "lane-marking"), "sidewalk": ("sidewalk", "other-ground"),
    "terrain": ("terrain",), "vegetation": ("vegetation", "trunk"),
    "building": ("building", "other-structure"), "fence": ("fence",),
    "pole": ("pole", "traffic-sign"), "car": ("car", "moving-car"),
    "other_vehicle": ("truck", "other-vehicle", "bus", "motorcycle", "bicycle", "moving-truck",
                      "moving-other-vehicle", "moving-bus"),
    "unlabeled": ("unlabeled", "outlier", "other-object"),
}
CLUTTER_GROUPS = ("vegetation", "building", "fence", "pole", "unlabeled")
CLUTTER_X = (5.0, 30.0)   # m ahead: the strip whose clutter's lateral distance a place keeps
FAR_CLUTTER_M = 30.0      # a side with no clutter in the strip
# Where the road ends: what is neither road nor a road user, in 1 m slices EDGE_X ahead.
EDGE_GROUPS = ("sidewalk", "terrain", "vegetation", "building", "fence", "pole", "unlabeled")
EDGE_X = (5.0, 15.0)
FAR_EDGE_M = 25.0         # a slice with no roadside within this on its side
MIN_EDGE_POINTS = 3


def road_edges(x: np.ndarray, y: np.ndarray, roadside: np.ndarray) -> tuple[float, float]:
    """Where the road ends on the left (+y) and right, m from the sensor's line: per 1 m slice
    of EDGE_X, the 10th percentile of |y| of the roadside points (FAR_EDGE_M where a slice has
    none), then the median over the slices, which a bend or a gap in one slice does not move."""
    out = []
    for sign in (1, -1):
        per_slice = []
        for x0 in np.arange(*EDGE_X, 1.0):
            on = roadside & (x >= x0) & (x < x0 + 1.0) & (sign * y > 0) & (np.abs(y) < FAR_EDGE_M)
            per_slice.append(float(np.percentile(np.abs(y[on]), 10))
                             if on.sum() >= MIN_EDGE_POINTS else FAR_EDGE_M)
        out.append(round(float(np.median(per_slice)), 3))
    return out[0], out[1]


def place_of(name: str, points: np.ndarray, labels: np.ndarray,
             stats: SceneStats) -> Place:
    """The place one labelled scan shows (falsify.world.places.Place): its pose from `stats`,
    its front-90-degree points' share per class group in each range band, and the 5th
    percentile of |y| of the clutter in the strip CLUTTER_X ahead on each side, and where its
    road ends on each side (road_edges)."""
    sem = split_label(labels)[0]
    x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    front = ok & (x > 0) & (np.abs(y) <= x)
    dist = np.hypot(x, y)
    ids = {g: np.array([RAW_ID[c] for c in GROUP_IDS[g] if c in RAW_ID]) for g in GROUPS}
    shares = []
    for g in GROUPS:
        member = np.isin(sem, ids[g])
        row = []
        for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:], strict=True):
            band = front & (dist >= lo) & (dist < hi)
            row.append(round(float((member & band).sum() / max(int(band.sum()), 1)), 5))
        shares.append(tuple(row))
    strip = front & (x > CLUTTER_X[0]) & (x < CLUTTER_X[1])
    clutter = strip & np.isin(sem, np.concatenate([ids[g] for g in CLUTTER_GROUPS]))
    near = []
    for sign in (1, -1):
        on = clutter & (sign * y > 0)
        near.append(round(float(np.percentile(np.abs(y[on]), 5)), 3)
                    if on.sum() >= MIN_CAR_POINTS else FAR_CLUTTER_M)
    roadside = ok & np.isin(sem, np.concatenate([ids[g] for g in EDGE_GROUPS]))
    left, right = road_edges(x, y, roadside)
    return Place(name=name, pitch_deg=round(stats.pitch_deg, 4),
                 height_m=round(stats.height_m, 4), shares=tuple(shares),
                 clutter_left_m=near[0], clutter_right_m=near[1], edge_left_m=left,
                 edge_right_m=right)


def silverman_bandwidth(values: np.ndarray) -> float:
    """Silverman's rule-of-thumb bandwidth of a Gaussian kernel density estimate,
    0.9 min(sigma, IQR / 1.34) n^(-1/5) (Silverman, Density Estimation, 1986, eq. 3.31)."""
    v = np.asarray(values, np.float64)
    sigma = v.std(ddof=1) if len(v) > 1 else 0.0
    iqr = np.subtract(*np.percentile(v, [75, 25]))
    spread = min(sigma, iqr / 1.34) if iqr > 0 else sigma
    return float(0.9 * spread * len(v) ** -0.2)


def summarise(stats: list[SceneStats]) -> dict:
    """Per statistic: mean and the QUANTILES over the scans."""
    out: dict = {"scans": len(stats)}
    for key in STAT_KEYS:
        v = np.array([getattr(s, key) for s in stats], np.float64)
        out[key] = {"mean": float(v.mean()),
                    **{f"p{q}": float(np.percentile(v, q)) for q in QUANTILES}}
    return out


def wasserstein_1d(a: np.ndarray, b: np.ndarray) -> float:
    """The 1-Wasserstein distance between two empirical distributions (the area between their
    CDFs), in the values' own unit."""
    a, b = np.sort(np.asarray(a, np.float64)), np.sort(np.asarray(b, np.float64))
    grid = np.sort(np.concatenate([a, b]))
    fa = np.searchsorted(a, grid[:-1], side="right") / len(a)
    fb = np.searchsorted(b, grid[:-1], side="right") / len(b)
    return float(np.sum(np.abs(fa - fb) * np.diff(grid)))


def distances(stats: list[SceneStats], reference: list[SceneStats]) -> dict[str, float]:
    """Per statistic, the 1-Wasserstein distance of `stats`' per-scan values from
    `reference`'s: a diagnostic of what differs, lower is closer."""
    return {k: wasserstein_1d(np.array([getattr(s, k) for s in stats], np.float64),
                              np.array([getattr(s, k) for s in reference], np.float64))
            for k in STAT_KEYS}


def labelled_scans(paths: list[str], sequences: list[str] | None = None):
    """(name, points, labels) of every labelled scan the paths name (real or a `falsify dataset
    --format semantickitti` set); FalsifyError naming a scan without SemanticKITTI labels."""
    for name, path, label, kind in real_scans(paths, sequences):
        if kind != "semantickitti" or label is None:
            raise FalsifyError(f"{path}: no SemanticKITTI .label beside it or in ../labels/ "
                               "(its road and cars cannot be measured)")
        yield name, read_bin(path), np.fromfile(label, np.uint32)


def describe(paths: list[str], sequences: list[str] | None = None) -> list[SceneStats]:
    """The statistics of every labelled scan the paths name (labelled_scans)."""
    return [scene_stats(n, p, lab) for n, p, lab in labelled_scans(paths, sequences)]


def describe_places(paths: list[str], sequences: list[str] | None = None
                    ) -> tuple[list[SceneStats], list[Place]]:
    """The statistics and the place (place_of) of every labelled scan the paths name, each scan
    read once."""
    stats, places = [], []
    for name, points, labels in labelled_scans(paths, sequences):
        stats.append(scene_stats(name, points, labels))
        places.append(place_of(name, points, labels, stats[-1]))
    return stats, places


def check_fit_data(paths: list[str], sequences: list[str] | None,
                   holdout: Sequence[str | Path] = ()) -> None:
    """FalsifyError naming a scan given twice, or the first scan that is held out (never fitted
    to): by the split manifests `holdout`, FALSIFY_HOLDOUT, a splits.toml beside the data or its
    official split."""
    files = [path for _, path, _, _ in real_scans(paths, sequences)]
    check_each_once(files, "fit-world's scans")
    check_not_held_out(files, holdout, "fit-world's scans")


def world_scenes(sensor, scans: int = BASE_SCANS, seed: int = BASE_SEED,
                 profiles: tuple[WorldProfile | None, ...] = (None,),
                 places_out: list[list[Place]] | None = None) -> list[list[SceneStats]]:
    """The statistics of `scans` training scenes of the world, one list per profile (None: the
    world as built), and their places into `places_out` (one list per profile) when given; the
    scenes stand on as many streets (every SCANS_PER_BACKGROUND-th scene), so the world is
    measured across streets, not on a few."""
    from falsify.data.training import (
        SCANS_PER_BACKGROUND,
        TRAIN_BACKGROUND_FIRST,
        TrafficOptions,
        scene_for,
        training_simulator,
    )
    from falsify.data.velodyne import kitti_arrays

    opts = [TrafficOptions(first_background=TRAIN_BACKGROUND_FIRST, backgrounds=625, world=p)
            for p in profiles]
    sims = [training_simulator(sensor, o, max_hits=8) for o in opts]
    out: list[list[SceneStats]] = [[] for _ in profiles]
    for i in range(scans):
        index = i * SCANS_PER_BACKGROUND
        for k, (sim, o) in enumerate(zip(sims, opts, strict=True)):
            bg_id, pose, placed = scene_for(index, seed, sim, o)
            scan = sim.render(bg_id, placed, pose, np.random.default_rng([seed, index, 1]))
            points, labels = kitti_arrays(scan)
            stats = scene_stats(f"world/{index:06d}", points, labels)
            if places_out is not None:
                places_out[k].append(place_of(stats.name, points, labels, stats))
            out[k].append(stats)
    return out


def _spread(values: list[float]) -> float:
    """The sample standard deviation a W1 distance is divided by (1 where the values agree)."""
    sd = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
    return sd if sd > 0 else 1.0


def parked_score(world: list[SceneStats], fit: list[SceneStats]) -> float:
    """How far a world's cars are from the fit scans': the 1-Wasserstein distances of cars in
    view and of the car share, each over the fit scans' standard deviation, summed."""
    d = distances(world, fit)
    return (d["cars_front"] / _spread([s.cars_front for s in fit])
            + d["car_share"] / _spread([s.car_share for s in fit]))


def place_summary(places: list[Place], reference: list[Place] | None = None) -> dict:
    """Per class group and range band: the 10th, 50th and 90th percentile of the places'
    shares (the spread over scans, not just the median) and, against `reference`, the
    1-Wasserstein distance of the per-scan shares."""
    out: dict = {}
    for g in GROUPS:
        for b, (lo, hi) in enumerate(zip(BANDS_M[:-1], BANDS_M[1:], strict=True)):
            v = np.array([p.share(g)[b] for p in places], np.float64)
            row = {f"p{q}": round(float(np.percentile(v, q)), 5) for q in (10, 50, 90)}
            if reference is not None:
                ref = np.array([p.share(g)[b] for p in reference], np.float64)
                row["w1"] = round(wasserstein_1d(v, ref), 5)
            out[f"{g} {lo:g}-{hi:g} m"] = row
    return out


@dataclass(frozen=True)
class WorldFit:
    """`fit-world`'s result: the profile, the fit scans', the world's and the profiled world's
    statistics and places, and the parked-car share tried at each PARKED_KEEP_GRID value."""

    profile: WorldProfile
    fit: list[SceneStats]
    base: list[SceneStats]
    profiled: list[SceneStats]
    parked_tries: list[dict]
    base_places: list[Place]
    profiled_places: list[Place]

    def to_json(self) -> dict:
        return {"profile": self.profile.to_json(),
                "fit": summarise(self.fit), "world": summarise(self.base),
                "profiled_world": summarise(self.profiled),
                "distance_world_to_fit": distances(self.base, self.fit),
                "distance_profiled_to_fit": distances(self.profiled, self.fit),
                "places_fit": place_summary(list(self.profile.places)),
                "places_world": place_summary(self.base_places, list(self.profile.places)),
                "places_profiled_world": place_summary(self.profiled_places,
                                                       list(self.profile.places)),
                "parked_keep_tries": self.parked_tries,
                "fit_scans": [asdict(s) for s in self.fit]}


def fit_world(paths: list[str], sequences: list[str] | None, sensor, name: str,
              holdout: Sequence[str | Path] = (), base_scans: int = BASE_SCANS,
              keep_grid: tuple[float, ...] = PARKED_KEEP_GRID) -> WorldFit:
    """Fit a profile on the fit scans the paths name: each scan's road pitch, sensor height,
    car count and place (place_of: class shares per range band, the roadside's nearness), with
    the world's own median pitch and height as the base the draws add to, and Silverman's
    bandwidth as the draws' jitter (a kernel density estimate of the fit scans); then the share
    of parked cars kept, the `keep_grid` value whose profiled world's cars come nearest the fit
    scans' (parked_score; a tie keeps more), measured on streets standing for the places."""
    check_fit_data(paths, sequences, holdout)
    fit, places = describe_places(paths, sequences)
    base_places: list[list[Place]] = [[]]
    base = world_scenes(sensor, base_scans, places_out=base_places)[0]
    profile = WorldProfile(
        name=name, scans=tuple(s.name for s in fit),
        pitch_deg=tuple(round(s.pitch_deg, 4) for s in fit),
        height_m=tuple(round(s.height_m, 4) for s in fit),
        cars_front=tuple(s.cars_front for s in fit),
        base_pitch_deg=round(float(np.median([s.pitch_deg for s in base])), 4),
        base_height_m=round(float(np.median([s.height_m for s in base])), 4),
        pitch_jitter_deg=round(silverman_bandwidth([s.pitch_deg for s in fit]), 4),
        height_jitter_m=round(silverman_bandwidth([s.height_m for s in fit]), 4),
        places=tuple(places))
    keeps = tuple(sorted(set(keep_grid), reverse=True))
    tried_places: list[list[Place]] = [[] for _ in keeps]
    worlds = world_scenes(sensor, base_scans,
                          profiles=tuple(replace(profile, parked_keep=k) for k in keeps),
                          places_out=tried_places)
    tries = [{"keep": k, "score": round(parked_score(w, fit), 6),
              **{f"w1_{key}": round(d, 6) for key, d in distances(w, fit).items()
                 if key in ("cars_front", "car_share")},
              "cars_front_mean": float(np.mean([s.cars_front for s in w])),
              "car_share_mean": float(np.mean([s.car_share for s in w]))}
             for k, w in zip(keeps, worlds, strict=True)]
    best = min(range(len(keeps)), key=lambda j: (tries[j]["score"], j))
    return WorldFit(replace(profile, parked_keep=keeps[best]), fit, base, worlds[best], tries,
                    base_places[0], tried_places[best])
