"""TOML a user's editor writes: a byte-order mark (Windows editors) before a space config, a
sensor or a split manifest is read; a sensor TOML is UTF-8 in any locale; a file in another
encoding says so; and a reader that stops early (`| head`) ends a command without a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.data.holdout import load_manifest
from falsify.errors import ConfigError
from falsify.paths import SENSOR_PRESETS
from falsify.sensor.lidar import load_sensor
from falsify.world.space import load_space
from tests.runfixture import SMOKE

ROOT = Path(__file__).resolve().parents[2]
BOM = b"\xef\xbb\xbf"


def test_a_config_with_a_bom_runs_and_its_run_reads_back(tmp_path, capsys):
    """Before: 'not valid TOML (Invalid statement (at line 1, column 1))'."""
    config = tmp_path / "bom.toml"
    config.write_bytes(BOM + SMOKE.read_bytes())
    assert load_space(config).dims == load_space(SMOKE).dims
    run = tmp_path / "run"
    assert main(["grid", str(config), "--out", str(run), "--quiet"]) == 0
    assert main(["gate", str(run), "--json"]) in (0, 1)   # the stored config parses again
    assert main(["report", str(run)]) == 0


def test_a_sensor_and_a_manifest_with_a_bom_are_read(tmp_path):
    sensor = tmp_path / "mine.toml"
    sensor.write_bytes(BOM + (SENSOR_PRESETS / "vlp16.toml").read_bytes())
    assert load_sensor(sensor).rows == load_sensor("vlp16").rows
    manifest = tmp_path / "splits.toml"
    (tmp_path / "held.npy").write_bytes(b"scan")
    manifest.write_bytes(BOM + b'[holdout]\npaths = ["held.npy"]\n')
    assert load_manifest(manifest).held_out([tmp_path / "held.npy"])


def test_a_latin1_config_says_it_is_not_utf8(tmp_path):
    config = tmp_path / "latin1.toml"
    config.write_bytes(b"# caf\xe9\n" + SMOKE.read_bytes())
    with pytest.raises(ConfigError, match=r"latin1.toml: not valid TOML \(not UTF-8: invalid "
                                          r"continuation byte at byte 5\)"):
        load_space(config)


def test_a_sensor_toml_is_utf8_in_a_non_utf8_locale(tmp_path):
    """Before: read in the locale's encoding, a UnicodeDecodeError traceback under LC_ALL=C."""
    sensor = tmp_path / "mine.toml"
    sensor.write_bytes("# Capteur réglé à 10 Hz\n".encode() +
                       (SENSOR_PRESETS / "vlp16.toml").read_bytes())
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0",
           "PYTHONUTF8": "0", "PYTHONIOENCODING": ""}
    code = ("import sys; from falsify.sensor.lidar import load_sensor; "
            "print(load_sensor(sys.argv[1]).rows)")
    done = subprocess.run([sys.executable, "-c", code, str(sensor)], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "16"


def test_a_reader_that_stops_early_ends_the_command_quietly(tmp_path):
    """Before: `falsify gate RUN --json | true` printed a BrokenPipeError traceback."""
    run = tmp_path / "run"
    assert main(["grid", str(SMOKE), "--out", str(run), "--quiet", "--no-report"]) == 0
    reader = subprocess.Popen([sys.executable, "-m", "falsify", "gate", str(run), "--json",
                               "--allow-incomplete"], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE)
    reader.stdout.close()   # the reader is gone before the command prints
    err = reader.stderr.read().decode()
    assert reader.wait(timeout=60) == 141 and "Traceback" not in err, err
