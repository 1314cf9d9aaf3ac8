"""Every option of every command says what it does in `--help` (48 said nothing, among them
train's --precision and --device, retrain's --threshold and grid's --no-report)."""

from __future__ import annotations

import argparse

from falsify.cli import build_parser, main


def test_every_option_has_help() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    silent = [f"{name} {a.option_strings[-1]}" for name, cmd in sub.choices.items()
              for a in cmd._actions
              if a.option_strings and not isinstance(a, argparse._HelpAction) and not a.help]
    assert not silent, silent


def test_help_shows_the_defaults_a_user_must_know(capsys) -> None:
    for argv, says in ((["train", "--help"], "auto: bf16 where the CPU (or GPU) computes it"),
                       (["grid", "--help"], "write no retraining set"),
                       (["report", "--help"], "print the summary as JSON on stdout")):
        try:
            main(argv)
        except SystemExit as exc:
            assert exc.code == 0
        text = " ".join(capsys.readouterr().out.split())
        assert says in text, (argv, says)


def test_version_is_printed(capsys) -> None:
    import falsify
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    assert capsys.readouterr().out == f"falsify {falsify.__version__}\n"
