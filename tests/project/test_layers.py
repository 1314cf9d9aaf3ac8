"""Layers look only down, by folder, and no module depends on itself through others.

A layer is a list of folders; a module's layer is its folder's. A new folder of Python files
must be placed here before this test passes. Imports inside functions and under TYPE_CHECKING
count too: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# The folders that install as falsify.NAME (pyproject's package-dir) besides falsify/ itself.
TOP = ("sampler", "models", "reports", "configs")

# Lowest first. A module may import from its own layer and the layers before it.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base: errors, class ids, atomic files, paths, argument checks, rotations", ("falsify",)),
    ("images: PNG, scan pictures, overlays", ("falsify/images",)),
    ("world: the space, meshes, streets, materials", ("falsify/world",)),
    ("sensor: LiDAR, ray casting, returns, scans, simulator, camera", ("falsify/sensor",)),
    ("data: formats on disk, scan sets, training scenes", ("falsify/data",)),
    ("results: metrics, store, maps, replay; samplers", ("falsify/results", "sampler")),
    ("network: SqueezeSeg, its spec, runners, export, training", ("models",)),
    ("drawing: HTML renderers", ("reports",)),
    ("executors: evaluator, driver, processes, Ray", ("falsify/executors",)),
    ("jobs: run, gate, report, predict, realism, retrain, calib, fits", ("falsify/jobs",)),
    ("bench: benchmarks and the trade-off", ("falsify/bench",)),
    ("command line", ("falsify/cli", "falsify/__main__")),
)
FOLDERS = {f: i for i, (_, folders) in enumerate(LAYERS) for f in folders}


def folder_of_file(path: Path) -> str:
    """The layer key of a source file: its folder (a family's subfolder, such as
    models/runners, counts as its parent's), or falsify/__main__ for that one file."""
    rel = path.relative_to(ROOT)
    if rel.as_posix() == "falsify/__main__.py":
        return "falsify/__main__"
    parts = rel.parent.parts
    return "/".join(parts[:2] if parts[0] == "falsify" else parts[:1])


def module_of_file(path: Path) -> str:
    """The installed dotted name of a source file (sampler/grid.py is falsify.sampler.grid)."""
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts if parts[0] == "falsify" else ["falsify", *parts])


def folder_of_module(name: str) -> str | None:
    """The layer key of an imported dotted name; None for third-party modules."""
    parts = name.split(".")
    if parts[0] in TOP:   # the source-checkout spelling of falsify.sampler etc.
        parts = ["falsify", *parts]
    if parts[0] != "falsify":
        return None
    if len(parts) == 1:
        return "falsify"
    if parts[1] in TOP:
        return parts[1]
    if parts[1] == "__main__":
        return "falsify/__main__"
    sub = ROOT / "falsify" / parts[1]
    return f"falsify/{parts[1]}" if sub.is_dir() else "falsify"


def sources() -> list[Path]:
    out = sorted((ROOT / "falsify").rglob("*.py"))
    for top in TOP:
        out += sorted((ROOT / top).rglob("*.py"))
    return [p for p in out if "__pycache__" not in p.parts]


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every import in the file, wherever it stands (in a function, under
    `if TYPE_CHECKING:`); `from falsify.world import shapes` counts as an import of
    falsify.world.shapes."""
    out = []
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.lineno, node.module))
            out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


def known_modules() -> set[str]:
    return {module_of_file(p) for p in sources()}


def module_deps() -> dict[str, set[str]]:
    """Each of our modules -> the modules of ours it imports (a package's __init__ counts)."""
    known = known_modules()
    deps: dict[str, set[str]] = {}
    for path in sources():
        me = module_of_file(path)
        got = set()
        for _, name in imports(path):
            parts = name.split(".")
            if parts[0] in TOP:
                parts = ["falsify", *parts]
            full = ".".join(parts)
            if full in known and full != me:
                got.add(full)
        deps[me] = got
    return deps


def test_every_folder_has_a_layer():
    missing = sorted({folder_of_file(p) for p in sources()} - set(FOLDERS))
    assert not missing, f"place these folders in tests/project/test_layers.py LAYERS: {missing}"


@pytest.mark.parametrize("path", sources(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_imports_look_only_down(path):
    here = folder_of_file(path)
    mine = FOLDERS[here]
    upward = []
    for line, name in imports(path):
        there = folder_of_module(name)
        if there is None or there not in FOLDERS:
            continue
        if FOLDERS[there] > mine:
            upward.append(f"{path.relative_to(ROOT)}:{line} imports {name} "
                          f"({LAYERS[FOLDERS[there]][0]}) from {LAYERS[mine][0]}")
    assert not upward, "\n".join(upward)


def cycles(deps: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(deps.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(deps):
        if v not in index:
            visit(v)
    return sorted(out)


def test_no_import_cycle_between_modules():
    """Lazy imports inside functions count, and so do imports for annotations only
    (`if TYPE_CHECKING:`): a cycle through them is still two modules that need each other."""
    found = cycles(module_deps())
    assert not found, f"import cycles: {found}"


def test_no_import_cycle_between_folders():
    """Folders of one layer (results and sampler) may use each other only one way."""
    by_folder: dict[str, set[str]] = {}
    for path in sources():
        here = folder_of_file(path)
        for _, name in imports(path):
            there = folder_of_module(name)
            if there is not None and there != here:
                by_folder.setdefault(here, set()).add(there)
    assert not cycles(by_folder), cycles(by_folder)


def test_the_checkers_see_an_upward_import_and_a_cycle(tmp_path):
    bad = tmp_path / "x.py"
    bad.write_text("def f():\n    from falsify.jobs.run import execute\n")
    names = [n for _, n in imports(bad)]
    assert "falsify.jobs.run" in names
    typed = tmp_path / "t.py"
    typed.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                     "    from falsify.sensor.render import CameraRenderer\n")
    assert "falsify.sensor.render" in [n for _, n in imports(typed)]
    assert FOLDERS[folder_of_module("falsify.jobs.run")] > FOLDERS["models"]
    assert folder_of_module("falsify.errors") == "falsify"
    assert folder_of_module("sampler.grid") == "sampler"
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_renderers_neither_cast_nor_infer():
    """The HTML renderers draw what they are handed: no scene, sensor, replay or network."""
    for path in (ROOT / "reports").rglob("*.py"):
        for line, name in imports(path):
            bad = (name.startswith(("falsify.sensor", "falsify.models", "models.",
                                    "falsify.results.replay", "falsify.world.streets",
                                    "falsify.world.cars", "falsify.executors")))
            assert not bad, f"{path.relative_to(ROOT)}:{line} imports {name}"
