"""What grid, search, explain, fit-world and bench say of their options, held to what they do.

- `--fidelity` picks a variant of the bundled network: with `--model` it was silently ignored
  (the user's model ran as given, exit 0) while the run recorded the preset; now refused.
- Options whose help said nothing of their default or of the limits enforced now say them, and
  what they say is what the parser and the job use.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from falsify.cli import build_parser, main
from falsify.models.runners import BUNDLED_ONNX
from tests.runfixture import SMOKE


def _option_help(command: str, option: str) -> tuple[str, object]:
    """The help text of `falsify COMMAND OPTION`, whitespace collapsed, and its parser default."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    action = next(a for a in sub.choices[command]._actions if option in a.option_strings)
    return " ".join((action.help or "").split()), action.default


@pytest.mark.parametrize("command", ["grid", "search"])
def test_a_fidelity_preset_with_an_own_model_is_refused(tmp_path: Path, capsys,
                                                        command: str) -> None:
    out = tmp_path / "run"
    search = ["--algorithm", "random", "--budget", "4"] if command == "search" else []
    argv = [command, str(SMOKE), "--out", str(out), "--quiet", "--no-report",
            "--model", str(BUNDLED_ONNX), *search]
    assert main([*argv, "--fidelity", "fast"]) == 2
    err = capsys.readouterr().err
    assert "--fidelity fast" in err and "--model" in err and "squeezeseg-int8-crf1" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()
    # exact (the default) with a model of one's own runs as before
    assert main([*argv, "--fidelity", "exact"]) == 0


def test_a_fidelity_runs_resume_command_still_continues_it(tmp_path: Path, capsys) -> None:
    """The command a run prints to finish it names the preset's own variant as --model beside
    --fidelity: that pair is the preset itself, not a model of one's own."""
    import sqlite3

    from falsify.results.store import STORE_NAME, open_run

    out = tmp_path / "run"
    assert main(["grid", str(SMOKE), "--out", str(out), "--quiet", "--no-report",
                 "--fidelity", "fast"]) == 0
    with sqlite3.connect(out / STORE_NAME) as db:   # a sample the run has yet to score
        db.execute("DELETE FROM samples WHERE rowid = (SELECT MAX(rowid) FROM samples)")
    db.close()
    command = open_run(out).resume_command()
    assert "--model" in command and "--fidelity fast" in command
    capsys.readouterr()
    assert main([*shlex.split(command)[1:], "--quiet", "--no-report", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["computed_this_time"] == 1


def test_fidelity_help_names_every_preset_and_the_default() -> None:
    from falsify.jobs.fidelity import PRESETS

    text, default = _option_help("grid", "--fidelity")
    for name in PRESETS:
        assert name in text
    assert f"{default} (fp32, 3 CRF iterations; the default)" in text
    assert "not with --model" in text


@pytest.mark.parametrize("option,limit", [("--depth", "MAX_DEPTH"), ("--rules", "MAX_RULES"),
                                          ("--clusters", "MAX_CLUSTERS")])
def test_explain_help_states_the_limits_and_defaults_it_enforces(option: str, limit: str) -> None:
    from falsify.jobs import explain

    text, default = _option_help("explain", option)
    m = re.search(r"1 to (\d+) \(default (\d+)\)", text)
    assert m, f"explain {option}: {text!r} states no range and default"
    assert int(m.group(1)) == getattr(explain, limit)
    assert int(m.group(2)) == default


def test_fit_world_name_help_states_its_default() -> None:
    text, default = _option_help("fit-world", "--name")
    assert f"default {default}" in text


def test_bench_config_help_names_each_benchmarks_own_space() -> None:
    from falsify.cli.bench import BENCH_CONFIGS

    text, _ = _option_help("bench", "--config")
    for what, config in BENCH_CONFIGS.items():
        # "configs/X.toml for a, b and c": each benchmark is named after its space
        clause = re.search(rf"configs/{re.escape(config)} for ([^,)]*(?:, (?!configs)[^,)]*)*)",
                           text)
        assert clause and re.search(rf"\b{what}\b", clause.group(1)), \
            f"bench --config: {what}'s space configs/{config} not named: {text!r}"
