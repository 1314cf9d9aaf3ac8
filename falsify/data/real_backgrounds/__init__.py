"""Synthetic cars inserted into real scans: the user's own streets as backgrounds.

`scanner` holds the RealScanner (placement on the real ground, insertion, weather on real
returns) and `scanner_for`; `background` reads a real scan for insertion; `ground` indexes its
points and fits the ground under a car; `rays` holds the image's ray geometry; `normals`
estimates surface normals from the image.
"""

from falsify.data.real_backgrounds.background import RealBackground, read_background
from falsify.data.real_backgrounds.ground import PointIndex, fit_ground
from falsify.data.real_backgrounds.rays import pixel_directions
from falsify.data.real_backgrounds.scanner import (
    COLLISION_POINTS,
    INSERTED_INSTANCE,
    RealScanner,
    refuse_effects,
    scanner_for,
)

__all__ = ["COLLISION_POINTS", "INSERTED_INSTANCE", "PointIndex", "RealBackground", "RealScanner",
           "fit_ground", "pixel_directions", "read_background", "refuse_effects", "scanner_for"]
