"""The modification space: dimensions read from a TOML config, validated, and the samples in it.

A config names the sensor preset and one table per dimension. The object under test 1 is
described by `actor` (or its older name `car_model`: a config keeps the name it uses, and its
bytes), `x`, `y`, `yaw`; object k >= 2 by `actor_k`, `x_k`, `y_k`, `yaw_k` (defaulting to
object 1's ranges). An actor is a built-in car model, a built-in road user
(falsify.world.actors) or a user mesh (`[car_models.NAME]`, or `[actors.NAME]` with its
SemanticKITTI `class`); `on` in its table says where it must stand. `count` says how many
objects a sample holds, `background` which street it stands on, and image-only dims
(`colour`, `weather`, `time_of_day`) are carried along but never change a scan.
Effect dims (EFFECT_DIMS: `fog`, `rain`, `snow`, `wet_road`, `beam_loss`, `beams`, `crosstalk`,
`ego_speed`) are weather and faults in physical units that the sensor applies to each ray after
casting (falsify.sensor.weather); absent or 0 is today's clear scan.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from falsify.checks import SEED_MAX
from falsify.errors import ConfigError
from falsify.fileio import read_bytes
from falsify.paths import config_path

CONTINUOUS_BASE = ("x", "y", "yaw")
IMAGE_ONLY = ("colour", "weather", "time_of_day")
TOP_KEYS = {"name", "description", "sensor", "seed", "threshold", "dims", "car_models", "actors"}
MODEL_DIMS = ("actor", "car_model")   # the object dim's name, and its older alias
MAX_CARS = 8
# How far a coordinate may reach: metres for x and y (far beyond any sensor's range), degrees
# for yaw (one turn either way; the scene wraps any angle, a config needs no more).
LIMITS = {"x": 1000.0, "y": 1000.0, "yaw": 360.0}
MAX_VALUES = 1_000_000   # values one dim may list or range over
DEFAULT_THRESHOLD = 0.65   # mIoU below which a cell is a blind spot (the paper's)
CAR_FILE_KEYS = {"file", "scale", "forward", "up"}
ACTOR_FILE_KEYS = CAR_FILE_KEYS | {"class"}
# The SemanticKITTI classes a user's actor may declare: the things a road holds.
ACTOR_CLASSES = ("car", "truck", "bus", "other-vehicle", "motorcycle", "bicycle", "person",
                 "bicyclist", "motorcyclist", "other-object")
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

    @property
    def size(self) -> int:
        """How many values the grid takes, computed without making them."""
        return int(math.floor((self.hi - self.lo) / self.step + 1e-9)) + 1

    def grid(self) -> tuple[float, ...]:
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


@dataclass(frozen=True)
class UserCar:
    """A car model or actor the user brings as a mesh file, with the raw SemanticKITTI id its
    points carry (car for `[car_models.*]`)."""

    name: str
    file: Path
    scale: float = 1.0
    forward: str = "+x"
    up: str = "+z"
    semantic: int = 10


@dataclass(frozen=True)
class RealScan:
    """A real scan a background may be: its KITTI .bin and where its labels come from (a
    SemanticKITTI .label, a KITTI object frame's label_2 boxes, or none)."""

    name: str
    bin: Path
    label: Path | None = None
    kind: str = "none"   # "semantickitti", "object" or "none" (unlabelled)
    # The scan turned by this about the sensor's vertical axis before it is projected (rings
    # still from the stored order): a front-view sensor sees another slice of the 360 degrees.
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class CarPose:
    """One car in a sample: model and pose in the space's coordinates (x right, y forward)."""

    model: str
    x: float
    y: float
    yaw: float


@dataclass(frozen=True)
class Sample:
    """One point of the space: a value for every dim, in the space's dim order."""

    values: tuple[tuple[str, Value], ...]

    def __getitem__(self, key: str) -> Value:
        for name, value in self.values:
            if name == key:
                return value
        raise KeyError(key)

    def get(self, key: str, default: Value | None = None) -> Value | None:
        try:
            return self[key]
        except KeyError:
            return default

    def as_dict(self) -> dict[str, Value]:
        return dict(self.values)

    @property
    def count(self) -> int:
        return int(self.get("count", 1))

    @property
    def background(self) -> int:
        return int(self["background"])

    @property
    def cars(self) -> tuple[CarPose, ...]:
        """The sample's cars, car 1 first; dims of cars beyond `count` are ignored."""
        out = []
        for k in range(1, self.count + 1):
            sfx = "" if k == 1 else f"_{k}"
            model = self.get("actor" + sfx)
            out.append(
                CarPose(
                    model=str(self["car_model" + sfx] if model is None else model),
                    x=float(self["x" + sfx]),
                    y=float(self["y" + sfx]),
                    yaw=float(self["yaw" + sfx]),
                )
            )
        return tuple(out)

    @property
    def effects(self) -> tuple[tuple[str, float], ...]:
        """The sample's non-zero weather and fault dims (EFFECT_DIMS), in dim order."""
        return tuple((n, float(v)) for n, v in self.values if n in EFFECT_DIMS and float(v))

    def scene_key(self) -> tuple:
        """What the LiDAR scan depends on: cars (up to count), background and the effect dims
        (zero ones left out: they change nothing), not image dims."""
        return (self.background, tuple(self.cars), self.effects)


@dataclass(frozen=True)
class Space:
    """A validated modification space."""

    name: str
    sensor: str
    seed: int
    threshold: float
    dims: dict[str, Dim]
    user_cars: dict[str, UserCar] = field(default_factory=dict)
    source: str = ""
    config_hash: str = ""
    # Real scans as backgrounds (`[dims.background] real = [...]`): background k is the k-th.
    real_backgrounds: tuple[RealScan, ...] = ()
    # Where object k must stand ("any", "road", "sidewalk"), for k = 1..max count; () is any.
    surfaces: tuple[str, ...] = ()

    @property
    def model_dim(self) -> str:
        """The name of object 1's model dim: "actor", or "car_model" in older configs."""
        return "actor" if "actor" in self.dims else "car_model"

    def models(self) -> tuple[str, ...]:
        """Every model the space may place, over all objects' model dims, in first-seen order."""
        out: dict[str, None] = {}
        for name, dim in self.dims.items():
            if car_index(name) and name.startswith(self.model_dim):
                out.update((str(v), None) for v in dim.values)
        return tuple(out)

    def require_streets(self, what: str) -> None:
        """ConfigError unless the backgrounds are our streets: `what` renders or rebuilds the
        scene, which a real scan does not have."""
        if self.real_backgrounds:
            raise ConfigError(f"{self.source}: {what} works on our streets; this space's "
                              "backgrounds are real scans")

    def background_name(self, bg: int) -> str:
        """How a report names a background: the real scan's name, else the street's id."""
        if self.real_backgrounds:
            return self.real_backgrounds[int(bg)].name
        return f"street {int(bg)}"

    @property
    def max_count(self) -> int:
        count = self.dims["count"]
        return max(int(v) for v in count.grid())

    def continuous(self, count: int | None = None) -> tuple[Continuous, ...]:
        """Continuous dims that are active for samples holding `count` cars (default: all)."""
        return tuple(d for d in self.dims.values() if isinstance(d, Continuous)
                     and self.active(d.name, count))

    def discrete(self) -> tuple[Categorical, ...]:
        return tuple(d for d in self.dims.values() if isinstance(d, Categorical))

    def active(self, name: str, count: int | None) -> bool:
        """Whether dim `name` changes a sample holding `count` cars."""
        if count is None:
            return True
        return car_index(name) <= count

    def first(self) -> dict[str, Value]:
        return {name: dim.grid()[0] for name, dim in self.dims.items()}

    def make(self, values: dict[str, Value]) -> Sample:
        """Build a sample from a partial dict: missing dims take their first value, and dims of
        cars beyond `count` are pinned to their first value so equal scenes give equal samples."""
        unknown = sorted(set(values) - set(self.dims))
        if unknown:
            raise ConfigError(
                f"unknown dim {unknown[0]!r}; the space has: {', '.join(self.dims)}")
        merged = self.first()
        for name, raw in values.items():
            merged[name] = self.coerce(name, raw)
        count = int(merged.get("count", 1))
        for name, dim in self.dims.items():
            if not self.active(name, count):
                merged[name] = dim.grid()[0]
        return Sample(tuple((name, merged[name]) for name in self.dims))

    def coerce(self, name: str, raw: Value) -> Value:
        """Convert a raw value (e.g. a `--set` string) to the dim's type; check it is in range."""
        dim = self.dims[name]
        if isinstance(dim, Continuous):
            try:
                value = float(raw)
            except (TypeError, ValueError):
                raise ConfigError(f"{name}: {raw!r} is not a number") from None
            if not math.isfinite(value) or not dim.contains(value):
                raise ConfigError(f"{name}: {raw!r} is outside [{dim.lo:g}, {dim.hi:g}]")
            return value
        for allowed in dim.values:
            if str(allowed) == str(raw):
                return allowed
        if all(isinstance(v, float) for v in dim.values):   # `--set fog=50` for 50.0
            try:
                number = float(raw)
            except (TypeError, ValueError):
                number = math.nan
            for allowed in dim.values:
                if allowed == number:
                    return allowed
        raise ConfigError(
            f"{name}: {raw!r} is not one of {', '.join(str(v) for v in dim.values)}")

    def size(self) -> int:
        """How many samples `grid()` holds, computed without enumerating them."""
        total = 0
        for count in self.dims["count"].grid():
            n = 1
            for name, dim in self.dims.items():
                if name != "count" and self.active(name, int(count)):
                    n *= dim.size
            total += n
        return total

    def check_size(self, limit: int, option: str = "--max-samples") -> None:
        """ConfigError unless the grid holds at most `limit` samples (counted, not made)."""
        n = self.size()
        if n > limit:
            raise ConfigError(f"{self.source}: the grid holds {n:,} samples, more than {option} "
                              f"{limit:,}; take larger steps or fewer values")

    def grid(self) -> list[Sample]:
        """The full factorial set at the configured steps, no duplicates, in a fixed order.

        Dims of cars beyond a sample's `count` are not enumerated (they cannot change it)."""
        out: list[Sample] = []
        for count in self.dims["count"].grid():
            axes = []
            for name, dim in self.dims.items():
                axes.append(dim.grid() if self.active(name, int(count)) or name == "count"
                            else dim.grid()[:1])
            names = list(self.dims)
            ci = names.index("count")
            axes[ci] = (count,)
            for combo in itertools.product(*axes):
                out.append(Sample(tuple(zip(names, combo, strict=True))))
        return out


def car_index(name: str) -> int:
    """1 for car 1's dims, k for `*_k`, 0 for dims that are not per car."""
    for base in (*MODEL_DIMS, *CONTINUOUS_BASE):
        if name == base:
            return 1
        if name.startswith(base + "_") and name[len(base) + 1:].isdigit():
            return int(name[len(base) + 1:])
    return 0


def load_space(path: str | Path, builtin_cars: tuple[str, ...] | None = None) -> Space:
    """Read and validate a space config (a file, or a bundled config by its name); every problem
    names its key and the allowed values."""
    path = config_path(path)
    text = read_bytes(path, "config", ConfigError)
    try:
        raw = tomllib.loads(text.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    space = parse_space(raw, source=str(path), base_dir=path.parent,
                        config_hash=hashlib.sha256(text).hexdigest(), builtin_cars=builtin_cars)
    if not space.real_backgrounds:
        return space
    digest = hashlib.sha256(space.config_hash.encode())   # changed scans: another space
    for r in space.real_backgrounds:
        for f in (r.bin, r.label):
            if f is not None:
                digest.update(read_bytes(f, "real background", ConfigError))
    return replace(space, config_hash=digest.hexdigest())


def parse_space(raw: dict[str, Any], source: str = "<config>", base_dir: Path | None = None,
                config_hash: str = "", builtin_cars: tuple[str, ...] | None = None,
                real_backgrounds: tuple[RealScan, ...] | None = None) -> Space:
    """Validate a parsed config dict into a Space; `real_backgrounds`, when given, are the real
    scans a run recorded, used instead of looking for them again (a run's data may move)."""
    if builtin_cars is None:
        from falsify.world.cars import BUILTIN_MODELS
        builtin_cars = BUILTIN_MODELS
    from falsify.world.streets import MAX_BACKGROUND_ID

    where = f"{source}: "
    extra = sorted(set(raw) - TOP_KEYS)
    if extra:
        raise ConfigError(f"{where}unknown key {extra[0]!r}; allowed: "
                          f"{', '.join(sorted(TOP_KEYS))}")
    name = _typed(raw, "name", str, where, default=Path(source).stem)
    sensor = _typed(raw, "sensor", str, where, default="kitti-hdl64e-front")
    seed = _typed(raw, "seed", int, where, default=0)
    if not 0 <= seed <= SEED_MAX:
        raise ConfigError(f"{where}seed: {seed} must be between 0 and {SEED_MAX}")
    threshold = float(_typed(raw, "threshold", (int, float), where, default=DEFAULT_THRESHOLD))
    if not 0.0 < threshold <= 1.0:
        raise ConfigError(f"{where}threshold: {threshold} must be in (0, 1]")

    from falsify.world.actors import ACTOR_NAMES
    user_cars = _user_cars(raw.get("car_models", {}), where, base_dir or Path("."),
                           (*builtin_cars, *ACTOR_NAMES))
    user_cars |= _user_cars(raw.get("actors", {}), where, base_dir or Path("."),
                            (*builtin_cars, *ACTOR_NAMES, *user_cars), table="actors")
    models = (*builtin_cars, *ACTOR_NAMES, *user_cars)

    dims_raw = raw.get("dims")
    if not isinstance(dims_raw, dict):
        raise ConfigError(f"{where}missing table [dims] (with actor, x, y, yaw, count, "
                          "background)")
    if all(m in dims_raw for m in MODEL_DIMS):
        raise ConfigError(f"{where}dims.car_model: the older name of dims.actor; give one of "
                          "them, not both")
    model_dim = "car_model" if "car_model" in dims_raw else "actor"
    for required in (model_dim, "x", "y", "background"):
        if required not in dims_raw:
            raise ConfigError(f"{where}dims.{required} is missing; required dims: actor (or "
                              "car_model), x, y, background (yaw and count default to 0 and 1)")
    dims_raw = dict(dims_raw)
    dims_raw.setdefault("yaw", {"values": [0.0]})
    dims_raw.setdefault("count", {"values": [1]})

    count = _categorical("count", dims_raw["count"], where, int)
    for c in count.values:
        if not 1 <= int(c) <= MAX_CARS:
            raise ConfigError(f"{where}dims.count: {c} must be between 1 and {MAX_CARS}")
    max_count = max(int(c) for c in count.values)

    allowed = {model_dim, *CONTINUOUS_BASE, "count", "background", *IMAGE_ONLY, *EFFECT_DIMS}
    for k in range(2, max_count + 1):
        allowed |= {f"{model_dim}_{k}", *(f"{b}_{k}" for b in CONTINUOUS_BASE)}
    unknown = sorted(set(dims_raw) - allowed)
    if unknown:
        raise ConfigError(f"{where}unknown dim dims.{unknown[0]}; allowed: "
                          f"{', '.join(sorted(allowed))}")

    dims: dict[str, Dim] = {}
    surfaces: list[str] = []
    for k in range(1, max_count + 1):
        sfx = "" if k == 1 else f"_{k}"
        spec = dims_raw.get(model_dim + sfx, dims_raw[model_dim])
        on, spec = _surface(spec, f"{where}dims.{model_dim}{sfx}")
        surfaces.append(on)
        dim = _categorical(model_dim + sfx, spec, where, str)
        for v in dim.values:
            if v not in models:
                what = "car model" if model_dim == "car_model" else "actor"
                raise ConfigError(f"{where}dims.{model_dim}{sfx}: unknown {what} {v!r}; "
                                  f"allowed: {', '.join(models)}")
        dims[model_dim + sfx] = dim
        for base in CONTINUOUS_BASE:
            spec = dims_raw.get(base + sfx, dims_raw[base])
            dims[base + sfx] = _continuous_or_values(base + sfx, spec, where)
    dims["count"] = count
    real: tuple[RealScan, ...] = ()
    bg_raw = dims_raw["background"]
    if isinstance(bg_raw, dict) and "real" in bg_raw:
        real = (real_backgrounds if real_backgrounds is not None
                else _real_backgrounds(bg_raw, where, base_dir or Path(".")))
        bg = Categorical("background", tuple(range(len(real))))
    else:
        bg = _categorical("background", bg_raw, where, int)
        for v in bg.values:
            if not 0 <= int(v) <= MAX_BACKGROUND_ID:
                raise ConfigError(f"{where}dims.background: unknown background {v}; allowed: "
                                  f"integer ids 0..{MAX_BACKGROUND_ID}, or real = [KITTI .bin "
                                  "scans, folders or SemanticKITTI sequences]")
    dims["background"] = bg
    for image_dim in IMAGE_ONLY:
        if image_dim in dims_raw:
            dims[image_dim] = _categorical(image_dim, dims_raw[image_dim], where, str)
    for effect in EFFECT_DIMS:
        if effect in dims_raw:
            dims[effect] = _continuous_or_values(effect, dims_raw[effect], where)
    if any(on != "any" for on in surfaces):
        unlabelled = [r.name for r in real if r.kind != "semantickitti"]
        if unlabelled:
            on = next(on for on in surfaces if on != "any")
            raise ConfigError(f"{where}dims.{model_dim}.on: {on!r} reads where the road "
                              f"and sidewalk are from SemanticKITTI labels; background "
                              f"{unlabelled[0]!r} has none (use on = \"any\")")
    return Space(name=name, sensor=sensor, seed=seed, threshold=threshold, dims=dims,
                 user_cars=user_cars, source=source, config_hash=config_hash,
                 real_backgrounds=real,
                 surfaces=tuple(surfaces) if any(on != "any" for on in surfaces) else ())


def _surface(spec: Any, key: str) -> tuple[str, Any]:
    """An actor dim's `on` (default "any") and its table without it; ConfigError names an
    unknown surface with the allowed ones."""
    from falsify.world.actors import SURFACES
    if not isinstance(spec, dict) or "on" not in spec:
        return "any", spec
    on = spec["on"]
    if on not in SURFACES:
        raise ConfigError(f"{key}.on: {on!r}; allowed: {', '.join(SURFACES)}")
    return on, {k: v for k, v in spec.items() if k != "on"}


def _real_backgrounds(spec: dict, where: str, base_dir: Path) -> tuple[RealScan, ...]:
    """`real = [...]` (KITTI .bin files, folders of them, SemanticKITTI roots or sequence
    folders, KITTI object directories; relative to the config's folder) and optional
    `sequences = ["08", ...]`: the scans in order, each with where its labels come from."""
    key = "dims.background"
    extra = sorted(set(spec) - {"real", "sequences", "per_sequence"})
    if extra:
        raise ConfigError(f"{where}{key}: unknown key {extra[0]!r} beside real; allowed: real, "
                          "sequences, per_sequence")
    paths = spec["real"]
    if (not isinstance(paths, list) or not paths
            or not all(isinstance(p, str) and p for p in paths)):
        raise ConfigError(f"{where}{key}.real: expected a non-empty list of paths (KITTI .bin "
                          "scans, folders, SemanticKITTI roots or sequences)")
    sequences = spec.get("sequences")
    if sequences is not None and (not isinstance(sequences, list) or not sequences or not all(
            isinstance(q, str) for q in sequences)):
        raise ConfigError(f"{where}{key}.sequences: expected a non-empty list of sequence ids "
                          "such as [\"00\", \"08\"]")
    per_sequence = spec.get("per_sequence")
    if per_sequence is not None and (isinstance(per_sequence, bool)
                                     or not isinstance(per_sequence, int) or per_sequence < 1):
        raise ConfigError(f"{where}{key}.per_sequence: expected an integer >= 1 (scans taken "
                          f"evenly spaced from each folder of scans), got {per_sequence!r}")
    from falsify.errors import FalsifyError
    from falsify.paths import expand_data_path
    from falsify.world.real_scans import evenly_per_folder, real_scans
    expanded = [expand_data_path(p, f"{where}{key}.real") for p in paths]
    resolved = [p if Path(p).is_absolute() else str(base_dir / p) for p in expanded]
    try:
        found = real_scans(resolved, sequences)
    except FalsifyError as exc:
        raise ConfigError(f"{where}{key}.real: {exc}") from None
    if per_sequence is not None:
        found = evenly_per_folder(found, per_sequence)
    if len(found) > MAX_VALUES:
        raise ConfigError(f"{where}{key}.real: {len(found)} scans; at most {MAX_VALUES}")
    return tuple(RealScan(*f) for f in found)


def _typed(raw: dict, key: str, types, where: str, default):
    if key not in raw:
        return default
    value = raw[key]
    if isinstance(value, bool) or not isinstance(value, types):
        names = (types.__name__ if isinstance(types, type)
                 else " or ".join(t.__name__ for t in types))
        raise ConfigError(f"{where}{key}: expected {names}, got {value!r}")
    return value


def _categorical(name: str, spec: Any, where: str, kind: type) -> Categorical:
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


def _continuous_or_values(name: str, spec: Any, where: str) -> Dim:
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

    def within(v: float, what: str) -> None:
        if not lo <= v <= hi:
            raise ConfigError(f"{where}{what}: {v:g} is beyond the allowed {lo:g} to "
                              f"{hi:g} {unit}")
        if whole and v != int(v):
            raise ConfigError(f"{where}{what}: {v:g} is not a whole number of {unit}")
    if not isinstance(spec, dict):
        raise ConfigError(f"{where}{key}: expected a table with min, max, step (or values)")
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
        if len(values) == 1:
            v = float(values[0])
            return Continuous(name, v, v, 1.0)
        return Categorical(name, tuple(float(v) for v in values))
    missing = [k for k in ("min", "max", "step") if k not in spec]
    if missing:
        raise ConfigError(f"{where}{key}: missing {missing[0]!r}; a range needs min, max, step")
    extra = sorted(set(spec) - {"min", "max", "step"})
    if extra:
        raise ConfigError(f"{where}{key}: unknown key {extra[0]!r}; allowed: min, max, step, "
                          "values")
    nums = {}
    for k in ("min", "max", "step"):
        v = spec[k]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ConfigError(f"{where}{key}.{k}: expected a finite number, got {v!r}")
        nums[k] = float(v)
    if nums["step"] <= 0:
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} must be > 0")
    if nums["max"] < nums["min"]:
        raise ConfigError(f"{where}{key}: empty range, max {nums['max']:g} < min {nums['min']:g}")
    within(nums["min"], f"{key}.min")
    within(nums["max"], f"{key}.max")
    if whole and nums["step"] != int(nums["step"]):
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} is not a whole number of {unit}")
    dim = Continuous(name, nums["min"], nums["max"], nums["step"])
    if dim.size > MAX_VALUES:
        raise ConfigError(f"{where}{key}.step: {nums['step']:g} makes {dim.size} values; at most "
                          f"{MAX_VALUES} (take a larger step)")
    return dim


def _user_cars(raw: Any, where: str, base_dir: Path, builtin: tuple[str, ...],
               table: str = "car_models") -> dict:
    """`[car_models.NAME]` (cars) or `[actors.NAME]` (with a SemanticKITTI `class`) tables as
    UserCars; ConfigError names a bad key, a taken name or a missing class."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}{table}: expected tables like [{table}.mine] file = ...")
    keys = ACTOR_FILE_KEYS if table == "actors" else CAR_FILE_KEYS
    out: dict[str, UserCar] = {}
    for name, spec in raw.items():
        key = f"{table}.{name}"
        if name in builtin:
            raise ConfigError(f"{where}{key}: {name!r} is a built-in or declared model; choose "
                              "another name")
        if not isinstance(spec, dict) or "file" not in spec:
            raise ConfigError(f"{where}{key}: needs file = 'path/to/mesh' (OBJ, STL, PLY, GLB)")
        extra = sorted(set(spec) - keys)
        if extra:
            raise ConfigError(f"{where}{key}: unknown key {extra[0]!r}; allowed: "
                              f"{', '.join(sorted(keys))}")
        semantic = 10
        if table == "actors":
            cls = spec.get("class")
            if cls not in ACTOR_CLASSES:
                raise ConfigError(f"{where}{key}.class: " + (
                    "missing" if cls is None else repr(cls)) + "; a user's actor declares its "
                    f"SemanticKITTI class, one of: {', '.join(ACTOR_CLASSES)}")
            from falsify.semantic import RAW_ID
            semantic = RAW_ID[cls]
        scale = spec.get("scale", 1.0)
        if isinstance(scale, bool) or not isinstance(scale, int | float) or not (
                math.isfinite(scale) and scale > 0):
            raise ConfigError(f"{where}{key}.scale: {scale!r} must be a finite number > 0")
        for axis_key in ("forward", "up"):
            v = spec.get(axis_key, "+x" if axis_key == "forward" else "+z")
            if v not in ("+x", "-x", "+y", "-y", "+z", "-z"):
                raise ConfigError(f"{where}{key}.{axis_key}: {v!r}; allowed: +x, -x, +y, -y, "
                                  "+z, -z")
        file = Path(spec["file"])
        if not file.is_absolute():
            file = base_dir / file
        out[name] = UserCar(name, file, float(scale), spec.get("forward", "+x"),
                            spec.get("up", "+z"), semantic)
    return out
