"""What docs/scale-out.md and docs/camera.md tell a user to type, or say a command writes, held
to the product.

- scale-out.md's Ray figures were measured on configs/paper.toml, but the command shown had no
  `--config`: typed as written, `bench pipeline` measures configs/bench.toml.
- camera.md named only the npy layout of `grid --camera`'s files; with `--retrain-format
  semantickitti` they go elsewhere, and the page now says where.
"""

from __future__ import annotations

import csv
import re
import shlex
from pathlib import Path

from falsify.cli import build_parser, main
from tests.runfixture import ROOT, SMOKE

DOCS = ROOT / "docs"


def _section(page: str, heading: str) -> str:
    """The text of `## heading` up to the next heading of that level."""
    text = (DOCS / page).read_text()
    start = text.index(f"## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start:] if end < 0 else text[start:end]


def test_the_ray_cost_figures_command_measures_the_space_they_were_measured_on() -> None:
    from falsify.cli.bench import BENCH_CONFIGS
    from falsify.paths import CONFIGS

    section = _section("scale-out.md", "What the executor costs")
    command = re.search(r"`(falsify bench pipeline [^`]*)`", section).group(1)
    args = build_parser().parse_args(shlex.split(command)[1:])
    # as `bench` resolves it: its own space where --config is not given
    config = Path(args.config or CONFIGS / BENCH_CONFIGS[args.what])
    assert config.name == "paper.toml", f"{command!r} measures {config.name}"


def test_camera_doc_names_where_semantickitti_retraining_sets_keep_the_camera_files(
        tmp_path: Path, capsys) -> None:
    text = " ".join((DOCS / "camera.md").read_text().split())
    m = re.search(r"with `--retrain-format semantickitti`: the image as `([^`]+)`, the other "
                  r"files as `([^`]+)`", text)
    assert m, "camera.md does not say where --retrain-format semantickitti puts the camera files"
    image, other = m.group(1), m.group(2)
    out = tmp_path / "run"
    assert main(["grid", str(SMOKE), "--out", str(out), "--quiet", "--no-report", "--threshold",
                 "1", "--camera", "--retrain-format", "semantickitti"]) == 0
    retrain = out / "retrain"
    rows = list(csv.DictReader((retrain / "index.csv").open()))
    assert rows
    for row in rows:
        stem = f"{int(row['eval_index']):06d}"
        assert (retrain / image.replace("NNNNNN", stem)).is_file()
        assert (retrain / other.replace("NNNNNN", stem)).is_file()
    # the npy layout the page names first is unchanged
    assert not list(retrain.glob("*.image.png"))
