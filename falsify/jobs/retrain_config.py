"""The configs a retraining experiment derives from the user's: the background ids of V and R
as given on the command line, and the same space over either set only, written back as TOML."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from falsify.errors import ConfigError
from falsify.fileio import parse_toml, read_bytes
from falsify.world.space import RealScan


def parse_ids(text: str, option: str) -> tuple[int, ...]:
    """'0-6' or '0,2,4' or '0-3,9' -> sorted unique ids; ConfigError naming the option."""
    ids: set[int] = set()
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part[1:]:
                a, b = part.split("-", 1)
                lo, hi = int(a), int(b)
                if hi < lo:
                    raise ValueError
                ids.update(range(lo, hi + 1))
            else:
                ids.add(int(part))
    except ValueError:
        raise ConfigError(f"{option} {text!r}: expected background ids like 0-6 or 0,2,4") \
            from None
    if not ids or min(ids) < 0:
        raise ConfigError(f"{option} {text!r}: expected non-negative background ids like 0-6")
    return tuple(sorted(ids))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write config value {v!r}")


def toml_text(raw: dict, prefix: str = "") -> str:
    """A parsed config written back as TOML (scalars, lists and nested tables only)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in raw.items() if not isinstance(v, dict)]
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in raw.items():
        if isinstance(v, dict):
            name = f"{prefix}{k}"
            inner = toml_text(v, name + ".")
            if any(not isinstance(x, dict) for x in v.values()) or not v:
                out += f"\n[{name}]\n"
            out += inner
    return out


def subset_config(config: Path, backgrounds: Sequence[int], suffix: str,
                  real: Sequence[RealScan] = ()) -> str:
    """The config's text with its background dim replaced by `backgrounds` (paths absolute), its
    streets' world kept; for a space of real scans (`real`, its scans), the scans of those
    backgrounds and its `labels` (whether scans without labels may be among them)."""
    raw = parse_toml(read_bytes(config, "config"), config)
    raw["name"] = f"{raw.get('name', config.stem)}-{suffix}"
    before = raw["dims"]["background"]
    raw["dims"]["background"] = (
        {"real": [str(real[b].bin.resolve()) for b in backgrounds]} if real
        else {"values": list(backgrounds)})
    if real and isinstance(before, dict) and "labels" in before:   # scans without labels allowed
        raw["dims"]["background"]["labels"] = before["labels"]
    if not real and isinstance(before, dict) and "world" in before:
        # the subset's streets are the run's: its world, a file beside the config made absolute
        world, local = before["world"], config.parent / str(before["world"])
        raw["dims"]["background"]["world"] = (str(local.resolve()) if str(world).endswith(
            ".json") and local.is_file() else world)
    for spec in raw.get("car_models", {}).values():
        if isinstance(spec, dict) and "file" in spec and not Path(spec["file"]).is_absolute():
            spec["file"] = str((config.parent / spec["file"]).resolve())
    return toml_text(raw)
