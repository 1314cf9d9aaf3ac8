"""Layers look only down: no module imports from a layer above its own (read from the source).

Every module of the package is placed in exactly one layer below; a new module must be placed
here before this test passes. Imports inside functions and under TYPE_CHECKING count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("falsify", "models", "sampler", "reports")

# Lowest first. A module may import from its own layer and the layers before it.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base: errors, class ids, atomic files", (
        "falsify/__init__", "falsify/errors", "falsify/classes", "falsify/fileio",
        "falsify/paths", "falsify/checks")),
    ("world: space, meshes, streets, sensor, casting, scans, metrics", (
        "falsify/space", "falsify/shapes", "falsify/cars", "falsify/backgrounds",
        "falsify/sensor", "falsify/raycast", "falsify/materials", "falsify/terrain",
        "falsify/vegetation", "falsify/structures", "falsify/road_users", "falsify/fit_returns",
        "falsify/fit_rings",
        "falsify/scan", "falsify/kitti", "falsify/scene",
        "falsify/dataset", "falsify/preview", "falsify/metrics", "falsify/kitti_frames",
        "falsify/scansets", "falsify/calibration", "falsify/camera", "falsify/kitti_object",
        "falsify/kitti_export", "falsify/overlay", "falsify/pngread", "falsify/traffic")),
    ("network: SqueezeSeg, its spec, runners, export, training", (
        "models/*",)),
    ("results: maps, the store and its reader, replay, samplers", (
        "falsify/maps", "falsify/store", "falsify/replay", "sampler/*")),
    ("drawing: HTML renderers", (
        "reports/*",)),
    ("jobs: runs, pipeline, gate, report, trade-off, bench, presets", (
        "falsify/pipeline", "falsify/cluster", "falsify/runs", "falsify/gate",
        "falsify/reporting",
        "falsify/tradeoff", "falsify/bench", "falsify/fidelity", "falsify/evaluation",
        "falsify/realism", "falsify/calib_check", "falsify/bench_camera", "falsify/retrain",
        "falsify/bench_machine")),
    ("command line", (
        "falsify/cli", "falsify/camera_cli")),
)


def layer_of(key: str) -> int:
    """The layer index of a module key such as "falsify/store" or "models/runner"."""
    for i, (_, members) in enumerate(LAYERS):
        for m in members:
            if m == key or (m.endswith("/*") and key.startswith(m[:-1])):
                return i
    raise KeyError(key)


def key_of(module: str) -> str | None:
    """Our module key for an imported dotted name (falsify.models.x and models.x alike);
    None for third-party modules."""
    parts = module.split(".")
    if parts[0] == "falsify" and len(parts) > 1 and parts[1] in PACKAGES[1:]:
        parts = parts[1:]
    if parts[0] not in PACKAGES:
        return None
    if len(parts) == 1:
        return f"{parts[0]}/__init__"
    return f"{parts[0]}/{parts[1]}"


def modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).glob("*.py"))


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every import in the file, wherever it stands."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.lineno, node.module))
            for a in node.names:   # `from falsify import shapes` imports falsify.shapes
                sub = key_of(f"{node.module}.{a.name}")
                if sub not in (None, key_of(node.module)) and (ROOT / f"{sub}.py").exists():
                    out.append((node.lineno, f"{node.module}.{a.name}"))
    return out


def test_every_module_has_a_layer():
    missing = []
    for path in modules():
        key = f"{path.parent.name}/{path.stem}"
        try:
            layer_of(key)
        except KeyError:
            missing.append(key)
    assert not missing, f"place these modules in tests/test_layers.py LAYERS: {missing}"


@pytest.mark.parametrize("path", modules(), ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_imports_look_only_down(path):
    here = f"{path.parent.name}/{path.stem}"
    mine = layer_of(here)
    upward = []
    for line, name in imports(path):
        key = key_of(name)
        if key is None or key == here:
            continue
        theirs = layer_of(key)
        if theirs > mine:
            upward.append(f"{here}.py:{line} imports {name} ({LAYERS[theirs][0]}) from "
                          f"{LAYERS[mine][0]}")
    assert not upward, "\n".join(upward)


def test_the_checker_sees_an_upward_import(tmp_path):
    bad = tmp_path / "models" / "x.py"
    bad.parent.mkdir()
    bad.write_text("def f():\n    from falsify.runs import execute\n")
    assert [key_of(n) for _, n in imports(bad)] == ["falsify/runs"]
    assert layer_of("falsify/runs") > layer_of("models/x")


def test_the_renderers_neither_cast_nor_infer():
    """The HTML renderers draw what they are handed: no scene, sensor, replay or network."""
    banned = ("falsify/scene", "falsify/raycast", "falsify/sensor", "falsify/replay",
              "falsify/backgrounds", "falsify/cars")
    for path in (ROOT / "reports").glob("*.py"):
        for line, name in imports(path):
            key = key_of(name) or ""
            assert key not in banned and not key.startswith("models/"), \
                f"reports/{path.name}:{line} imports {name}"
