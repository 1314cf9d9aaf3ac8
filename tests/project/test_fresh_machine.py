"""A new user's first commands on a machine with nothing beside the clone: the README's main job
runs on the embedded streets, the real-scan job says where to point it, and no path of this
project's workspace ships in the package, its configs or the README."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from tests.conftest import ROOT
from tests.project.test_readme import code_blocks, readme_lines

FIRST = "<!-- first -->"
SHIPPED = ("falsify", "configs", "sampler", "models", "reports", "README.md")
WORKSPACE = re.compile(r"shared/data|/tmp/")


def first_command() -> str:
    """The README's first command: the block right under `<!-- first -->`."""
    lines = readme_lines()
    marked = [body for start, _, body in code_blocks(lines)
              if start >= 2 and lines[start - 2].strip() == FIRST]
    assert len(marked) == 1, f"README.md marks {len(marked)} blocks {FIRST}; one is the first"
    commands = [c.strip() for c in marked[0] if c.strip() and not c.strip().startswith("#")]
    assert len(commands) == 1, commands
    return commands[0]


def bare_env() -> dict[str, str]:
    """This Python's environment with no data variable set and its `falsify` first on PATH."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("SEMANTICKITTI", "KITTI_OBJECT", "FALSIFY_HOLDOUT")}
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


def main_job() -> str:
    """The README's first command from its `falsify` on (the set-up part installs what the tests
    already run on); `.ci/run` runs it as written."""
    command = first_command()
    assert command.startswith("pip install torch==2.13.0 && pip install -e"), command
    job = command[command.index("falsify grid"):]
    assert job.startswith("falsify grid configs/paper.toml --out runs/paper"), job
    return job


def run_main_job(cwd: Path, config: str | None = None) -> subprocess.CompletedProcess:
    """The README's main job in an empty folder; `config` swaps in a smaller space."""
    job = main_job()
    if config is not None:
        job = job.replace("configs/paper.toml", config)
    return subprocess.run(["bash", "-c", job], cwd=cwd, env=bare_env(), capture_output=True,
                          text=True, timeout=900)


def check_main_job(done: subprocess.CompletedProcess, cwd: Path) -> None:
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(r"^blind spots: \d+ of \d+ cells below mIoU 0\.65$", done.stdout, re.M), \
        done.stdout
    report = cwd / "runs" / "paper" / "report.html"
    assert report.is_file() and report.stat().st_size > 10_000
    # The retraining line names a folder only where one was written.
    retrain = re.search(r"^retraining set: (.*)$", done.stdout, re.M)
    assert retrain, done.stdout
    made = (cwd / "runs" / "paper" / "retrain").is_dir()
    assert made == retrain.group(1)[0].isdigit() and made != retrain.group(1).startswith(
        "none"), retrain.group(0)


def test_the_first_command_runs_with_nothing_beside_it(tmp_path: Path) -> None:
    """The main job, on the smoke space for time, from an empty folder with no data variable.
    The job as written (2,250 scans, 3.3 CPU-minutes) runs in `.ci/run`, gated at 0 blind cells."""
    check_main_job(run_main_job(tmp_path, "configs/smoke.toml"), tmp_path)


def test_ci_runs_the_main_job_as_written() -> None:
    """`.ci/run` takes its main job from the README through `main_job`, so the two cannot part."""
    ci = (ROOT / ".ci" / "run").read_text()
    assert "from tests.project.test_fresh_machine import main_job" in ci
    assert "grep -q '^2250 samples ' job.log" in ci and "runs/paper/report.html" in ci
    assert "falsify gate runs/paper --max-blind-spots 0" in ci


def test_the_real_scan_job_says_where_to_point_it(tmp_path: Path) -> None:
    """Without SEMANTICKITTI, paper-real exits 2 naming the variable, the key and how to get the
    data, and writes nothing."""
    done = subprocess.run([sys.executable, "-m", "falsify", "grid", "configs/paper-real.toml",
                           "--out", "runs/real"], cwd=tmp_path, env=bare_env(),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    err = done.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "dims.background.real" in err and "${SEMANTICKITTI} is not set" in err
    assert "export SEMANTICKITTI=DIR" in err and "semantic-kitti.org" in err
    assert not (tmp_path / "runs").exists()


def test_no_workspace_path_ships() -> None:
    """No `shared/data` or `/tmp/` path in what installs or what a user reads first."""
    found = []
    for top in SHIPPED:
        path = ROOT / top
        files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
        for f in files:
            try:
                text = f.read_text(encoding="utf-8")
            except (UnicodeDecodeError, OSError):
                continue   # weights and pictures
            found += [f"{f.relative_to(ROOT)}:{i}: {line.strip()}"
                      for i, line in enumerate(text.splitlines(), 1) if WORKSPACE.search(line)]
    assert not found, "\n".join(found)
