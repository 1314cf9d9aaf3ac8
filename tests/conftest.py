"""Shared fixtures: repo paths, the real KITTI data folder (skipped with a message if absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

from falsify.scansets import KITTI_DIR as KITTI

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"


@pytest.fixture
def kitti_dir() -> Path:
    if not (KITTI / "squeezeseg").is_dir():
        pytest.skip(f"real KITTI scans not found at {KITTI} (shared/data/ is beside the repo)")
    return KITTI
