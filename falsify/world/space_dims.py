"""The dims of a modification space: a range with a step (`Continuous`) or a list of values
(`Categorical`), the names a space's dims may take (per object, image-only, the weather and fault
effects with their bounds), and reading one dim, or one typed key, from its config table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from falsify.errors import ConfigError

CONTINUOUS_BASE = ("x", "y", "yaw")
IMAGE_ONLY = ("colour", "weather", "time_of_day")
MODEL_DIMS = ("actor", "car_model")   # the object dim's name, and its older alias
# How far a coordinate may reach: metres for x and y (far beyond any sensor's range), degrees
# for yaw (one turn either way; the scene wraps any angle, a config needs no more).
LIMITS = {"x": 1000.0, "y": 1000.0, "yaw": 360.0}
MAX_VALUES = 1_000_000   # values one dim may list or range over
MIN_STEP = 1e-9          # a range's smallest step: its values are rounded to 1e-10
# Weather and sensor faults on the LiDAR: name -> (lowest, highest, unit, whole numbers only).
# 0 is no effect; fog is the meteorological visibility (0 = no fog, small = dense).
EFFECT_DIMS: dict[str, tuple[float, float, str, bool]] = {
    "fog": (0.0, 100_000.0, "m of visibility", False),
    "rain": (0.0, 500.0, "mm/h", False),
    "snow": (0.0, 100.0, "mm/h of water", False),
    "wet_road": (0.0, 20.0, "mm of water film", False),
    "beam_loss": (0.0, 128.0, "lasers", True),
    "beams": (0.0, 128.0, "lasers kept (0 = all)", True),
    "crosstalk": (0.0, 100_000.0, "points per scan", True),
    "ego_speed": (0.0, 300.0, "km/h", False),
}


Value = float | int | str


@dataclass(frozen=True)
class Continuous:
    """A real-valued dim with inclusive bounds and the step the grid uses."""

    name: str
    lo: float
    hi: float
    step: float
    period: float | None = None   # an angle's turn (360 for yaw): lo and lo + period are one

    @property
    def size(self) -> int:
        """How many values the grid takes, computed without making them: an angle's grid
        stops before it comes round to a value it holds (-180..180 every 45: 8 headings)."""
        n = int(math.floor((self.hi - self.lo) / self.step + 1e-9)) + 1
        if self.period is not None:
            for turns in (1, 2):   # the grid's first repeat: k steps make whole turns
                k = round(turns * self.period / self.step)
                if abs(k * self.step - turns * self.period) < 1e-9 * max(1.0, self.period):
                    return min(n, k)
        return n

    def grid(self) -> tuple[float, ...]:
        """The values; a range's rounded to 1e-10 so that float steps land on their decimals,
        a single value as given (fog at 1e-11 m stays fog, not 0)."""
        if self.lo == self.hi:
            return (self.lo,)
        return tuple(round(self.lo + i * self.step, 10) for i in range(self.size))

    def contains(self, value: float) -> bool:
        return self.lo - 1e-9 <= value <= self.hi + 1e-9


@dataclass(frozen=True)
class Categorical:
    """A dim that takes one of a listed set of values (strings or integers)."""

    name: str
    values: tuple[Value, ...]

    @property
    def size(self) -> int:
        return len(self.values)

    def grid(self) -> tuple[Value, ...]:
        return self.values

    def contains(self, value: Value) -> bool:
        return value in self.values


Dim = Continuous | Categorical


def car_index(name: str) -> int:
    """1 for car 1's dims, k for `*_k`, 0 for dims that are not per car."""
    for base in (*MODEL_DIMS, *CONTINUOUS_BASE):
        if name == base:
            return 1
        if name.startswith(base + "_") and name[len(base) + 1:].isdigit():
            return int(name[len(base) + 1:])
    return 0



def read_typed(raw: dict, key: str, types, where: str, default):
    if key not in raw:
        return default
    value = raw[key]
    if isinstance(value, bool) or not isinstance(value, types):
        names = (types.__name__ if isinstance(types, type)
                 else " or ".join(t.__name__ for t in types))
        raise ConfigError(f"{where}{key}: expected {names}, got {value!r}")
    return value


def read_categorical(name: str, spec: Any, where: str, kind: type) -> Categorical:
    """`{values = [...]}` or, for integers, `{range = [start, stop]}` (stop exclusive)."""
    key = f"dims.{name}"
    if not isinstance(spec, dict):
        raise ConfigError(f"{where}{key}: expected a table with 'values' (a list)")
    extra = sorted(set(spec) - {"values", "range"})
    if extra:
        raise ConfigError(f"{where}{key}: unknown key {extra[0]!r}; allowed: values"
                          + (", range" if kind is int else ""))
    if "range" in spec and kind is int:
        r = spec["range"]
        if (not isinstance(r, list) or len(r) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in r)):
            raise ConfigError(f"{where}{key}.range: expected [start, stop] integers")
        if not 0 < r[1] - r[0] <= MAX_VALUES:
            raise ConfigError(f"{where}{key}.range: [{r[0]}, {r[1]}) holds {r[1] - r[0]} values; "
                              f"allowed 1 to {MAX_VALUES}")
        values = list(range(r[0], r[1]))
    elif "values" in spec:
        values = spec["values"]
    else:
        raise ConfigError(f"{where}{key}: needs 'values'" + (" or 'range'" if kind is int else ""))
    if not isinstance(values, list) or not values:
        raise ConfigError(f"{where}{key}.values: expected a non-empty list")
    if len(values) > MAX_VALUES:
        raise ConfigError(f"{where}{key}.values: {len(values)} values; at most {MAX_VALUES}")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, kind):
            raise ConfigError(f"{where}{key}.values: {v!r} is not {kind.__name__}")
    if len(set(values)) != len(values):
        raise ConfigError(f"{where}{key}.values: duplicate values")
    return Categorical(name, tuple(values))


def read_continuous_or_values(name: str, spec: Any, where: str) -> Dim:
    """`{min, max, step}` for a range, or `{values = [...]}` for fixed values (all numbers),
    within the dim's limit (LIMITS, or EFFECT_DIMS' bounds, whole numbers where it says so) and at
    most MAX_VALUES of them."""
    key = f"dims.{name}"
    whole = False
    if name in EFFECT_DIMS:
        lo, hi, unit, whole = EFFECT_DIMS[name]
    else:
        limit = LIMITS[name.split("_")[0]]
        lo, hi = -limit, limit
        unit = "degrees" if name.startswith("yaw") else "m"
    period = 360.0 if name.startswith("yaw") else None

    def within(v: float, what: str) -> None:
        if not lo <= v <= hi:
            raise ConfigError(f"{where}{what}: {v:g} is beyond the allowed {lo:g} to "
                              f"{hi:g} {unit}")
        if whole and v != int(v):
            raise ConfigError(f"{where}{what}: {v:g} is not a whole number of {unit}")
    if not isinstance(spec, dict):
        raise ConfigError(f"{where}{key}: expected a table with min, max, step (or values)")
    extra = sorted(set(spec) - {"min", "max", "step", "values"})
    if extra:
        raise ConfigError(f"{where}{key}: unknown key {extra[0]!r}; allowed: min, max, step, "
                          "values")
    if "values" in spec:
        if set(spec) != {"values"}:
            raise ConfigError(f"{where}{key}: give either values or min/max/step, not both")
        values = spec["values"]
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}{key}.values: expected a non-empty list of numbers")
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{where}{key}.values: {v!r} is not a finite number")
            within(float(v), f"{key}.values")
        if len(values) > MAX_VALUES:
            raise ConfigError(f"{where}{key}.values: {len(values)} values; at most {MAX_VALUES}")
        if period is not None:
            turned = [round(float(v) % period, 9) % period for v in values]
            for i, t in enumerate(turned):
                j = turned.index(t)
                if j < i:
                    raise ConfigError(f"{where}{key}.values: {values[j]:g} and {values[i]:g} "
                                      f"degrees are one heading; list each heading once")
        if len(values) == 1:
            v = float(values[0])
            return Continuous(name, v, v, 1.0, period)
        return Categorical(name, tuple(float(v) for v in values))
    missing = [k for k in ("min", "max", "step") if k not in spec]
    if missing:
        raise ConfigError(f"{where}{key}: missing {missing[0]!r}; a range needs min, max, step")
    nums = {}
    for k in ("min", "max", "step"):
        v = spec[k]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ConfigError(f"{where}{key}.{k}: expected a finite number, got {v!r}")
        nums[k] = float(v)
    if nums["step"] <= 0:
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} must be > 0")
    if nums["step"] < MIN_STEP:
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} must be >= {MIN_STEP:g} (a "
                          "range's values are rounded to 1e-10)")
    if nums["max"] < nums["min"]:
        raise ConfigError(f"{where}{key}: empty range, max {nums['max']:g} < min {nums['min']:g}")
    within(nums["min"], f"{key}.min")
    within(nums["max"], f"{key}.max")
    if whole and nums["step"] != int(nums["step"]):
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} is not a whole number of {unit}")
    dim = Continuous(name, nums["min"], nums["max"], nums["step"], period)
    if dim.size > MAX_VALUES:
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} makes {dim.size} values; at most "
                          f"{MAX_VALUES} (take a larger step)")
    return dim
