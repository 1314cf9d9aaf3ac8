"""`falsify bench camera`: the cost of one camera image, beside the naive path in the same run.

Fast path: the Simulator's BVHs (background once, each car model in its own frame), the street
cast and shaded once per background and look, then only the car's image window cast and only
the pixels a car covers or may shade re-shaded. Naive path (as `bench scan`'s): merge the
background and the posed cars into one mesh per image, cast every pixel ray and every shadow ray
through trimesh's `intersects_id` / `intersects_any`, and shade every pixel with the same
shading code, so both paths make the same image.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from falsify.bench.machine import machine
from falsify.bench.scan import possible
from falsify.errors import FalsifyError
from falsify.sensor.camera import camera_preset
from falsify.sensor.lidar import load_sensor
from falsify.sensor.look import look_of
from falsify.sensor.render import CameraRenderer, Hits
from falsify.sensor.shading import shade
from falsify.sensor.simulator import Simulator
from falsify.world.space import Sample, Space, load_space


def naive_image(space: Space, sample: Sample, renderer: CameraRenderer
                ) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3), owner (H, W): -1 street, k car k, -2 sky) through one merged trimesh
    scene built for this image."""
    import trimesh


    sim = renderer.sim
    bg = space.street(sample.background)
    placed = sim.placed_cars(sample)
    meshes = [trimesh.Trimesh(bg.vertices, bg.faces, process=False)]
    offsets = [len(bg.faces)]
    for car in placed:
        m = sim.car_mesh(car.model).copy()
        m.apply_transform(car.matrix())
        meshes.append(m)
        offsets.append(offsets[-1] + len(m.faces))
    merged = trimesh.util.concatenate(meshes)
    origin, rot = renderer.pose_of(sim.ego_pose(sample.background))
    rays = renderer.camera.intrinsics.rays().reshape(-1, 3)
    d = rays @ rot.T
    o = np.tile(origin, (len(d), 1))
    tri, ray, loc = merged.ray.intersects_id(o, d, multiple_hits=False, return_locations=True)
    n = len(d)
    t = np.full(n, np.inf)
    t[ray] = np.linalg.norm(loc - o[ray], axis=1)
    owner = np.full(n, -1, np.int16)
    prim = np.full(n, -1, np.int32)
    normal = np.zeros((n, 3), np.float32)
    k = np.searchsorted(offsets, tri, side="right") - 1  # -1: the street, k: car k
    owner[ray] = k
    starts = np.array([0, *offsets[:-1]])
    prim[ray] = tri - starts[k + 1]
    world_n = merged.face_normals[tri]
    for j, car in enumerate(placed):  # shading takes car normals in the car's frame
        mine = k == j
        world_n[mine] = world_n[mine] @ car.rotation()
    normal[ray] = world_n

    def shadow_test(points: np.ndarray, sun_d: np.ndarray) -> np.ndarray:
        if not len(points):
            return np.zeros(0, bool)
        return merged.ray.intersects_any(points, np.broadcast_to(sun_d, points.shape))
    look = look_of(sample)
    rgb, _, _ = shade(renderer, bg, placed, [look.colour] * len(placed),
                      Hits(t, owner, prim, normal), d, origin, rot[:, 2], look,
                      renderer.streaks, shadow_test)
    owner[~np.isfinite(t)] = -2
    return rgb.reshape(*renderer.camera.shape, 3), owner.reshape(renderer.camera.shape)


def _seconds_each(renderer: CameraRenderer, samples: list[Sample]) -> float:
    """Mean wall-clock seconds per image of rendering `samples` in order."""
    t0 = time.perf_counter()
    for s in samples:
        renderer.render_sample(s)
    return (time.perf_counter() - t0) / len(samples)


def bench_camera(config: str | Path, camera: str = "kitti-centre", samples: int = 10,
                 naive_samples: int = 3) -> dict:
    """ms per image: cold (every pixel cast and shaded: each image on another background than
    the one before), warm (the street cast and shaded once, then only the car's pixels and its
    shadow: a grid's samples on one background), and the naive path; ratios in the same run."""
    if samples < 1 or naive_samples < 1:
        raise FalsifyError(f"--samples {samples} and --naive-samples {naive_samples} must be "
                           ">= 1")
    space = load_space(config)
    space.require_streets("bench camera")
    cam = camera_preset(camera)
    sim = Simulator(load_sensor(space.sensor), space.user_cars, max_bvh=64,
                    background_source=space.background_source())
    grid = possible(sim, space.grid())
    picked = [grid[i * len(grid) // samples + i] for i in range(min(samples, len(grid) // 2))]
    renderer = CameraRenderer(sim, cam, max_cached=1)  # each image on a new background: cold
    for s in picked:  # build every BVH before the clock starts
        sim.background(s.background)
        sim.placed_cars(s)
    renderer.render_sample(picked[0])
    cold = _seconds_each(renderer, picked)
    warm_renderer = CameraRenderer(sim, cam, max_cached=len(picked))
    for s in picked:
        warm_renderer.render_sample(s)
    warm = _seconds_each(warm_renderer, picked)
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
