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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from falsify.checks import SEED_MAX
from falsify.errors import ConfigError
from falsify.fileio import parse_toml, read_bytes
from falsify.paths import bundled_configs, config_path, sensor_digest
from falsify.world.space_dims import (
    CONTINUOUS_BASE,
    EFFECT_DIMS,
    IMAGE_ONLY,
    MODEL_DIMS,
    Categorical,
    Continuous,
    Dim,
    Value,
    car_index,
    read_categorical,
    read_continuous_or_values,
    read_typed,
)
from falsify.world.space_files import RealScan, UserCar, read_real_backgrounds, read_user_cars

# The dims' and files' names callers import from here stay importable from here.
__all__ = [
    "DEFAULT_THRESHOLD", "EFFECT_DIMS", "IMAGE_ONLY", "CarPose", "Categorical", "Continuous",
    "Dim", "RealScan", "Sample", "Space", "UserCar", "Value", "car_index", "load_space",
    "parse_space",
]

TOP_KEYS = {"name", "description", "sensor", "seed", "threshold", "dims", "car_models", "actors"}
MAX_CARS = 8
DEFAULT_THRESHOLD = 0.65   # mIoU below which a cell is a blind spot (the paper's)


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
    def lidar_values(self) -> tuple[tuple[str, Value], ...]:
        """The values the LiDAR scan reads: all but the camera-only dims, so those dims never
        change a scan's random draws."""
        return tuple((k, v) for k, v in self.values if k not in IMAGE_ONLY)

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
    # The world profile our streets are built from (`[dims.background] world = "NAME"`, a
    # profile written by `falsify fit-world`, or its path); "" is the streets as built.
    world: str = ""

    def background_source(self):
        """What a Simulator builds this space's streets with (None: the streets as built);
        ConfigError names the world key when its profile cannot be read."""
        if not self.world:
            return None
        from falsify.world.profile import load_profile

        try:
            return load_profile(self.world).background_source()
        except ConfigError as exc:
            raise ConfigError(f"{self.source}: dims.background.world: {exc}") from None

    def street(self, bg_id: int):
        """Street `bg_id` as this space builds it (its world's, or as built)."""
        from falsify.world.streets import build_background

        return (self.background_source() or build_background)(int(bg_id))

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
        """How a report names a background: the real scan's name, else the street's id and,
        in a world of places, the place it stands for."""
        if self.real_backgrounds:
            return self.real_backgrounds[int(bg)].name
        place = self.background_place(bg)
        return f"street {int(bg)}" + (f" ({place})" if place else "")

    def background_place(self, bg: int) -> str | None:
        """The real place a background is (a real scan's name) or stands for (a street's place
        in a world of places); None for a street of no place, or whose profile has gone."""
        if self.real_backgrounds:
            return self.real_backgrounds[int(bg)].name
        if not self.world:
            return None
        from falsify.world.profile import load_profile

        try:
            return load_profile(self.world).place_name(int(bg))
        except ConfigError:
            return None

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



def load_space(path: str | Path, builtin_cars: tuple[str, ...] | None = None) -> Space:
    """Read and validate a space config (a file, or a bundled config by its name); every problem
    names its key and the allowed values."""
    path = config_path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such config; give a TOML file or a bundled config: "
                          f"{', '.join(bundled_configs())}")
    text = read_bytes(path, "config", ConfigError)
    raw = parse_toml(text, path, error=ConfigError)
    space = parse_space(raw, source=str(path), base_dir=path.parent,
                        config_hash=hashlib.sha256(text).hexdigest(), builtin_cars=builtin_cars)
    # Files beside the config that change what is scored make another space (--resume and
    # gate baselines compare the hash); a config naming none keeps its bytes' hash.
    parts: list[bytes] = []
    if space.sensor.endswith(".toml"):   # a user's sensor: another file casts other scans
        parts.append(sensor_digest(space.sensor, ConfigError).encode())
    for name, car in sorted(space.user_cars.items()):   # a changed mesh is another object
        if car.file.is_file():   # a missing one is named where the meshes are checked
            parts += [name.encode(), read_bytes(car.file, "mesh", ConfigError)]
    if space.world:   # a changed profile builds other streets
        from falsify.world.profile import profile_file

        space.background_source()
        parts.append(read_bytes(profile_file(space.world), "world profile", ConfigError))
    else:   # changed real scans
        parts += [read_bytes(f, "real background", ConfigError)
                  for r in space.real_backgrounds for f in (r.bin, r.label) if f is not None]
    if not parts:
        return space
    digest = hashlib.sha256(space.config_hash.encode())
    for part in parts:
        digest.update(part)
    return replace(space, config_hash=digest.hexdigest())


def parse_space(raw: dict[str, Any], source: str = "<config>", base_dir: Path | None = None,
                config_hash: str = "", builtin_cars: tuple[str, ...] | None = None,
                real_backgrounds: tuple[RealScan, ...] | None = None) -> Space:
    """Validate a parsed config dict into a Space; `real_backgrounds`, when given, are the real
    scans a run recorded, used instead of looking for them again (a run's data may move)."""
    if builtin_cars is None:
        from falsify.world.cars import BUILTIN_MODELS
        builtin_cars = BUILTIN_MODELS
    where = f"{source}: "
    name, sensor, seed, threshold = _top_keys(raw, source, where)
    if sensor.endswith(".toml") and base_dir is not None and (base_dir / sensor).is_file():
        sensor = str((base_dir / sensor).resolve())   # beside the config, as its meshes are

    from falsify.world.actors import ACTOR_NAMES
    user_cars = read_user_cars(raw.get("car_models", {}), where, base_dir or Path("."),
                               (*builtin_cars, *ACTOR_NAMES))
    user_cars |= read_user_cars(raw.get("actors", {}), where, base_dir or Path("."),
                                (*builtin_cars, *ACTOR_NAMES, *user_cars), table="actors")
    models = (*builtin_cars, *ACTOR_NAMES, *user_cars)

    dims_raw, model_dim = _dims_table(raw, where)
    count = read_categorical("count", dims_raw["count"], where, int)
    for c in count.values:
        if not 1 <= int(c) <= MAX_CARS:
            raise ConfigError(f"{where}dims.count: {c} must be between 1 and {MAX_CARS}")
    max_count = max(int(c) for c in count.values)
    _check_dim_names(dims_raw, model_dim, max_count, where)

    dims, surfaces = _object_dims(dims_raw, model_dim, max_count, models, where)
    dims["count"] = count
    bg, real, world = _background_dim(dims_raw["background"], where, base_dir, real_backgrounds)
    dims["background"] = bg
    for image_dim in IMAGE_ONLY:
        if image_dim in dims_raw:
            dims[image_dim] = read_categorical(image_dim, dims_raw[image_dim], where, str)
    for effect in EFFECT_DIMS:
        if effect in dims_raw:
            dims[effect] = read_continuous_or_values(effect, dims_raw[effect], where)
    _check_labelled(surfaces, real, model_dim, where)
    return Space(name=name, sensor=sensor, seed=seed, threshold=threshold, dims=dims,
                 user_cars=user_cars, source=source, config_hash=config_hash,
                 real_backgrounds=real, world=world,
                 surfaces=tuple(surfaces) if any(on != "any" for on in surfaces) else ())


def _top_keys(raw: dict[str, Any], source: str, where: str) -> tuple[str, str, int, float]:
    """The config's name, sensor, seed and threshold; ConfigError names an unknown top-level
    key or a value out of range."""
    extra = sorted(set(raw) - TOP_KEYS)
    if extra:
        raise ConfigError(f"{where}unknown key {extra[0]!r}; allowed: "
                          f"{', '.join(sorted(TOP_KEYS))}")
    name = read_typed(raw, "name", str, where, default=Path(source).stem)
    sensor = read_typed(raw, "sensor", str, where, default="kitti-hdl64e-front")
    seed = read_typed(raw, "seed", int, where, default=0)
    if not 0 <= seed <= SEED_MAX:
        raise ConfigError(f"{where}seed: {seed} must be between 0 and {SEED_MAX}")
    threshold = float(read_typed(raw, "threshold", (int, float), where, default=DEFAULT_THRESHOLD))
    if not 0.0 < threshold <= 1.0:
        raise ConfigError(f"{where}threshold: {threshold} must be in (0, 1]")
    return name, sensor, seed, threshold


def _dims_table(raw: dict[str, Any], where: str) -> tuple[dict[str, Any], str]:
    """The [dims] table, yaw and count defaulted, and the name of object 1's model dim (actor,
    or car_model in older configs); ConfigError names a missing required dim."""
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
    return dims_raw, model_dim


def _check_dim_names(dims_raw: dict[str, Any], model_dim: str, max_count: int,
                     where: str) -> None:
    """ConfigError naming a dim that a space of up to `max_count` objects cannot have."""
    allowed = {model_dim, *CONTINUOUS_BASE, "count", "background", *IMAGE_ONLY, *EFFECT_DIMS}
    for k in range(2, max_count + 1):
        allowed |= {f"{model_dim}_{k}", *(f"{b}_{k}" for b in CONTINUOUS_BASE)}
    unknown = sorted(set(dims_raw) - allowed)
    if unknown:
        raise ConfigError(f"{where}unknown dim dims.{unknown[0]}; allowed: "
                          f"{', '.join(sorted(allowed))}")


def _object_dims(dims_raw: dict[str, Any], model_dim: str, max_count: int,
                 models: tuple[str, ...], where: str) -> tuple[dict[str, Dim], list[str]]:
    """Each object's model dim (values among `models`) and its x, y, yaw, object k's tables
    defaulting to object 1's, and where each object must stand."""
    dims: dict[str, Dim] = {}
    surfaces: list[str] = []
    for k in range(1, max_count + 1):
        sfx = "" if k == 1 else f"_{k}"
        spec = dims_raw.get(model_dim + sfx, dims_raw[model_dim])
        on, spec = _surface(spec, f"{where}dims.{model_dim}{sfx}")
        surfaces.append(on)
        dim = read_categorical(model_dim + sfx, spec, where, str)
        for v in dim.values:
            if v not in models:
                what = "car model" if model_dim == "car_model" else "actor"
                raise ConfigError(f"{where}dims.{model_dim}{sfx}: unknown {what} {v!r}; "
                                  f"allowed: {', '.join(models)}")
        dims[model_dim + sfx] = dim
        for base in CONTINUOUS_BASE:
            spec = dims_raw.get(base + sfx, dims_raw[base])
            dims[base + sfx] = read_continuous_or_values(base + sfx, spec, where)
    return dims, surfaces


def _background_dim(bg_raw: Any, where: str, base_dir: Path | None,
                    real_backgrounds: tuple[RealScan, ...] | None
                    ) -> tuple[Categorical, tuple[RealScan, ...], str]:
    """The background dim, its real scans and its world: indices into `real = [...]` (or into
    the `real_backgrounds` a run recorded), else street ids with no scans, built from the
    world profile `world = "NAME"` names (its path resolved against the config's folder)."""
    from falsify.world.streets import MAX_BACKGROUND_ID

    if isinstance(bg_raw, dict) and "real" in bg_raw:
        if "world" in bg_raw:
            raise ConfigError(f"{where}dims.background.world: builds our streets; real scans "
                              "take no world (drop one of world and real)")
        real = (real_backgrounds if real_backgrounds is not None
                else read_real_backgrounds(bg_raw, where, base_dir or Path(".")))
        return Categorical("background", tuple(range(len(real)))), real, ""
    world = ""
    if isinstance(bg_raw, dict) and "world" in bg_raw:
        bg_raw = dict(bg_raw)
        world = bg_raw.pop("world")
        if not isinstance(world, str) or not world:
            raise ConfigError(f"{where}dims.background.world: {world!r} is not a world "
                              "profile's name or path (configs/worlds/NAME.json, or a file "
                              "written by `falsify fit-world`)")
        local = (base_dir or Path(".")) / world
        if world.endswith(".json") and local.is_file():
            world = str(local.resolve())
    bg = read_categorical("background", bg_raw, where, int)
    for v in bg.values:
        if not 0 <= int(v) <= MAX_BACKGROUND_ID:
            raise ConfigError(f"{where}dims.background: unknown background {v}; allowed: "
                              f"integer ids 0..{MAX_BACKGROUND_ID}, or real = [KITTI .bin "
                              "scans, folders or SemanticKITTI sequences]")
    return bg, (), world


def _check_labelled(surfaces: list[str], real: tuple[RealScan, ...], model_dim: str,
                    where: str) -> None:
    """ConfigError where an object must stand on road or sidewalk on a real background without
    SemanticKITTI labels to say where they are."""
    if any(on != "any" for on in surfaces):
        unlabelled = [r.name for r in real if r.kind != "semantickitti"]
        if unlabelled:
            on = next(on for on in surfaces if on != "any")
            raise ConfigError(f"{where}dims.{model_dim}.on: {on!r} reads where the road "
                              f"and sidewalk are from SemanticKITTI labels; background "
                              f"{unlabelled[0]!r} has none (use on = \"any\")")


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
