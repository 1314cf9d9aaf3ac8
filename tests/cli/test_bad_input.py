"""Bad input, tried as a new user would: exit 2, one line naming the key or file, nothing written.

Each case is one line of CASES: the command line (run as a subprocess in a scratch directory
holding the files SETUP makes), and a word the message must contain. The scratch directory must
hold exactly what it held before the command ran.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
SMOKE = (ROOT / "configs" / "smoke.toml").read_text()


def config(**replace: str) -> str:
    """smoke.toml with some of its lines replaced (key: the line's start, value: the new line)."""
    lines = SMOKE.splitlines()
    for start, new in replace.items():
        lines = [new if line.startswith(start) else line for line in lines]
    return "\n".join(lines) + "\n"


def dims(extra: str, text: str = SMOKE) -> str:
    """The config with a [dims.*] table replaced by `extra` (its first line names the table)."""
    head = extra.splitlines()[0]
    out, skip = [], False
    for line in text.splitlines():
        if line.startswith("["):
            skip = line == head
            if skip:
                out.append(extra)
                continue
        if not skip:
            out.append(line)
    return "\n".join(out) + "\n"


MESH_CAR = SMOKE.replace('[dims.car_model]\nvalues = ["sedan"]', '[car_models.mine]\n'
                         'file = "{file}"\n\n[dims.car_model]\nvalues = ["mine"]')

def npy_bytes(a: np.ndarray) -> bytes:
    """An array as the bytes of its .npy file."""
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


SETUP = {   # file name: content (bytes or str); made in the scratch directory before each case
    "afile": "not a directory\n",
    "empty.npy": b"",
    "empty.bin": b"",
    "nan.bin": np.full((100, 4), np.nan, np.float32).tobytes(),
    "text.npy": b"\x93NUMPY garbage",
    "badlab.npy": npy_bytes(np.concatenate([np.ones((8, 16, 5), np.float32),
                                            np.full((8, 16, 1), 7, np.float32)], axis=2)),
    "yaw720.toml": dims("[dims.yaw]\nmin = 0.0\nmax = 720.0\nstep = 90.0"),
    "far.toml": dims("[dims.x]\nvalues = [1e9]"),
    "seedneg.toml": config(seed="seed = -1"),
    "seed64.toml": config(seed=f"seed = {2**64 - 1}"),
    "huge.toml": dims("[dims.x]\nmin = -500.0\nmax = 500.0\nstep = 0.001"),
    "biggrid.toml": dims("[dims.y]\nmin = 0.0\nmax = 999.0\nstep = 1.0",
                         dims("[dims.x]\nmin = -500.0\nmax = 500.0\nstep = 1.0")),
    "bgs.toml": dims("[dims.background]\nrange = [0, 1000000000]"),
    "nomesh.toml": MESH_CAR.format(file="missing.glb"),
    "bytes.glb": os.urandom(512),
    "bytesmesh.toml": MESH_CAR.format(file="bytes.glb"),
    "notmesh.obj": "this is not a mesh\n",
    "notmesh.toml": MESH_CAR.format(file="notmesh.obj"),
    "run/results.sqlite": b"SQLite format 3\x00" + b"\x00" * 84,   # truncated: header only
}

# `falsify retrain` on the smoke config, V = background 0, R = background 1 (add --out)
RETRAIN = ["retrain", "SMOKE", "--model", "squeezeseg", "--train-data", "afile",
           "--validation-backgrounds", "0", "--retraining-backgrounds", "1"]

CASES = [   # (id, command line after `falsify`, a word the message must name)
    ("grid --out is a file", ["grid", "SMOKE", "--out", "afile"], "--out afile"),
    ("grid --out under a file", ["grid", "SMOKE", "--out", "afile/run"], "--out afile/run"),
    ("scan --out is a file", ["scan", "SMOKE", "--out", "afile"], "--out afile"),
    ("scan --out under a file", ["scan", "SMOKE", "--out", "afile/x"], "--out afile/x"),
    ("predict --out is a file", ["predict", "nan.bin", "--out", "afile"], "--out afile"),
    ("dataset --out under a file", ["dataset", "SMOKE", "--scans", "1", "--out", "afile/d"],
     "--out afile/d"),
    ("tradeoff --out is a file", ["tradeoff", "SMOKE", "--out", "afile"], "--out afile"),
    ("report --out under a file", ["report", "run", "--out", "afile/r.html"], "afile"),
    ("report --out a folder's name", ["report", "run", "--out", "pages/"],
     "--out pages/: names a folder; give a file name"),
    ("scan --out on a read-only file system", ["scan", "SMOKE", "--out", "/proc/falsify-out"],
     "/proc/falsify-out"),
    ("grid --out on a read-only file system", ["grid", "SMOKE", "--out", "/proc/falsify-run"],
     "/proc/falsify-run"),
    ("predict an empty .npy", ["predict", "empty.npy", "--out", "p"], "empty.npy"),
    ("predict a .npy that is not one", ["predict", "text.npy", "--out", "p"], "text.npy"),
    ("predict an empty .bin", ["predict", "empty.bin", "--out", "p"], "empty.bin"),
    ("predict a .bin of NaN", ["predict", "nan.bin", "--out", "p"], "nan.bin"),
    ("predict a .npy whose labels are no class", ["predict", "badlab.npy", "--out", "p"],
     "badlab.npy: label channel holds 7"),
    ("bench model --samples 0", ["bench", "model", "--samples", "0"], "--samples"),
    ("calib --scenes --samples 0", ["calib", "--scenes", "SMOKE", "--samples", "0"],
     "--samples: 0: allowed 1..1000000"),
    ("bench model --calibration-scans 0", ["bench", "model", "--calibration-scans", "0"],
     "--calibration-scans"),
    ("tradeoff --threads 0", ["tradeoff", "SMOKE", "--out", "t", "--threads", "0"],
     "--threads: 0: allowed 1..64"),
    ("bench pipeline --workers 0", ["bench", "pipeline", "--workers", "0"], "--workers"),
    ("bench scan --samples -1", ["bench", "scan", "--samples", "-1"], "--samples"),
    ("search --seed -1", ["search", "SMOKE", "--algorithm", "random", "--budget", "2",
                          "--seed", "-1", "--out", "r"], "--seed"),
    ("grid --seed 2^64", ["grid", "SMOKE", "--seed", str(2**64), "--out", "r"], "--seed"),
    ("search --budget 1e12", ["search", "SMOKE", "--algorithm", "random", "--budget",
                              str(10**12), "--out", "r"], "--budget"),
    ("search level-set without a budget beyond --max-samples",
     ["search", "SMOKE", "--algorithm", "level-set", "--max-samples", "4", "--out", "r"],
     "--max-samples: level-set without --budget may score the whole grid, 8 samples"),
    ("bench scan --samples 1e9", ["bench", "scan", "--samples", str(10**9)], "--samples"),
    ("grid --workers 0", ["grid", "SMOKE", "--workers", "0", "--out", "r"], "--workers"),
    ("dataset --seed -1", ["dataset", "SMOKE", "--scans", "1", "--seed", "-1", "--out", "d"],
     "--seed"),
    ("config seed -1", ["grid", "seedneg.toml", "--out", "r"], "seed"),
    ("config seed 2^64", ["grid", "seed64.toml", "--out", "r"], "seed"),
    ("yaw beyond one turn", ["grid", "yaw720.toml", "--out", "r"], "dims.yaw"),
    ("a car 1e9 m away", ["grid", "far.toml", "--out", "r"], "dims.x"),
    ("a step making 1e6 values", ["grid", "huge.toml", "--out", "r"], "dims.x"),
    ("a grid of 2e6 samples", ["grid", "biggrid.toml", "--out", "r"], "--max-samples"),
    ("tradeoff on a 2e6 grid", ["tradeoff", "biggrid.toml", "--out", "t"], "biggrid.toml"),
    ("bench scan on a 2e6 grid", ["bench", "scan", "--config", "biggrid.toml"], "biggrid.toml"),
    ("1e9 backgrounds", ["grid", "bgs.toml", "--out", "r"], "dims.background"),
    ("user mesh missing", ["grid", "nomesh.toml", "--out", "r"], "missing.glb"),
    ("user mesh random bytes", ["grid", "bytesmesh.toml", "--out", "r"], "bytes.glb"),
    ("user mesh not a mesh", ["grid", "notmesh.toml", "--out", "r"], "notmesh.obj"),
    ("scan with a missing mesh", ["scan", "nomesh.toml", "--out", "s"], "missing.glb"),
    ("gate on a truncated store", ["gate", "run"], "results.sqlite"),
    ("report on a truncated store", ["report", "run"], "results.sqlite"),
    ("dataset --traffic unknown", ["dataset", "SMOKE", "--scans", "1", "--traffic", "jam",
                                   "--out", "d"], "--traffic"),
    ("report --retrain without --compare", ["report", "run", "--retrain", "afile"],
     "--compare"),
    ("retrain --out is a file", [*RETRAIN, "--out", "afile"], "--out afile"),
    ("retrain --seed -1", [*RETRAIN, "--seed", "-1", "--out", "r"], "--seed"),
    ("retrain --epochs 0", [*RETRAIN, "--epochs", "0", "--out", "r"], "--epochs"),
    ("retrain --threshold 2", [*RETRAIN, "--threshold", "2", "--out", "r"], "--threshold"),
    ("retrain V outside the config", [*RETRAIN[:-3], "7", *RETRAIN[-2:], "--out", "r"],
     "--validation-backgrounds"),
    ("retrain --train-data a file", [*RETRAIN, "--out", "r"], "--train-data"),
]


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*"))}


@pytest.fixture
def scratch(tmp_path: Path) -> Path:
    for name, content in SETUP.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    return tmp_path


@pytest.mark.parametrize("argv, names", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_exits_2_naming_it_and_writes_nothing(scratch, argv, names):
    before = snapshot(scratch)
    cmd = [ROOT / "configs" / "smoke.toml" if a == "SMOKE" else a for a in argv]
    r = subprocess.run([sys.executable, "-m", "falsify", *map(str, cmd)], cwd=scratch,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and names in lines[0], r.stderr
    assert snapshot(scratch) == before, "the command wrote or changed files"


def test_train_help_lists_its_options():
    r = subprocess.run([sys.executable, "-m", "falsify", "train", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    for option in ("--data", "--out", "--epochs", "--resume"):
        assert option in r.stdout
