"""`falsify bench scan`: scans per second of the composed fast path beside the naive path (a
merged scene re-cast with trimesh), in one run; and what scene size and image-only dims cost.
On a space of real backgrounds it times insertion, beside the same positions on our streets.
`bench_effects` (`falsify bench effects`) times the same samples with their
weather and faults on and off in one process.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.bench.machine import machine
from falsify.checks import MAX_SAMPLES
from falsify.data.real_backgrounds import RealScanner, scanner_for
from falsify.errors import FalsifyError
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import InvalidSample, Scanner, Simulator
from falsify.world.space import EFFECT_DIMS, Categorical, Sample, Space, load_space


def warm(sim: Scanner, samples: list[Sample]) -> None:
    """Build every background's hits and the car BVHs before the clock starts."""
    for bg in sorted({s.background for s in samples}):
        sim.background_hits(bg, sim.ego_pose(bg))
    for s in samples[:4]:
        try:
            sim.scan(s)
        except InvalidSample:   # a real background's collisions: nothing to warm
            continue


def _timed(sim: Scanner, samples: list[Sample]) -> float:
    """Scans per second of a warm scanner over the samples."""
    t0 = time.perf_counter()
    for s in samples:
        sim.scan(s)
    return len(samples) / (time.perf_counter() - t0)


def _scan_worker(args) -> tuple[int, float, float]:
    config, samples, lod = args
    space = load_space(config)
    sim = scanner_for(space, lod=lod)
    warm(sim, samples)
    t0 = time.perf_counter()
    for s in samples:
        sim.scan(s)
    return len(samples), t0, time.perf_counter()


def possible(sim: Scanner, samples: list[Sample]) -> list[Sample]:
    """The samples whose scenes can exist: a car in a real scan's pole, or on a street standing
    for a place in its roadside's hedge, is an invalid sample, not a scan to time."""
    out = []
    for s in samples:
        try:
            sim.placed_cars(s)
        except InvalidSample:
            continue
        out.append(s)
    return out


def naive_insert(space: Space, sample: Sample) -> np.ndarray:
    """The naive path of insertion: read the real scan afresh, stand the car on it, and cast
    every pixel's ray at the posed car mesh with trimesh's exact `intersects_location` (a new
    BVH per sample), re-casting past glass with the fast path's hash-decided passes. Returns
    each pixel's range, the car's where it is nearer than the real point (H x W)."""
    import trimesh

    from falsify.world.materials import PASS_PROB

    scanner = RealScanner(load_sensor(space.sensor), space.real_backgrounds, space.user_cars)
    bg = scanner.background(sample.background)
    meshes, mats = [], []
    for pc in scanner.placed_cars(sample):
        m = scanner.sim.car_mesh(pc.model).copy()
        m.apply_transform(pc.matrix())
        meshes.append(m)
        mats.append(scanner.sim.car_materials(pc.model))
    merged = trimesh.util.concatenate(meshes)
    face_pass = PASS_PROB[np.concatenate(mats)]
    hit = naive_cast(merged, bg.origin.reshape(-1, 3), bg.direction.reshape(-1, 3), face_pass, 0)
    return np.minimum(bg.dist.ravel(), hit).reshape(bg.dist.shape)


def naive_cast(mesh, o: np.ndarray, d: np.ndarray, face_pass: np.ndarray,
               seed: int) -> np.ndarray:
    """Each ray's first surface that does not let it pass (inf where none), with trimesh's
    exact `intersects_location`, re-casting past porous and glass triangles with the fast
    path's hash-decided passes."""
    from falsify.sensor.raycast import STEP, unit_hash

    ranges = np.full(len(d), np.inf)
    todo, start = np.arange(len(d)), np.zeros(len(d))
    for _ in range(16):
        loc, idx, tri = mesh.ray.intersects_location(o[todo] + d[todo] * start[todo, None],
                                                     d[todo], multiple_hits=False)
        ray = todo[idx]
        t = start[ray] + np.linalg.norm(loc - (o[ray] + d[ray] * start[ray, None]), axis=1)
        passed = unit_hash(ray, tri, seed) < face_pass[tri]
        ranges[ray[~passed]] = t[~passed]
        todo = ray[passed]
        start[todo] = t[passed] + STEP
        if len(todo) == 0:
            break
    return ranges


def naive_scan(space: Space, sample: Sample):
    """The naive path: rebuild the merged scene for the sample and cast every ray with trimesh's
    exact `intersects_location` (a new BVH per sample), re-casting past porous and glass
    surfaces with the same hash-decided passes as the fast path."""
    import trimesh

    from falsify.sensor.simulator import porosity_seed
    from falsify.world.materials import PASS_PROB

    sensor = load_sensor(space.sensor)
    sim = Simulator(sensor, space.user_cars, background_source=space.background_source())
    bg = space.street(sample.background)
    meshes = [trimesh.Trimesh(bg.vertices, bg.faces, process=False)]
    mats = [bg.materials()]
    for pc in sim.placed_cars(sample):
        m = sim.car_mesh(pc.model).copy()
        m.apply_transform(pc.matrix())
        meshes.append(m)
        mats.append(sim.car_materials(pc.model))
    merged = trimesh.util.concatenate(meshes)
    face_pass = PASS_PROB[np.concatenate(mats)]
    pose = sim.ego_pose(sample.background)
    rot = pose.rotation(sensor)
    d = sensor.directions.reshape(-1, 3) @ rot.T
    o = np.broadcast_to(sim.ray_starts(pose, rot), d.shape).copy()
    ranges = naive_cast(merged, o, d, face_pass, porosity_seed(sample.background))
    ranges[ranges > sensor.max_range] = 0.0
    return ranges.reshape(sensor.shape)


@dataclass(frozen=True)
class ScanBench:
    """Scans/s of the fast path in 1 and `workers` processes against the naive path."""

    config: str
    sensor: str
    samples: int
    workers: int
    machine: dict
    fast_1: float          # scans/s, 1 process (median of its rounds; real scans: best of 3)
    fast_n: float          # scans/s, `workers` processes (the median of its rounds)
    naive: float           # scans/s, the naive path
    naive_samples: int
    scene_size: dict
    streets_1: float | None = None   # real backgrounds: the same positions on our streets
    rounds_1: tuple[float, ...] = ()   # every round's scans/s, 1 process (real scans: the 3)
    rounds_n: tuple[float, ...] = ()   # every round's scans/s, `workers` processes

    def to_json(self) -> dict:
        w = self.workers
        return {
            "benchmark": "scan", "config": self.config, "sensor": self.sensor,
            "samples": self.samples, "machine": self.machine,
            "fast_scans_per_s_1_process": round(self.fast_1, 1),
            f"fast_scans_per_s_{w}_processes": round(self.fast_n, 1),
            "naive_scans_per_s": round(self.naive, 3),
            "naive_samples": self.naive_samples,
            "speedup_1_process": round(self.fast_1 / self.naive, 1),
            f"speedup_{w}_processes": round(self.fast_n / self.naive, 1),
            "scene_size": self.scene_size,
            "rounds": len(self.rounds_n),
            "fast_scans_per_s_1_process_rounds": [round(v, 1) for v in self.rounds_1],
            f"fast_scans_per_s_{w}_processes_rounds": [round(v, 1) for v in self.rounds_n],
            **({} if self.streets_1 is None else {
                "background": "real scans (insertion)",
                "streets_scans_per_s_1_process": round(self.streets_1, 1),
                "real_to_streets_1_process": round(self.fast_1 / self.streets_1, 3)}),
        }


# Samples the scene-size part times, all on the first sample's street: each of its four scenes
# is built once per street (a 16x street's BVH in about 10 s), then scanned three times.
SIZE_SAMPLES = 150


def bench_scan(config: str | Path, samples: int = 1000, naive_samples: int = 5,
               workers: int = 2, size_samples: int = SIZE_SAMPLES,
               repeats: int = 1) -> ScanBench:
    """Scans/s of the fast path (1 process and `workers` processes, `repeats` interleaved rounds
    of each, the median reported: a shared machine swings by a third between runs) against the
    naive path, plus how flat the per-scan time stays when the background grows and image-only
    dims change (on the first `size_samples` samples on the first sample's street)."""
    if samples <= 0 or samples < workers:
        raise FalsifyError(f"--samples: {samples} must be at least the number of workers")
    if repeats < 1:
        raise FalsifyError(f"--repeats: {repeats} must be at least 1")
    if size_samples < 1:
        raise FalsifyError(f"size_samples: {size_samples} must be at least 1")
    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    sim = scanner_for(space)
    grid = possible(sim, space.grid())
    if not grid:
        raise FalsifyError(f"{config}: no sample of the space can exist (every one collides)")
    picked = [grid[i % len(grid)] for i in range(samples)]
    warm(sim, picked)
    rounds_1, rounds_n = [], []
    for _ in range(repeats):   # interleaved, so a busy spell of the machine hits both alike
        if not space.real_backgrounds:
            rounds_1.append(_timed(sim, picked))
        rounds_n.append(_multi_rate(config, picked, workers))
    multi = float(np.median(rounds_n))
    single = float(np.median(rounds_1)) if rounds_1 else 0.0
    streets = None
    if space.real_backgrounds:   # 1 process: beside our streets, alternating, best of 3
        paved = dataclasses.replace(
            space, real_backgrounds=(),
            dims={**space.dims, "background": Categorical("background", tuple(range(15)))})
        on_streets = [paved.make({**s.as_dict(), "background": s.background % 15})
                      for s in picked]
        street_sim = scanner_for(paved)
        warm(street_sim, on_streets)
        rates = [(_timed(sim, picked), _timed(street_sim, on_streets)) for _ in range(3)]
        rounds_1 = [r[0] for r in rates]
        single, streets = max(rounds_1), max(r[1] for r in rates)

    naive_path = naive_insert if space.real_backgrounds else naive_scan
    naive_times = []
    for s in picked[:naive_samples]:
        t0 = time.perf_counter()
        naive_path(space, s)
        naive_times.append(time.perf_counter() - t0)
    naive = 1.0 / float(np.mean(naive_times))
    first = [s for s in picked if s.background == picked[0].background]
    size = {} if space.real_backgrounds else scene_size_effect(space, first[:size_samples])
    return ScanBench(str(config), space.sensor, samples, workers, machine(), single, multi,
                     naive, naive_samples, size, streets, tuple(rounds_1), tuple(rounds_n))


def _multi_rate(config: str | Path, picked: list[Sample], workers: int) -> float:
    """Scans/s of `workers` fresh processes sharing the samples, from the first one's clock
    start to the last one's stop (each warms its caches before its clock starts)."""
    chunks = np.array_split(np.arange(len(picked)), workers)
    ctx = mp.get_context("spawn")
    with ctx.Pool(workers) as pool:
        parts = pool.map(_scan_worker, [(str(config), [picked[i] for i in c], 2)
                                        for c in chunks])
    return sum(p[0] for p in parts) / (max(p[2] for p in parts) - min(p[1] for p in parts))


def scene_size_effect(space: Space, samples: list[Sample]) -> dict:
    """Per-scan time with the street as built, with every triangle split in 4 twice (16× the
    triangles), and with 10× the objects far beyond max range, and with image-only dims varied."""

    def warmed(transform) -> tuple[Simulator, int]:
        """A simulator over the transformed streets, every street built and cast before the
        clock, and the streets' mean triangle count. One street's BVH is kept at most: a warm
        scan reads its street's cached hits and casts only the car."""
        tri = {}

        def source(bg_id):
            bg = transform(space.street(bg_id))
            tri[bg_id] = len(bg.faces)
            return bg
        sim = Simulator(load_sensor(space.sensor), space.user_cars, max_bvh=1,
                        background_source=source)
        warm(sim, samples)
        return sim, int(np.mean(list(tri.values())))

    def subdivided(bg):
        v, f = bg.vertices, bg.faces
        cls, inst, mat, sem = bg.face_class, bg.face_instance, bg.materials(), bg.semantics()
        for _ in range(2):
            v, f, idx = _subdivide(v, f)
            cls, inst, mat, sem = cls[idx], inst[idx], mat[idx], sem[idx]
        return dataclasses.replace(bg, vertices=v, faces=f, face_class=cls, face_instance=inst,
                                   face_material=mat, face_semantic=sem)

    def far_objects(bg):
        v, f = [bg.vertices], [bg.faces]
        n = len(bg.vertices)
        for k in range(1, 10):
            v.append(bg.vertices + [1000.0 * k, 0.0, 0.0])
            f.append(bg.faces + n * k)
        return dataclasses.replace(
            bg, vertices=np.concatenate(v), faces=np.concatenate(f).astype(np.int32),
            face_class=np.tile(bg.face_class, 10), face_instance=np.tile(bg.face_instance, 10),
            face_material=np.tile(bg.materials(), 10), face_semantic=np.tile(bg.semantics(), 10))

    # Every variant built and warmed once (a 16x street's BVH takes seconds to build, outside
    # the clock); then best of three passes, interleaved, so a busy moment of the machine does
    # not land on one variant.
    (base, base_tri), (sub, sub_tri), (far, far_tri) = (
        warmed(t) for t in (lambda b: b, subdivided, far_objects))
    image_sim, varied = _image_dims_scans(space, samples)
    runs = [(_timed(base, samples), _timed(sub, samples), _timed(far, samples),
             _timed(image_sim, varied)) for _ in range(3)]
    base_ms, sub_ms, far_ms, image_ms = (1e3 / max(r[k] for r in runs) for k in range(4))
    return {
        "samples": len(samples), "streets": len({s.background for s in samples}),
        "ms_per_scan": round(base_ms, 3), "triangles": base_tri,
        "ms_per_scan_16x_triangles": round(sub_ms, 3), "triangles_16x": sub_tri,
        "ms_per_scan_10x_objects_beyond_range": round(far_ms, 3), "triangles_10x": far_tri,
        "ms_per_scan_image_dims_varied": round(image_ms, 3),
        "ratio_16x_triangles": round(sub_ms / base_ms, 3),
        "ratio_10x_objects": round(far_ms / base_ms, 3),
        "ratio_image_dims": round(image_ms / base_ms, 3),
    }


def _image_dims_scans(space: Space, samples: list[Sample]) -> tuple[Simulator, list[Sample]]:
    """The samples with every one also changing colour, weather and time of day, and a warm
    simulator for them."""
    from falsify.world.space import IMAGE_ONLY, Categorical
    dims = dict(space.dims)
    for name, values in zip(IMAGE_ONLY, (("red", "white", "black"), ("sun", "rain", "fog"),
                                         ("noon", "dusk", "night")), strict=True):
        dims[name] = Categorical(name, values)
    wide = dataclasses.replace(space, dims=dims)
    varied = []
    for i, s in enumerate(samples):
        d = s.as_dict()
        d.update(colour=("red", "white", "black")[i % 3], weather=("sun", "rain", "fog")[i % 3],
                 time_of_day=("noon", "dusk", "night")[(i // 3) % 3])
        varied.append(wide.make(d))
    sim = Simulator(load_sensor(space.sensor), space.user_cars,
                    background_source=space.background_source())
    warm(sim, varied)
    return sim, varied


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every triangle into 4 at its edge midpoints (same surface, 4× the triangles)."""
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    n = len(v)
    m = len(f)
    ab, bc, ca = n + np.arange(m), n + m + np.arange(m), n + 2 * m + np.arange(m)
    v2 = np.concatenate([v, (v[a] + v[b]) / 2, (v[b] + v[c]) / 2, (v[c] + v[a]) / 2])
    f2 = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                         np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)]).astype(np.int32)
    return v2, f2, np.tile(np.arange(m), 4)


# -- weather and faults -----------------------------------------------------------------------
# Every effect at once, for the worst case of `bench_effects`.
ALL_EFFECTS = {"fog": 50.0, "rain": 10.0, "snow": 1.0, "wet_road": 1.0, "beam_loss": 4,
               "crosstalk": 100, "ego_speed": 50.0}


@dataclass(frozen=True)
class EffectsBench:
    """Per-scan time of the same samples with their effect dims and without (clear twins, the
    same generator seeds), and with every effect at once; best of `repeats` interleaved runs."""

    config: str
    samples: int
    with_effects: int      # samples whose effect dims are not all zero
    machine: dict
    ms_clear: float
    ms_effects: float
    ms_all_effects: float

    def to_json(self) -> dict:
        return {
            "benchmark": "scan effects", "config": self.config, "samples": self.samples,
            "samples_with_effects": self.with_effects, "machine": self.machine,
            "ms_per_scan_clear": round(self.ms_clear, 3),
            "ms_per_scan_effects": round(self.ms_effects, 3),
            "ms_per_scan_all_effects": round(self.ms_all_effects, 3),
            "rate_effects_vs_clear": round(self.ms_clear / self.ms_effects, 3),
            "rate_all_effects_vs_clear": round(self.ms_clear / self.ms_all_effects, 3),
        }


def without_effects(sample: Sample) -> Sample:
    """The sample with its effect dims left out: today's clear scan of the same scene."""
    return Sample(tuple(v for v in sample.values if v[0] not in EFFECT_DIMS))


def bench_effects(config: str | Path, samples: int | None = None,
                  repeats: int = 3) -> EffectsBench:
    """Simulator.scan with the samples' weather and faults against their clear twins (and with
    every effect at once), in one warm simulator, each with its run's seed (as a worker)."""
    from falsify.results.samples import sample_seed
    from falsify.sensor.weather import Effects, effects_of

    space = load_space(config)
    sim = Simulator(load_sensor(space.sensor), space.user_cars,
                    background_source=space.background_source())
    grid = possible(sim, space.grid())
    picked = grid if samples is None else [grid[i % len(grid)] for i in range(samples)]
    warm(sim, picked)
    seeds = [sample_seed(space, s) for s in picked]
    clear = [without_effects(s) for s in picked]
    every = Effects(**ALL_EFFECTS)
    for s, seed in zip(picked, seeds, strict=True):   # fog peaks and tables cached, as in a run
        sim.scan(s, rng=np.random.default_rng(seed))

    def per_scan(run) -> float:
        t0 = time.perf_counter()
        for i in range(len(picked)):
            run(i)
        return (time.perf_counter() - t0) / len(picked) * 1e3

    def on(i: int) -> None:
        sim.scan(picked[i], rng=np.random.default_rng(seeds[i]))

    def off(i: int) -> None:
        sim.scan(clear[i], rng=np.random.default_rng(seeds[i]))

    def everything(i: int) -> None:   # as scan() composes the scene, every effect on
        s = picked[i]
        sim.render(s.background, sim.placed_cars(s), sim.ego_pose(s.background),
                   np.random.default_rng(seeds[i]), every, seeds[i])

    runs = [(per_scan(off), per_scan(on), per_scan(everything)) for _ in range(repeats)]
    best = [min(r[k] for r in runs) for k in range(3)]
    return EffectsBench(str(config), len(picked),
                        sum(not effects_of(s).clear for s in picked), machine(), *best)

