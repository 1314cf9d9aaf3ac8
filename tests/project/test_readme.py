"""README.md is the user's guide: short, free of lab-notebook residue (dates, outside paths), its
links resolve and its `<!-- quick -->` code blocks run as written, so a new user's first steps work.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
MAX_LINES = 250
QUICK = "<!-- quick -->"
FORBIDDEN: list[tuple[re.Pattern[str], str]] = [
    (re.compile(r"\b20\d\d-\d\d-\d\d\b"), "a date"),
    (re.compile(r"\.\./"), "a path outside the repository (../)"),
    (re.compile(r"/work"), "a path outside the repository (/work)"),
    (re.compile(r"/tmp/"), "a path outside the repository (/tmp/)"),
    (re.compile(r"\bsessions?\b", re.IGNORECASE), "the word 'session'"),
    (re.compile(r"\bbranch(es)?\b", re.IGNORECASE), "the word 'branch'"),
]
FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"`[^`]*`")
# `runs/...` at the start of a path (not inside another word or path)
RUNS = re.compile(r"(?<![\w./-])runs/")


def readme_lines() -> list[str]:
    return README.read_text(encoding="utf-8").splitlines()


def code_blocks(lines: list[str]) -> list[tuple[int, bool, list[str]]]:
    """(line number of the opening fence, marked quick, the block's lines) for each fenced block;
    a block is quick when the line directly above its opening fence is `<!-- quick -->`."""
    blocks: list[tuple[int, bool, list[str]]] = []
    start: int | None = None
    body: list[str] = []
    for i, line in enumerate(lines):
        if FENCE.match(line):
            if start is None:
                start, body = i, []
            else:
                quick = start > 0 and lines[start - 1].strip() == QUICK
                blocks.append((start + 1, quick, body))
                start = None
        elif start is not None:
            body.append(line)
    assert start is None, f"README.md:{start + 1}: code block never closed"
    return blocks


def quick_commands() -> list[str]:
    """Every command line of the quick blocks, in order (blank and comment lines skipped)."""
    return [line.strip() for _, quick, body in code_blocks(readme_lines()) if quick
            for line in body if line.strip() and not line.strip().startswith("#")]


def prose_lines(lines: list[str]) -> list[tuple[int, str]]:
    """(line number, text) of the lines outside fenced code blocks, inline code removed."""
    out, inside = [], False
    for i, line in enumerate(lines, 1):
        if FENCE.match(line):
            inside = not inside
            continue
        if not inside:
            out.append((i, INLINE_CODE.sub("", line)))
    return out


def test_readme_is_short() -> None:
    n = len(readme_lines())
    assert n <= MAX_LINES, f"README.md has {n} lines; the user's guide keeps to {MAX_LINES}"


def test_readme_has_no_notebook_residue() -> None:
    bad = [f"README.md:{i}: {why}: {line.strip()}"
           for i, line in enumerate(readme_lines(), 1)
           for pattern, why in FORBIDDEN if pattern.search(line)]
    assert not bad, "\n".join(bad)


def test_readme_links_resolve() -> None:
    missing = []
    for i, line in prose_lines(readme_lines()):
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("#"):
                continue  # a URL (http:, mailto:, ...) or an anchor in the README itself
            path = target.split("#", 1)[0]
            if not (ROOT / path).exists():
                missing.append(f"README.md:{i}: {target}")
    assert not missing, "links to files that do not exist:\n" + "\n".join(missing)


def test_quick_blocks_use_the_smoke_config_only() -> None:
    commands = quick_commands()
    assert commands, f"README.md marks no code block {QUICK}"
    configs = {c for line in commands for c in re.findall(r"configs/[\w./-]+", line)}
    assert configs <= {"configs/smoke.toml"}, configs


def test_quick_blocks_run(tmp_path: Path) -> None:
    """Each line of each quick block, in order, with `runs/` moved into tmp_path so nothing is
    written into the repository; the `falsify` of this Python comes first on PATH."""
    commands = quick_commands()
    assert commands
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    runs = tmp_path / "runs"
    runs.mkdir()
    for line in commands:
        command = RUNS.sub(f"{runs}/", line)
        done = subprocess.run(["bash", "-c", command], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=600)
        if done.returncode != 0:
            tail = (done.stdout + done.stderr)[-3000:]
            pytest.fail(f"{line!r} exited {done.returncode}:\n{tail}")


def test_ci_runs_the_readme_test_command_exactly() -> None:
    """The block under "Set up and run the tests" is one line, and `.ci/run` runs it as written,
    on every core, so CI and a new user run the same suite the same way."""
    lines = readme_lines()
    heading = next(i for i, line in enumerate(lines) if line.startswith("Set up and run the tests"))
    start, _, body = next(b for b in code_blocks(lines) if b[0] > heading + 1)
    commands = [c.strip() for c in body if c.strip()]
    assert len(commands) == 1, f"README.md:{start}: the test block holds {commands}"
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert commands[0] in ci, f".ci/run does not run the README's test command: {commands[0]}"
    assert "python -m pytest -n auto" in commands[0] and "pytest -m slow -n auto" in commands[0]


def test_ci_stops_when_the_test_command_fails(tmp_path: Path) -> None:
    """A failure early in the test line's `&&` list (the main tier) fails `.ci/run` at once:
    `set -e` alone would carry on to the gates and pass. Stand-in tools on PATH record calls."""
    (tmp_path / ".ci").mkdir()
    (tmp_path / ".ci" / "run").write_text((ROOT / ".ci" / "run").read_text())
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    tools = {"python": f'echo "$*" >> "{tmp_path}/python-called"\n'
                       'case "$*" in *"-m pytest -n auto"*) exit 1;; esac; exit 0',
             "pip": "exit 0", "chromium": "exit 0", "chromedriver": "exit 0",
             "falsify": f'echo "$*" >> "{tmp_path}/falsify-called"'}
    for name, body in tools.items():
        (bin_dir / name).write_text(f"#!/bin/sh\n{body}\n")
        (bin_dir / name).chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}/usr/bin{os.pathsep}/bin"}
    done = subprocess.run(["bash", str(tmp_path / ".ci" / "run")], env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 1, done.stderr
    assert "the test command failed (1)" in done.stderr
    called = (tmp_path / "python-called").read_text().splitlines()
    assert called == ["-m ruff check .", "-m pytest -n auto"], called   # nothing after it ran
    assert not (tmp_path / "falsify-called").exists()
