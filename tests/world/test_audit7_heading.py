"""A street's cars face where the street placed them, and its KITTI labels say so: the box of
a parked car's vertices alone has no front (a principal axis is + or -), so half the parked
cars' rotation_y and alpha were off by 180 degrees."""

from __future__ import annotations

import math

import numpy as np
import pytest

from falsify.classes import CAR
from falsify.data.kitti_export import street_object
from falsify.world.cars import BUILTIN_MODELS, car_parts
from falsify.world.streets import build_background


def _roof_offset(verts: np.ndarray, heading: float) -> float:
    """How far ahead (+) of the box's centre the top fifth of a car stands, along `heading`."""
    ax = np.array([math.cos(heading), math.sin(heading)])
    along = verts[:, :2] @ ax
    z = verts[:, 2]
    top = z > z.min() + 0.8 * (z.max() - z.min())
    return float(along[top].mean() - (along.max() + along.min()) / 2)


def test_every_builtin_car_but_the_pickup_has_its_roof_behind_its_centre() -> None:
    """The signature the street test reads: a car's own frame faces +x."""
    for name in BUILTIN_MODELS:
        v = np.asarray(car_parts(name, 1)[0])
        off = _roof_offset(v, 0.0)
        assert (off > 0) if name == "pickup" else (off < -0.1), (name, off)


@pytest.mark.parametrize("bg_id", [0, 3, 7])
def test_parked_cars_face_where_the_street_placed_them(bg_id: int) -> None:
    bg = build_background(bg_id)
    cars = [o for o in bg.obstacles if o.label.startswith("parked car")]
    assert len(cars) >= 3
    judged = 0
    for o in cars:
        box = street_object(bg, o.instance)
        assert box is not None and box.cls == CAR
        assert abs(math.remainder(box.heading - o.heading, 2 * math.pi)) < 1e-9
        verts = bg.vertices[np.unique(bg.faces[bg.face_instance == o.instance])]
        off = _roof_offset(verts, box.heading)
        if abs(off) > 0.2:   # every model but the pickup, whose roof sits near its centre
            assert off < 0, (o.label, off)
            judged += 1
        assert 3.4 < box.length < 5.5 and 1.4 < box.width < 2.5, o.label
    assert judged >= 2
