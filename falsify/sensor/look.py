"""What the image-only dims (colour, weather, time of day) mean to the camera: a Look.

Only the camera's RGB image reads these dims; the LiDAR scan never does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from falsify.errors import ConfigError
from falsify.world.space import IMAGE_ONLY, Sample, Space

# -- the image-only dims ----------------------------------------------------------------------
COLOURS = {
    "red": (0.55, 0.03, 0.03), "white": (0.80, 0.80, 0.78), "black": (0.025, 0.025, 0.03),
    "silver": (0.50, 0.52, 0.55), "grey": (0.22, 0.23, 0.24), "gray": (0.22, 0.23, 0.24),
    "blue": (0.03, 0.10, 0.45), "green": (0.04, 0.28, 0.08), "yellow": (0.75, 0.55, 0.02),
    "orange": (0.80, 0.25, 0.02), "brown": (0.20, 0.09, 0.04),
}
WEATHERS = ("clear", "sun", "cloudy", "rain", "fog")
TIMES = {"dawn": 6.5, "morning": 9.0, "noon": 12.0, "afternoon": 15.0, "dusk": 17.5,
         "night": 22.0}
# Extinction per metre (fog and rain attenuate with depth) and direct sun kept through clouds.
EXTINCTION = {"clear": 1 / 3000, "cloudy": 1 / 1500, "rain": 1 / 180, "fog": 1 / 28}
SUN_KEPT = {"clear": 1.0, "cloudy": 0.2, "rain": 0.08, "fog": 0.25}


@dataclass(frozen=True)
class Look:
    """What the image-only dims set: car paint (linear RGB), weather and the hour (0..24);
    `extinction` (1/m) overrides the weather's own when a `fog` visibility sets it."""

    colour: tuple[float, float, float] = COLOURS["silver"]
    weather: str = "clear"
    hour: float = 12.0
    extinction: float | None = None


def parse_look(values: dict[str, object]) -> Look:
    """Look from {colour, weather, time_of_day}; a bad value names its dim and what is allowed."""
    look = Look()
    if "colour" in values:
        c = str(values["colour"]).lower()
        if c in COLOURS:
            rgb = COLOURS[c]
        elif len(c) == 7 and c[0] == "#" and all(ch in "0123456789abcdef" for ch in c[1:]):
            rgb = tuple((int(c[k:k + 2], 16) / 255.0) ** 2.2 for k in (1, 3, 5))
        else:
            raise ConfigError(f"dims.colour: {values['colour']!r} is not a colour; allowed: "
                              f"{', '.join(COLOURS)} or #rrggbb")
        look = replace(look, colour=tuple(float(v) for v in rgb))
    if "weather" in values:
        w = str(values["weather"]).lower()
        if w not in WEATHERS:
            raise ConfigError(f"dims.weather: {values['weather']!r} is not a weather; allowed: "
                              f"{', '.join(WEATHERS)}")
        look = replace(look, weather="clear" if w == "sun" else w)
    if "time_of_day" in values:
        t = str(values["time_of_day"]).lower()
        if t in TIMES:
            hour = TIMES[t]
        else:
            try:
                hh, mm = t.split(":")
                hour = int(hh) + int(mm) / 60
                ok = len(mm) == 2 and 0 <= int(mm) < 60 and 0 <= hour <= 24
            except ValueError:
                ok = False
            if not ok:
                raise ConfigError(f"dims.time_of_day: {values['time_of_day']!r} is not a time; "
                                  f"allowed: {', '.join(TIMES)} or HH:MM (00:00..24:00)")
        look = replace(look, hour=float(hour))
    return look


def look_of(sample: Sample) -> Look:
    """The sample's look; the LiDAR's weather dims drive the camera from the same values: a
    `fog` visibility V sets the extinction ln(20) / V (Koschmieder, as the LiDAR's fog) and, with
    no `weather` dim, the weather "fog"; a `rain` rate with no `weather` dim the weather "rain"."""
    look = parse_look({d: sample[d] for d in IMAGE_ONLY if sample.get(d) is not None})
    fog, rain = float(sample.get("fog") or 0.0), float(sample.get("rain") or 0.0)
    own = sample.get("weather") is not None
    if fog > 0:
        look = replace(look, extinction=math.log(20.0) / fog,
                       weather=look.weather if own else "fog")
    elif rain > 0 and not own:
        look = replace(look, weather="rain")
    return look


def check_looks(space: Space) -> None:
    """Fail before anything is written if an image-only dim holds a value we cannot render,
    with or without a camera: the value is stored with every sample either way."""
    for name in IMAGE_ONLY:
        if name in space.dims:
            for v in space.dims[name].grid():
                try:
                    parse_look({name: v})
                except ConfigError as e:
                    raise ConfigError(f"{space.source}: {e}") from None
