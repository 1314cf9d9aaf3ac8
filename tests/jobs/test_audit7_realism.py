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


def test_a_set_with_some_blank_scans_is_compared_and_its_blank_draws_counted(tmp_path,
                                                                             capsys) -> None:
    """A bootstrap draw (or a floor split) of blank scans only has no Fréchet distance: it was
    a ValueError traceback; now such draws are counted and the rest give the interval."""
    import json
    import shutil

    real = tmp_path / "real"
    assert main(["dataset", str(SMOKE), "--scans", "1", "--out", str(real), "--json"]) == 0
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    shutil.copy(next(real.glob("*.npy")), mixed / "000000.npy")
    for i in range(1, 4):
        np.save(mixed / f"{i:06d}.npy", np.zeros((64, 512, 6), np.float32))
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["realism", str(mixed), "--real", str(real), "--bootstrap", "20", "--out",
                 str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    boot = doc["bootstrap"]
    assert 0 < boot["undefined_draws"]["mixed"] < 20   # P(no good scan in 4 draws) = 0.32
    assert all(v is not None for v in boot["intervals"]["mixed"].values())
    assert doc["synthetic"][0]["frechet_floor"] is None   # every 1-vs-3 split holds a blank part
    page = (out / "realism.html").read_text()
    assert f"{boot['undefined_draws']['mixed']} of the draws of mixed held only blank" in page


def test_intervals_and_shares_of_undefined_draws() -> None:
    from falsify.results.scan_statistics import _interval, _share_closer

    nan = float("nan")
    assert _interval([nan, nan]) is None and _interval([nan, 1.0, 3.0]) is not None
    assert _share_closer([1.0, nan, 3.0], [2.0, 2.0, nan]) == 1.0
    assert _share_closer([nan], [1.0]) is None
