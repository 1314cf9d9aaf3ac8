"""A SIGTERM (a cancelled CI job, `kill`) stops any command the clean way: its clean-up runs
(temporary folders removed) and it says so, exit 143; only grid, search and the trainers
had this, the others died from the raw signal, leaving e.g. tradeoff's temporary models."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = """
import os, signal, sys, tempfile, time
import falsify.cli.holdout as command
from falsify.cli import main

def run(args):
    with tempfile.TemporaryDirectory(dir=sys.argv[1]):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    return 0

command.run = run
sys.exit(main(["holdout", "scans", "--out", "m.toml"]))
"""


def test_sigterm_runs_a_commands_clean_up_and_says_so(tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(work)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 143, (done.returncode, done.stderr)
    assert done.stderr.strip() == "falsify: terminated"
    assert list(work.iterdir()) == []
