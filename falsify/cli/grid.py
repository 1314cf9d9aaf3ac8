"""`falsify grid`: evaluate the full factorial grid of a space."""

from __future__ import annotations

import argparse

from falsify.cli.run import run_job, run_options


def add_arguments(p: argparse.ArgumentParser) -> None:
    run_options(p)


def run(args) -> int:
    return run_job(args, "grid", "grid")
