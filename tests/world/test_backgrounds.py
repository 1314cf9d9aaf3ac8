"""Procedural street backgrounds: determinism, labels, the free zone, size, and a LiDAR sweep."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from falsify.errors import ConfigError
from falsify.world import streets
from falsify.world.materials import MATERIAL_ID, MATERIALS
from falsify.world.streets import (
    FREE_ZONE,
    MAX_BACKGROUND_ID,
    SENSOR_CLEARANCE,
    Background,
    build_background,
)

IDS = [*range(15), *range(1000, 1005), MAX_BACKGROUND_ID]


@pytest.fixture(scope="module")
def built() -> dict[int, Background]:
    out = {}
    for i in IDS:
        t0 = time.perf_counter()
        out[i] = build_background(i)
        print(f"background {i}: {len(out[i].faces)} triangles in {time.perf_counter() - t0:.3f} s")
    return out


def test_arrays_and_size(built):
    for bg in built.values():
        v, f = bg.vertices, bg.faces
        assert v.dtype == np.float64 and v.ndim == 2 and v.shape[1] == 3
        assert f.dtype == np.int32 and f.shape[1] == 3
        assert bg.face_class.dtype == np.uint8 and bg.face_class.shape == (len(f),)
        assert bg.face_instance.dtype == np.int32 and bg.face_instance.shape == (len(f),)
        assert np.isfinite(v).all() and f.min() >= 0 and f.max() < len(v)
        assert 50_000 <= len(f) <= 400_000
        assert bg.face_material.dtype == np.uint8 and bg.face_material.shape == (len(f),)
        assert bg.face_material.max() < len(MATERIALS)
        tri = v[f]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        assert (area > 0).all()
        assert bg.face_class.max() <= 3
        assert bg.road_half_width >= 9.0
        assert not v.flags.writeable


def test_deterministic_bytes(built):
    for i in (0, 7, 1003):
        streets._build.cache_clear()
        again = build_background(i)
        ref = built[i]
        assert again is not ref
        for name in ("vertices", "faces", "face_class", "face_instance", "face_material"):
            assert getattr(again, name).tobytes() == getattr(ref, name).tobytes()
        assert len(again.obstacles) == len(ref.obstacles)


def test_ids_differ(built):
    digests = {(len(bg.faces), bg.road_half_width, bg.vertices[-10:].tobytes())
               for bg in built.values()}
    assert len(digests) == len(built)


def test_every_label_present(built):
    for bg in built.values():
        assert set(np.unique(bg.face_class).tolist()) == {0, 1, 2, 3}


def test_instances_have_one_class(built):
    for bg in built.values():
        inst, cls = bg.face_instance, bg.face_class
        assert (cls[inst == 0] == 0).all(), "cars, pedestrians and cyclists need instance ids"
        assert inst[inst != 0].min() >= 1000
        ids, first = np.unique(inst, return_inverse=True)
        per_instance = np.zeros(len(ids), dtype=np.int64)
        np.maximum.at(per_instance, first, cls.astype(np.int64))
        lowest = np.full(len(ids), 9, dtype=np.int64)
        np.minimum.at(lowest, first, cls.astype(np.int64))
        assert (lowest == per_instance).all()


def _overlaps_free_zone(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    (x0, x1), (y0, y1) = FREE_ZONE
    return (hi[:, 0] > x0) & (lo[:, 0] < x1) & (hi[:, 1] > y0) & (lo[:, 1] < y1)


def test_free_zone_is_empty_road(built):
    """Only asphalt in the free zone and around the sensor: every vertex of a triangle there
    lies on the terrain's road surface (which has grade and camber, no longer z = 0)."""
    for bg in built.values():
        tri = bg.vertices[bg.faces]
        lo, hi = tri.min(axis=1), tri.max(axis=1)
        c = SENSOR_CLEARANCE
        near = ((hi[:, 0] > -c) & (lo[:, 0] < c) & (hi[:, 1] > -c) & (lo[:, 1] < c))
        inside = _overlaps_free_zone(lo, hi)
        assert inside.any()  # the road itself
        for sel in (inside, near):
            assert (bg.face_class[sel] == 0).all()
            assert (bg.face_material[sel] == MATERIAL_ID["asphalt"]).all()
            pts = tri[sel].reshape(-1, 3)
            ground = bg.terrain.height(pts[:, 0], np.clip(pts[:, 1], -bg.road_half_width + 1e-6,
                                                          bg.road_half_width - 1e-6))
            np.testing.assert_allclose(pts[:, 2], ground, atol=1e-6)
        polys = [o.polygon for o in bg.obstacles]
        plo = np.array([p.min(axis=0) for p in polys])
        phi = np.array([p.max(axis=0) for p in polys])
        assert not _overlaps_free_zone(plo, phi).any()


def test_obstacles_are_ccw_convex(built):
    for o in built[0].obstacles:
        p = o.polygon
        assert p.dtype == np.float64 and p.shape[1] == 2 and len(p) >= 3
        e = np.roll(p, -1, axis=0) - p
        cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
        assert (cross > 0).all(), o.label
    labels = " ".join(o.label for o in built[0].obstacles)
    for word in ("curb", "parked car", "pedestrian", "cyclist"):
        assert word in labels
    everywhere = " ".join(o.label for i in range(15) for o in built[i].obstacles)
    for word in ("building", "tree", "band tree", "guard rail", "fence", "railing", "hedge",
                 "wall", "sign", "pole", "bicycle", "parked box truck", "parked bus"):
        assert word in everywhere, word


@pytest.mark.parametrize("bad", [-1, MAX_BACKGROUND_ID + 1, 1.5, "3", None, True])
def test_bad_ids(bad):
    with pytest.raises(ConfigError, match="999999"):
        build_background(bad)


def test_numpy_integer_id():
    assert build_background(np.int64(3)) is build_background(3)


def _front_fan(bg: Background) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 64×512 front-90° HDL-64E-like sweep from (0, 0, 1.73): hit mask, range, class."""
    el = np.deg2rad(np.linspace(2.0, -24.9, 64))
    az = np.deg2rad(np.linspace(45.0, -45.0, 512))
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    o = np.tile([0.0, 0.0, 1.73], (len(d), 1))
    mesh = trimesh.Trimesh(bg.vertices, bg.faces, process=False)
    loc, ray, tri = RayMeshIntersector(mesh).intersects_location(o, d, multiple_hits=False)
    rng = np.full(len(d), np.inf)
    rng[ray] = np.linalg.norm(loc - o[ray], axis=1)
    cls = np.full(len(d), 255)
    cls[ray] = bg.face_class[tri]
    hit = rng < 120.0
    return hit, rng, cls


def test_lidar_sweep_sees_the_street(built):
    seen = set()
    for i in (0, 1, 2, 3):
        hit, rng, cls = _front_fan(built[i])
        assert hit.mean() > 0.85
        seen |= set(np.unique(cls[hit & (rng < 60.0)]).tolist())
    assert {1, 2, 3} <= seen


def _side_hits(bg: Background, x: float, up: float, deg: tuple[float, float]) -> np.ndarray:
    """|y| where level rays from the centre line at x, `up` metres above the road, fanned
    deg[0]..deg[1] degrees off the road to both sides, first hit the street (inf: no hit)."""
    mesh = trimesh.Trimesh(bg.vertices, bg.faces, process=False)
    az = np.radians(np.r_[np.linspace(*deg, 16), -np.linspace(*deg, 16)])
    z0 = float(bg.terrain.height(np.array([x]), np.array([0.0]))[0]) + up
    o = np.tile([x, 0.0, z0], (len(az), 1))
    d = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], axis=1)
    loc, ray, _ = RayMeshIntersector(mesh).intersects_location(o, d, multiple_hits=False)
    lateral = np.full(len(az), np.inf)
    lateral[ray] = np.abs(loc[:, 1])
    return lateral


def test_town_streets_are_narrow_and_built_up_on_both_sides():
    """A town street (drawn with probability TOWN_P from its own stream) has flat roadsides, the
    narrowest road the free zone allows, narrow sidewalks, and blocks close behind them on both
    sides: level rays to the sides from the road's centre line end on them within 25 m."""
    town = [i for i in range(60) if streets._layout(i).town]
    other = [i for i in range(60) if i not in town]
    assert 0 < len(town) < 60
    assert abs(len(town) / 60 - streets.TOWN_P) < 0.2
    for i in town[:4]:
        lay = streets._layout(i)
        assert streets.TOWN_HALF_WIDTH[0] <= lay.half_width <= streets.TOWN_HALF_WIDTH[1]
        assert all(streets.TOWN_SIDEWALK[0] <= w <= streets.TOWN_SIDEWALK[1]
                   for w in lay.sidewalk)
        assert [s.kind for s in lay.terrain.sides] == ["flat", "flat"]
        bg = build_background(i)
        blocks = [o.polygon for o in bg.obstacles if o.label.startswith("building")]
        for side in (1, -1):
            near = [float(np.abs(p[:, 1]).min()) for p in blocks if p[:, 1].mean() * side > 0]
            assert near, f"street {i}: no block on side {side}"
            assert min(near) <= lay.half_width + max(lay.sidewalk) + 12.0
        # Level rays 2 m up, 30-60 degrees off the road to both sides, from x = 40 m (past the
        # free zone's kerbside gap): most end within 25 m sideways.
        lateral = _side_hits(bg, 40.0, 2.0, (30, 60))
        assert np.median(lateral) < 25.0, (i, np.round(lateral, 1))
    assert all(streets._layout(i).half_width >= 9.0 for i in other)


def test_narrowing_streets_keep_the_free_zone_and_narrow_beyond_it():
    """A narrowing street (drawn with probability NARROW_P from its own stream) keeps its full
    width along the free zone and a margin each way, and beyond the tapers its kerbs stand
    NARROW_KERB from the centre line: the ground there is road inside the kerb and sidewalk
    outside, the kerb obstacles follow the line, and level rays to the sides from the centre
    line end within a residential street's width."""
    narrow = [i for i in range(60) if streets._layout(i).terrain.narrow > 0]
    assert abs(len(narrow) / 60 - streets.NARROW_P) < 0.2
    for i in narrow[:4]:
        t = streets._layout(i).terrain
        (fx0, fx1), _ = FREE_ZONE
        zone = np.linspace(fx0 - streets.NARROW_WIDE_BEHIND[0],
                           fx1 + streets.NARROW_WIDE_AHEAD[0], 50)
        assert (t.kerb(zone) == t.half_width).all()
        far = np.array([-120.0, -60.0, 90.0, 150.0])
        k = t.kerb(far)
        assert ((k >= streets.NARROW_KERB[0] - 1e-9) & (k <= streets.NARROW_KERB[1]
                                                              + 1e-9)).all()
        # road just inside the kerb, the raised sidewalk just outside it
        for side in (1, -1):
            z_in = t.height(far, side * (k - 0.05))
            z_out = t.height(far, side * (k + 0.05))
            np.testing.assert_allclose(z_out - z_in, t.curb_h, atol=0.01)
        bg = build_background(i)
        curbs = [o.polygon for o in bg.obstacles if o.label.startswith("curb left")]
        for x in (-60.0, 10.0, 90.0):
            inner = min(float(np.interp(x, p[:2, 0], p[:2, 1])) for p in curbs
                        if p[0, 0] <= x <= p[1, 0])
            assert inner == pytest.approx(float(t.kerb(x)))
        lateral = _side_hits(bg, 90.0, 1.0, (40, 80))
        assert np.median(lateral) < 25.0, (i, np.round(lateral, 1))
    wide = next(i for i in range(60) if i not in narrow)
    assert build_background(wide).terrain.narrow == 0.0   # the built street keeps its layout


def test_guard_rails_stand_where_the_ground_falls_away():
    """Streets with an embankment down or a ditch beside the road get a guard rail on that side
    in about 7 of 10 cases (poles and signs, placed after, keep off its line)."""
    falls = [i for i in range(60) if any(s.kind in ("embankment down", "ditch")
                                         for s in streets._layout(i).terrain.sides)]
    # The rails are placed third; what is placed after them never removes one.
    upto_rails = streets.STEPS[:streets.STEPS.index(streets._guard_rails) + 1]

    def rails(i: int) -> bool:
        st, _ = streets.placed(i, upto_rails)
        return any(o.label.startswith("guard rail") for o in st.obstacles)

    railed = [i for i in falls if rails(i)]
    assert len(falls) >= 15 and len(railed) >= 0.5 * len(falls)
    assert not any(rails(i) for i in range(60) if i not in falls)
    # and the whole street holds the same rails
    whole = build_background(railed[0]).obstacles
    assert any(o.label.startswith("guard rail") for o in whole)
