"""What the command modules share: the parser class, the usage error, JSON-or-text output, the
options several commands take and their help texts."""

from __future__ import annotations

import argparse
import json

from falsify.checks import require_torch
from falsify.errors import FalsifyError
from falsify.paths import CONFIGS

DEFAULT_CONFIG = CONFIGS / "paper.toml"
MODEL_HELP = ("an ONNX segmentation model with its .json spec, a bundled model's name, or a "
              "Python plug-in MODULE:FACTORY or FILE.py:FACTORY (see falsify.models.plugin) "
              "(default: bundled)")
BACKEND_HELP = "onnx or torch for a model file; python (set by itself) for a plug-in"
def int_in(lo: int, hi: int):
    """An argparse type: an integer in lo..hi, whose error says the range, not every value."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: not an integer") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{value}: allowed {lo}..{hi}")
        return value
    return parse


ALLOW_INCOMPLETE_HELP = ("read a run stopped before its end, or still being written, on the "
                         "samples it holds (default: refuse it, exit 2)")
DEVICE_HELP = ("where the network runs: cpu, or cuda (torch and plug-ins: a CUDA build of "
               "torch; onnx: pip install onnxruntime-gpu)")


class UsageError(FalsifyError):
    """A bad command-line argument."""


class Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line and exit code 2 (its own convention too)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"falsify: error: {message}\n")


def emit(args, summary: dict, text: str) -> None:
    """Print the summary as JSON with --json, else as text."""
    if getattr(args, "json", False):
        print(json.dumps(summary, indent=2, sort_keys=True, default=str))
    else:
        print(text)


def predict_sequences(value: str | None, scans: list[str]) -> list[str] | None:
    """--sequences as a list of two-digit ids found under the SemanticKITTI roots named; a
    UsageError names the option and the allowed values."""
    if value is None:
        return None
    from falsify.world.real_scans import SEQUENCE_ID, available_sequences

    allowed = available_sequences(scans)
    hint = (f"allowed: {', '.join(allowed)}" if allowed else "no SemanticKITTI root or "
            "sequences/ folder (sequences/SS/velodyne/*.bin) among the scans")
    ids = [v.strip() for v in value.split(",")]
    for v in ids:
        if not SEQUENCE_ID.fullmatch(v):
            raise UsageError(f"--sequences {value}: {v!r} is not a two-digit sequence id; {hint}")
        if v not in allowed:
            raise UsageError(f"--sequences {value}: no sequence {v} in the scans named; {hint}")
    return sorted(set(ids))


def holdout_option(p: argparse.ArgumentParser) -> None:
    """--holdout: split manifests whose held-out scans the command refuses."""
    p.add_argument("--holdout", action="append", metavar="SPLITS_TOML",
                   help="a split manifest whose held-out scans this command refuses (matched by "
                   "content); also read: $FALSIFY_HOLDOUT, a splits.toml beside the data, and "
                   "a SemanticKITTI root's official split (08, 11-21)")


def camera_option(p: argparse.ArgumentParser, help_text: str) -> None:
    """--camera [PRESET]: what the command does with the camera, and the presets."""
    from falsify.sensor.camera import CAMERA_PRESETS, DEFAULT_CAMERA
    p.add_argument("--camera", nargs="?", const=DEFAULT_CAMERA, default=None, metavar="PRESET",
                   help=f"{help_text} (presets: {', '.join(CAMERA_PRESETS)}; "
                   f"default {DEFAULT_CAMERA})")


def check_backend(backend: str | None, model: str | None) -> str:
    """The --backend to run `model` on (onnx when not given); UsageError for a backend other
    than python given with a plug-in, which would otherwise be silently ignored."""
    from falsify.models.plugin import is_plugin

    if backend not in (None, "python") and is_plugin(model):
        raise UsageError(f"--backend {backend}: the plug-in model {model} runs on python; "
                         "leave --backend out (or give python)")
    if backend == "torch":
        require_torch("--backend torch")
    return backend or "onnx"


def given_options(args, *names: str) -> dict:
    """The named options the user gave (not None): each benchmark's own defaults stand for the
    rest, since one shared parser default cannot suit scans, pipelines and camera images."""
    return {n: getattr(args, n) for n in names if getattr(args, n) is not None}
