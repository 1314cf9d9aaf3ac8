"""Commands that read thousands of real scans (predict, realism) count them on a terminal's
stderr, one line redrawn in place; a log or CI (no terminal) gets none of it."""

from __future__ import annotations

import io
import json
import sys

import numpy as np
import pytest

from falsify.cli import main
from falsify.cli.progress import ScanCounter
from falsify.data.training import held_out_scans
from falsify.sensor.lidar import load_sensor


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_count_is_drawn_in_place_on_a_terminal_only() -> None:
    tty, log = Terminal(), io.StringIO()
    for stream in (tty, log):
        counter = ScanCounter("predict", 5, stream)
        counter(2)   # drawn a quarter second after the last line at the most often
        counter(3)   # the last part is drawn whatever the time since the one before
        counter.close()
    assert tty.getvalue().startswith("\rpredict: ")
    assert "\rpredict: 5/5 scans" in tty.getvalue() and tty.getvalue().endswith("\n")
    assert tty.getvalue().count("\n") == 1 and "ETA" in tty.getvalue()
    assert log.getvalue() == ""


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    folder = tmp_path_factory.mktemp("counted") / "set"
    folder.mkdir()
    for k, image in enumerate(held_out_scans(load_sensor("kitti-hdl64e-front"), 5)):
        np.save(folder / f"{k:06d}.npy", image)
    return folder


def test_predict_and_realism_count_every_scan_on_a_terminal(scans, tmp_path, monkeypatch,
                                                           capsys) -> None:
    tty = Terminal()
    monkeypatch.setattr(sys, "stderr", tty)
    assert main(["predict", str(scans), "--out", str(tmp_path / "p"), "--json"]) == 0
    json.loads(capsys.readouterr().out)   # stdout holds the summary alone
    assert "\rpredict: 5/5 scans" in tty.getvalue() and tty.getvalue().endswith("\n")
    tty.truncate(0)
    tty.seek(0)
    assert main(["realism", str(scans), "--real", str(scans), "--out", str(tmp_path / "r"),
                 "--json"]) == 0
    json.loads(capsys.readouterr().out)
    assert "\rrealism: 10/10 scans" in tty.getvalue()   # the synthetic set and the real one


def test_without_a_terminal_predict_prints_no_count(scans, tmp_path, capsys) -> None:
    assert main(["predict", str(scans), "--out", str(tmp_path / "p")]) == 0
    assert "scans  " not in capsys.readouterr().err
