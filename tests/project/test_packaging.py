"""Every package folder ships: pyproject's explicit package list names each folder that holds an
`__init__.py` (the slow wheel test would find a missing one only after a build)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TOP = ("sampler", "models", "reports", "configs")


def test_every_package_folder_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
                 ["packages"])
    found = set()
    for top in ("falsify", *TOP):
        for init in (ROOT / top).rglob("__init__.py"):
            parts = init.parent.relative_to(ROOT).parts
            found.add(".".join(parts if parts[0] == "falsify" else ("falsify", *parts)))
    assert found - listed == set(), f"add to pyproject's packages: {sorted(found - listed)}"
    data_only = {"falsify.configs"}   # TOML and JSON, no Python
    assert listed - found == data_only, f"listed but not a package: {sorted(listed - found)}"
