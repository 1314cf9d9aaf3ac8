"""Every command builds the whole parser first (a CI gate, `--help`): it must not import the
heavy libraries that only some commands use. scipy.stats (Sobol) and pandas (the trade-off's
knob names) took it from 0.4 s to 2 s."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("scipy.stats", "pandas", "torch", "trimesh", "onnxruntime", "ray", "optuna")


def test_building_the_parser_imports_no_heavy_library() -> None:
    code = ("import sys\nfrom falsify.cli import build_parser\nbuild_parser()\n"
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "", f"imported while building the parser: {out}"
