"""A plain install has no torch (scoring, reports and the gate need none): each command that
trains, exports or runs the torch backend says so before any work, exit 2, and writes nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from falsify.models.runners import WEIGHTS_DIR
from falsify.paths import CONFIGS
from tests.conftest import NO_TORCH

SMOKE = str(CONFIGS / "smoke.toml")
PT = str(WEIGHTS_DIR / "squeezeseg.pt")
NO_TORCH_MAIN = (NO_TORCH + "from falsify.cli import main\n"
                 "sys.exit(main(sys.argv[1:]))\n")


def _without_torch(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", NO_TORCH_MAIN, *argv], capture_output=True,
                          text=True, cwd=cwd, timeout=120)


@pytest.mark.parametrize(("argv", "what"), [
    (["train", "--data", "scans", "--out", "out"], "falsify train"),
    (["train-pointnet", "--data", "scans", "--out", "out"], "falsify train-pointnet"),
    (["adjust", PT, "--val", "scans", "--out", "out/adjusted.pt"], "falsify adjust"),
    (["export", PT, "--out", "out/net.onnx"], "falsify export"),
    (["retrain", SMOKE, "--out", "out", "--model", "squeezeseg", "--train-data", "scans",
      "--validation-backgrounds", "0", "--retraining-backgrounds", "1"], "falsify retrain"),
    (["grid", SMOKE, "--out", "out", "--backend", "torch", "--quiet"], "--backend torch"),
    (["predict", "scans", "--backend", "torch", "--out", "out"], "--backend torch"),
])
def test_a_command_that_needs_torch_says_so_and_writes_nothing(tmp_path, argv, what):
    (tmp_path / "scans").mkdir()   # one blank scan: retrain checks its inputs first
    np.save(tmp_path / "scans" / "000000.npy", np.zeros((64, 512, 6), np.float32))
    r = _without_torch(argv, tmp_path)
    assert r.returncode == 2, r.stderr
    [line] = r.stderr.strip().splitlines()   # one line, no traceback
    assert line.startswith(f"falsify: error: {what}") and "needs torch" in line, line
    assert "No module named 'torch'" in line and 'pip install "falsify[torch]"' in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scans"]   # nothing written


def test_their_help_needs_no_torch(tmp_path):
    """The check is the command's, not the parser's: --help works without torch."""
    r = _without_torch(["train", "--help"], tmp_path)
    assert r.returncode == 0 and "--data" in r.stdout, r.stderr
