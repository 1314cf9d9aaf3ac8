"""`--fidelity` presets: named trades of speed against accuracy for `grid` and `search`.

Each preset is a setting of the knobs `falsify tradeoff` measures; the README records what each
costs and changes (time per sample, mIoU-map error, blind-spot agreement) on the paper's space.
"""

from __future__ import annotations

from dataclasses import dataclass

from falsify.errors import FalsifyError


@dataclass(frozen=True)
class Fidelity:
    """Car mesh level of detail and sensor resolution scale for a run."""

    name: str
    lod: int = 2

    def sensor_overrides(self, sensor: str) -> dict:
        """Sensor keys this preset changes (none: the network fixes the resolution)."""
        return {}


PRESETS = {
    "exact": Fidelity("exact", lod=2),
    "balanced": Fidelity("balanced", lod=1),
    "fast": Fidelity("fast", lod=0),
}


def preset(name: str) -> Fidelity:
    if name not in PRESETS:
        raise FalsifyError(f"--fidelity: unknown preset {name!r}; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]
