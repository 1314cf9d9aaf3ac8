"""`falsify bench camera`: the cost of one camera image, beside the naive path in the same run.

Fast path: the Simulator's BVHs (background once, each car model in its own frame), car rays
only in the car's image window, then labels and shading. Naive path (as `bench scan`'s): merge
the background and the posed cars into one mesh per image and cast every pixel ray through
trimesh's `intersects_location` (first hits only, no labels and no shading).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from falsify.bench import _pose_matrix, machine
from falsify.camera import CameraRenderer, camera_preset
from falsify.errors import FalsifyError
from falsify.scene import Simulator, place
from falsify.sensor import SensorPose, load_sensor
from falsify.space import Sample, Space, load_space


def naive_image(space: Space, sample: Sample, renderer: CameraRenderer) -> np.ndarray:
    """First-hit distance per pixel through one merged trimesh scene built for this image."""
    import trimesh

    from falsify.backgrounds import build_background

    sim = renderer.sim
    bg = build_background(sample.background)
    meshes = [trimesh.Trimesh(bg.vertices, bg.faces, process=False)]
    for i, car in enumerate(sample.cars):
        pc = place(car, i + 1)
        m = sim.car_mesh(car.model).copy()
        m.apply_transform(_pose_matrix(pc.rotation(), pc.translation()))
        meshes.append(m)
    merged = trimesh.util.concatenate(meshes)
    origin, rot = renderer.pose_of(SensorPose())
    d = renderer.camera.intrinsics.rays().reshape(-1, 3) @ rot.T
    o = np.tile(origin, (len(d), 1))
    loc, idx, _ = merged.ray.intersects_location(o, d, multiple_hits=False)
    t = np.full(len(d), np.inf)
    t[idx] = np.linalg.norm(loc - o[idx], axis=1)
    return t.reshape(renderer.camera.shape)


def bench_camera(config: str | Path, camera: str = "kitti-centre", samples: int = 10,
                 naive_samples: int = 3) -> dict:
    """ms per image: cold (every pixel cast at a new background), warm (background hits cached,
    as when samples share a background), and the naive path; ratios in the same run."""
    if samples < 1 or naive_samples < 1:
        raise FalsifyError(f"--samples {samples} and --naive-samples {naive_samples} must be "
                           ">= 1")
    space = load_space(config)
    cam = camera_preset(camera)
    grid = space.grid()
    picked = [grid[i * len(grid) // samples] for i in range(min(samples, len(grid)))]
    sim = Simulator(load_sensor(space.sensor), space.user_cars, max_bvh=64)
    renderer = CameraRenderer(sim, cam, max_cached=0)
    for s in picked:  # build every BVH before the clock starts
        sim.background(s.background)
        sim.placed_cars(s)
    renderer.render_sample(picked[0])
    t0 = time.perf_counter()
    for s in picked:
        renderer.render_sample(s)
    cold = (time.perf_counter() - t0) / len(picked)
    warm_renderer = CameraRenderer(sim, cam, max_cached=len(picked))
    for s in picked:
        warm_renderer.render_sample(s)
    t0 = time.perf_counter()
    for s in picked:
        warm_renderer.render_sample(s)
    warm = (time.perf_counter() - t0) / len(picked)
    naive_times = []
    for s in picked[:naive_samples]:
        t0 = time.perf_counter()
        naive_image(space, s, renderer)
        naive_times.append(time.perf_counter() - t0)
    naive = float(np.mean(naive_times))
    h, w = cam.shape
    return {"benchmark": "camera", "config": str(config), "camera": cam.name,
            "image": f"{w}x{h}", "rays_per_image": w * h, "samples": len(picked),
            "naive_samples": len(naive_times), "machine": machine(),
            "ms_per_image_cold": round(cold * 1e3, 1),
            "ms_per_image_warm": round(warm * 1e3, 1),
            "naive_ms_per_image": round(naive * 1e3, 1),
            "speedup_cold": round(naive / cold, 2), "speedup_warm": round(naive / warm, 2)}
