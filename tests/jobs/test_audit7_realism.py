"""realism on a set of blank scans (empty files, or dense fog throughout) exits 2 naming the
set, before writing anything: it was a ValueError traceback from the Fréchet distance."""

from __future__ import annotations

import numpy as np

from falsify.cli import main
from tests.runfixture import SMOKE


def test_a_set_of_blank_scans_is_named(tmp_path, capsys) -> None:
    real = tmp_path / "real"
    assert main(["dataset", str(SMOKE), "--scans", "2", "--out", str(real), "--json"]) == 0
    blank = tmp_path / "blank"
    blank.mkdir()
    for i in range(3):
        np.save(blank / f"{i:06d}.npy", np.zeros((64, 512, 6), np.float32))
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["realism", str(blank), "--real", str(real), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["falsify: error: set blank: its 3 scans hold no valid point (range > 0); "
                   "nothing to compare (blank scans, or dense fog throughout?)"]
    assert not out.exists()
