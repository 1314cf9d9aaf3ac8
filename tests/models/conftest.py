"""Scans the training tests share: 64 x 64 crops of plausible scans (the centre columns, where
the cars are; labels 0..3, valid for both label sets)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.models.plausible import plausible_scans


def write_crops(folder: Path, n: int, seed: int, name: str = "scan_{i}.npy") -> Path:
    """`n` crops into `folder`, each named by `name`."""
    for i, s in enumerate(plausible_scans(n, 64, 512, seed=seed)):
        np.save(folder / name.format(i=i), np.ascontiguousarray(s[:, 224:288]))
    return folder


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """Four crops: a training set small enough for a step a second."""
    return write_crops(tmp_path_factory.mktemp("scans"), 4, seed=11)


@pytest.fixture(scope="module")
def val(tmp_path_factory) -> Path:
    """Two crops of other scenes than `data`'s: validation scans apart from the training's."""
    return write_crops(tmp_path_factory.mktemp("val"), 2, seed=12)


def copy_of(data: Path, folder: Path, labels: str | None = None) -> Path:
    """The scans of `data` copied into `folder`, with an index.json naming `labels` if given."""
    folder.mkdir()
    for f in data.glob("*.npy"):
        (folder / f.name).write_bytes(f.read_bytes())
    if labels is not None:
        (folder / "index.json").write_text(json.dumps({"scans": 4, "labels": labels}))
    return folder
