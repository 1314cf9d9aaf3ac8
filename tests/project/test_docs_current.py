"""The docs name what exists today: every `falsify ...` command line they show parses against the
command line (placeholders in capitals such as N, CONFIG or [--epochs N], and required arguments
a line leaves to the prose, are allowed), and every file of the repository they name is there.
A renamed option or a moved file fails here, not in a user's shell."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from falsify.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted([ROOT / "README.md", ROOT / "models" / "README.md",
               *(ROOT / "docs").glob("*.md"), *(ROOT / "docs" / "experiments").glob("*.md"),
               *(ROOT / "models" / "cards").glob("*.md")])
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9_]*|.*[\[\]|].*")
REPO_FILE = re.compile(r"(?:configs|research|models|docs|reports|sampler|tests|falsify)/"
                       r"[\w./{},-]+\.(?:toml|py|json|sh|md|csv|onnx|pt)")
OFFENDING = re.compile(r"unrecognized arguments: (.*)|invalid (?:choice|\w+ value): '([^']*)'")


def commands(text: str) -> list[str]:
    """The command lines in fenced blocks (continuations joined) and in inline code."""
    found = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            m = re.search(r"(?:^|&&|;|\|)\s*(falsify\s.*)$", line.strip())
            if m:
                found.append(m.group(1))
    found += re.findall(r"`(falsify [^`]+)`", re.sub(r"\n\s*", " ", text))
    # a command ends where the shell's next one, a redirection or a comment begins
    return [re.split(r"\s(?:&&|\||;|>|2>|#)\s?", c)[0] for c in found]


def problem(parser, line: str) -> str | None:
    """The parser's complaint about a line, unless it is only about placeholders or arguments
    the line leaves out."""
    try:
        argv = shlex.split(line)[1:]
    except ValueError:
        return None
    if not argv or "..." in line or {"-h", "--help"} & set(argv):
        return None
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            parser.parse_args(argv)
    except SystemExit as exc:
        if not exc.code:
            return None
        msg = err.getvalue().strip().splitlines()[-1]
        m = OFFENDING.search(msg)
        if m is None:
            return None if "arguments are required" in msg else msg
        tokens = (m.group(1) or "").split() or [m.group(2)]
        return None if all(PLACEHOLDER.fullmatch(t) for t in tokens) else msg
    return None


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_doc_commands_parse(doc: Path) -> None:
    parser = build_parser()
    bad = [f"{c}\n    {p}" for c in commands(doc.read_text(encoding="utf-8"))
           if (p := problem(parser, c))]
    assert not bad, "\n".join(bad)


def named_files(text: str) -> list[str]:
    """The repository files a text names, each {a,b} alternative spelled out; capitals or a
    placeholder's name (EFFECT, my_net) make a name a pattern, not a file."""
    out = []
    for name in REPO_FILE.findall(text):
        m = re.search(r"\{([^}]*)\}", name)
        alts = m.group(1).split(",") if m else [""]
        out += [name[:m.start()] + a + name[m.end():] if m else name for a in alts]
    return [n for n in out if not re.search(r"/(?:[A-Z]+|my_\w+)\.", n)]


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_doc_files_exist(doc: Path) -> None:
    missing = [n for n in named_files(doc.read_text(encoding="utf-8")) if not (ROOT / n).exists()]
    assert not missing, missing


def test_the_file_check_spells_out_alternatives_and_skips_patterns() -> None:
    assert named_files("`configs/{paper,smoke}.toml`, research/experiments/robo3d/EFFECT.toml, "
                       "models/my_net.onnx") == ["configs/paper.toml", "configs/smoke.toml"]


def test_the_check_sees_a_renamed_option_and_a_wrong_choice() -> None:
    parser = build_parser()
    text = ("```sh\nfalsify grid configs/paper.toml --out runs/p \\\n    --wokers 2\n```\n"
            "and `falsify bench scann --json`, but `falsify grid CONFIG --workers N` is fine.")
    got = [problem(parser, c) for c in commands(text)]
    assert "unrecognized arguments: --wokers 2" in got[0]
    assert "invalid choice: 'scann'" in got[1]
    assert got[2] is None
