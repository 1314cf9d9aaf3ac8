"""The CI gate: count a run's blind spots (x, y cells below the mIoU threshold) → exit code.

Exit 0 when the count is within the limit (default 0) and no cell became a blind spot that was
not one in a baseline; 1 otherwise. Bad input raises FalsifyError (exit 2) before anything is
written; so does a run that is incomplete (stopped before its sampler ended, or being written
now), whose missing cells would pass unseen, unless it is allowed (`--allow-incomplete`). The
`--json` output doubles as the baseline file format; `--junit` writes one testcase per cell so
CI dashboards show which cells fail: those that fail the gate, so a dashboard's verdict is the
exit code's.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from falsify.errors import FalsifyError
from falsify.results.metrics import TO_KITTI4
from falsify.results.miou_maps import CellMap, axis_texts
from falsify.results.store import STORE_NAME, Completeness, check_complete, open_run

JUNIT_SUITE = "falsify gate"          # the JUnit suite's name: "falsify gate: <run>"
JUNIT_CLASS = "falsify.gate"          # its testcases' classname: "falsify.gate.<run>"


def cell_name(x: str, y: str) -> str:
    """A cell's name from its coordinates' texts (`axis_texts`)."""
    return f"cell x={x} y={y}"


def _key(x, y) -> tuple[float, float]:
    return (round(float(x), 6), round(float(y), 6))


@dataclass(frozen=True)
class GateCell:
    """One (x, y) cell as the gate sees it."""

    x: float
    y: float
    miou: float | None
    samples: int
    blind: bool
    name: str   # "cell x=.. y=..", unique among the map's cells

    def to_json(self, threshold: float) -> dict:
        d = {"x": self.x, "y": self.y,
             "miou": None if self.miou is None else round(self.miou, 6),
             "samples": self.samples, "blind": self.blind}
        if self.blind and self.miou is not None:
            d["below"] = round(threshold - self.miou, 6)
        return d


@dataclass(frozen=True)
class GateResult:
    """The verdict: all cells, the blind spots (worst first), and those the baseline lacked."""

    run: str
    threshold: float
    cells: tuple[GateCell, ...]
    blind_spots: tuple[GateCell, ...]
    new_blind_spots: tuple[GateCell, ...]
    limit: int | None          # None when judged against a baseline
    baseline: str | None
    completeness: Completeness
    writer: str | None = None  # the process computing on the run (gated with --allow-incomplete)
    objective: str = "car"     # the class whose IoU the cells average (or "miou")

    @property
    def passed(self) -> bool:
        if self.baseline is not None:
            return not self.new_blind_spots
        return len(self.blind_spots) <= (self.limit or 0)

    @property
    def exit_code(self) -> int:
        return 0 if self.passed else 1

    def to_json(self) -> dict:
        t = self.threshold
        return {"run": self.run, "objective": self.objective, "threshold": t,
                "limit": self.limit, "baseline": self.baseline,
                "cells": [c.to_json(t) for c in self.cells],
                "blind_spots": [c.to_json(t) for c in self.blind_spots],
                "new_blind_spots": [c.to_json(t) for c in self.new_blind_spots],
                **self.completeness.to_json(), "complete": self.complete, "writer": self.writer,
                "passed": self.passed, "exit_code": self.exit_code}

    @property
    def complete(self) -> bool | None:
        """False for a run stopped early or being written; None where that is not known."""
        return False if self.writer is not None else self.completeness.complete


def check_threshold(value: float | None, where: str = "--threshold") -> None:
    if value is not None and not (math.isfinite(value) and 0.0 < value <= 1.0):
        raise FalsifyError(f"{where}: {value} must be in (0, 1]")


def gate_cells(cmap: CellMap, threshold: float) -> list[GateCell]:
    """Every cell of the map, rows of y then x ascending, flagged blind below the threshold."""
    xs, ys = axis_texts(cmap.a_values), axis_texts(cmap.b_values)
    out = []
    for c in cmap.cells():
        blind = c.miou is not None and c.miou < threshold
        x, y = float(c.a), float(c.b)
        out.append(GateCell(x, y, c.miou, c.samples, blind, cell_name(xs[x], ys[y])))
    return out


def worst_first(cells: list[GateCell]) -> list[GateCell]:
    return sorted((c for c in cells if c.blind), key=lambda c: (c.miou, c.x, c.y))


def check_objective(baseline: str | Path, theirs: object, ours: str) -> None:
    """FalsifyError when a baseline gated another class's IoU than the run's, a class under a
    four-class network's name and SemanticKITTI's being one (None: a baseline that does not say,
    as `gate --json` files written before it did, is taken as it is)."""
    if theirs is None:
        return
    if TO_KITTI4.get(str(theirs), str(theirs)) != TO_KITTI4.get(ours, ours):
        raise FalsifyError(f"--baseline {baseline}: its blind spots are of {theirs} IoU, this "
                           f"run's of {ours} IoU; gate against a baseline of the same objective")


def _grid_text(keys: set[tuple[float, float]]) -> str:
    """A set of (x, y) cells as their x and y values, for messages."""
    xs, ys = axis_texts(k[0] for k in keys), axis_texts(k[1] for k in keys)
    return f"x [{', '.join(xs.values())}] × y [{', '.join(ys.values())}]"


def check_same_cells(baseline: str | Path, theirs: set[tuple[float, float]],
                     ours: set[tuple[float, float]] | None) -> None:
    """FalsifyError when a baseline's cells are not the run's: its blind spots would be
    compared with other positions' (a cell it lacks always new, one it holds never checked)."""
    if ours is not None and theirs != ours:
        raise FalsifyError(f"--baseline {baseline}: its cells are {_grid_text(theirs)}, this "
                           f"run's {_grid_text(ours)}; gate against a baseline of the same "
                           "x, y grid")


def _baseline_key(cell: dict) -> tuple[float, float]:
    """A baseline JSON cell's (x, y); ValueError unless both are finite numbers (true, NaN and
    Infinity, which Python's JSON reads, match no cell and would pass unseen)."""
    xy = (cell["x"], cell["y"])
    if not all(_finite(v) for v in xy):
        raise ValueError(f"not a finite number: {xy}")
    return _key(*xy)


def _finite(value: object) -> bool:
    """Whether a JSON value is a finite number (not true, NaN, Infinity, nor an int past a
    float's range)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def read_baseline(source: str | Path, threshold: float, allow_incomplete: bool = False,
                  objective: str = "car", cells: set[tuple[float, float]] | None = None
                  ) -> set[tuple[float, float]]:
    """Blind-spot cells of a baseline: a gate --json file, or a run directory (at `threshold`;
    a complete one unless `allow_incomplete`); FalsifyError when it gated another objective
    than the run's (`objective`), other (x, y) cells than the run's `cells`, or (a JSON file)
    at another threshold."""
    path = Path(source)
    if path.is_dir():
        try:
            base = open_run(path)
        except FalsifyError as exc:
            raise FalsifyError(f"--baseline: {exc}") from None
        check_complete(base, allow_incomplete, "--baseline ")
        check_objective(source, base.objective, objective)
        theirs = gate_cells(base.cell_map(), threshold)
        check_same_cells(source, {_key(c.x, c.y) for c in theirs}, cells)
        return {_key(c.x, c.y) for c in theirs if c.blind}
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FalsifyError(f"--baseline {path}: no such file or run directory") from None
    except (OSError, ValueError) as exc:   # ValueError: undecodable text, bad JSON, an int of
        # more digits than Python converts
        raise FalsifyError(f"--baseline {path}: not a readable gate JSON file ({exc})") from None
    spots = raw.get("blind_spots") if isinstance(raw, dict) else None
    if not isinstance(spots, list):
        raise FalsifyError(f"--baseline {path}: expected a JSON object with a 'blind_spots' list "
                           "(the output of `falsify gate --json`)")
    check_objective(source, raw.get("objective"), objective)
    t = raw.get("threshold")
    if t is not None and not _finite(t):
        raise FalsifyError(f"--baseline {path}: its threshold {json.dumps(t)} is not a number "
                           "in (0, 1]; write the baseline again with `falsify gate RUN --json`")
    if t is not None and abs(t - threshold) > 1e-9:
        raise FalsifyError(f"--baseline {path}: its blind spots are below mIoU {t:g}, this "
                           f"gate's below {threshold:g}; gate at the same threshold "
                           f"(--threshold {t:g}) or write the baseline again")
    if isinstance(raw.get("cells"), list):
        try:
            theirs = {_baseline_key(c) for c in raw["cells"]}
        except (KeyError, TypeError, ValueError):
            raise FalsifyError(f"--baseline {path}: each of its cells needs finite numeric x "
                               "and y") from None
        check_same_cells(source, theirs, cells)
    keys = set()
    for i, s in enumerate(spots):
        try:
            keys.add(_baseline_key(s))
        except (KeyError, TypeError, ValueError):
            raise FalsifyError(f"--baseline {path}: blind_spots[{i}] needs finite numeric x "
                               "and y") from None
    return keys


def judge(run: str | Path, threshold: float | None = None, max_blind_spots: int | None = None,
             baseline: str | Path | None = None, allow_incomplete: bool = False) -> GateResult:
    """Judge a run; every input is checked before any result exists. An incomplete run (or
    baseline run) is refused unless `allow_incomplete`, which judges the rows it holds."""
    if max_blind_spots is not None and baseline is not None:
        raise FalsifyError("--max-blind-spots and --baseline are mutually exclusive")
    if max_blind_spots is not None and max_blind_spots < 0:
        raise FalsifyError(f"--max-blind-spots: {max_blind_spots} must be >= 0")
    check_threshold(threshold)
    data = open_run(run)
    t = data.threshold if threshold is None else float(threshold)
    check_threshold(t, f"{data.path / STORE_NAME}: stored threshold")
    done, busy = check_complete(data, allow_incomplete)
    cells = gate_cells(data.cell_map(), t)
    base = (read_baseline(baseline, t, allow_incomplete, data.objective,
                          {_key(c.x, c.y) for c in cells})
            if baseline is not None else None)
    if not any(c.miou is not None for c in cells):
        counts = data.frame["status"].value_counts().to_dict() if len(data.frame) else {}
        what = ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) or "no rows"
        raise FalsifyError(f"{data.path / STORE_NAME}: no valid sample in any cell ({what}); "
                           "nothing to judge")
    blind = worst_first(cells)
    new = [c for c in blind if _key(c.x, c.y) not in base] if base is not None else []
    return GateResult(str(run), t, tuple(cells), tuple(blind), tuple(new),
                      None if baseline is not None else (max_blind_spots or 0),
                      None if baseline is None else str(baseline), done, busy,
                      data.objective)


def completeness_note(result: GateResult) -> str | None:
    """One line on a run gated while incomplete or of unknown completeness; None when complete."""
    done = result.completeness
    if result.writer is not None:
        return (f"INCOMPLETE: still being written by {result.writer}: {done.text()} so far, "
                "gated as they stand (--allow-incomplete)")
    if done.complete is False:
        return (f"INCOMPLETE: {done.text()}, stopped before its end, gated as they stand "
                "(--allow-incomplete)")
    if done.complete is None:
        return (f"completeness unknown: {done.text()} stored; the run does not record whether "
                "its sampler ended (written before falsify kept that, or by another tool)")
    return None


def _digits(miou: float, threshold: float) -> int:
    """Decimals that tell a blind cell's mIoU from the threshold (3, up to 6): 0.6496 under
    0.65 reads "0.6496 < 0.6500", not "0.650 < 0.650"."""
    return next((d for d in range(3, 7) if f"{miou:.{d}f}" != f"{threshold:.{d}f}"), 6)


def format_text(result: GateResult) -> str:
    """Verdict line, then the failing cells worst first with their margin below the threshold."""
    t = result.threshold
    n = len(result.blind_spots)
    verdict = "PASS" if result.passed else "FAIL"
    what = "" if result.objective in ("car", "miou") else f"{result.objective} "
    if result.baseline is None:
        head = (f"falsify gate: {verdict}: {n} blind spot{'s' * (n != 1)} ({what}mIoU < "
                f"{t:.3f}) in {result.run}; limit {result.limit}")
    else:
        k = len(result.new_blind_spots)
        head = (f"falsify gate: {verdict}: {n} blind spot{'s' * (n != 1)} ({what}mIoU < "
                f"{t:.3f}) in {result.run}, {k} new against baseline {result.baseline}")
    lines = [head]
    if note := completeness_note(result):
        lines.append(f"  {note}")
    scored = sum(c.miou is not None for c in result.cells)
    lines.append(f"  {len(result.cells)} cells, {scored} with valid samples")
    new = {_key(c.x, c.y) for c in result.new_blind_spots}
    for c in result.blind_spots:
        tag = "  NEW" if _key(c.x, c.y) in new else ""
        d = _digits(c.miou, t)
        lines.append(f"  {c.name}: mIoU {c.miou:.{d}f}, {t - c.miou:.{d}f} below the threshold "
                     f"({c.samples} samples){tag}")
    return "\n".join(lines)


# What XML 1.0 cannot hold, not even as a character reference: C0 controls but tab, LF and CR,
# lone surrogates (a path's non-UTF-8 bytes, as argv holds them) and U+FFFE, U+FFFF.
_NOT_XML = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def _xml_escape(m: re.Match) -> str:
    """One character XML 1.0 forbids as the escape Python prints for it."""
    code = ord(m.group())
    if 0xDC80 <= code <= 0xDCFF:   # surrogateescape's stand-in for the byte code - 0xDC00
        return f"\\x{code - 0xDC00:02x}"
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def xml_safe(text: str) -> str:
    """`text` with each character XML 1.0 forbids written as a Python escape (\\x1b, a path's
    byte \\xff), as the terminal shows them: JUnit readers reject the file otherwise."""
    return _NOT_XML.sub(_xml_escape, text)


_NOT_CLASS = re.compile(r"[^\w-]")   # what a JUnit classname's run part writes as _


def run_label(run: str | Path) -> str:
    """What names a run in JUnit XML: its path relative to the working directory when it lies
    under it (runs/a/grid and runs/b/grid stay apart), else its folder's name; the store file
    names its folder. The same command in the same place always gives the same label."""
    path = Path(os.path.abspath(run))
    if path.name == STORE_NAME and not path.is_dir():
        path = path.parent
    try:
        here: Path | None = Path(os.getcwd())
    except OSError:   # the working directory was removed
        here = None
    if here is not None and path != here and path.is_relative_to(here):
        return path.relative_to(here).as_posix()
    return path.name or path.as_posix()


def junit_names(run: str | Path) -> tuple[str, str]:
    """The suite name ("falsify gate: runs/a") and testcase classname ("falsify.gate.runs_a")
    of a run, XML-safe: dashboards (GitLab, Jenkins) merge testcases by classname and name, so
    several runs gated in one CI job must not share them. The classname keeps letters, digits,
    _ and -: a dot would split it into Jenkins packages."""
    label = run_label(run)
    return (xml_safe(f"{JUNIT_SUITE}: {label}"),
            f"{JUNIT_CLASS}.{_NOT_CLASS.sub('_', label)}")


def junit_xml(result: GateResult) -> str:
    """JUnit XML: a suite named for the run (`junit_names`), one testcase per cell. The cells
    that fail the gate fail (every blind spot over the limit, the new ones against a baseline);
    blind spots it accepts and empty cells are skipped, each saying why; a passing gate has no
    failure, as JUnit readers (Jenkins, GitLab, test-report actions) judge a build by its
    failures."""
    t = result.threshold
    suite_name, classname = junit_names(result.run)
    suite = ET.Element("testsuite", {"name": suite_name, "tests": str(len(result.cells))})
    props = ET.SubElement(suite, "properties")
    for name, value in (("run", result.run), ("objective", result.objective),
                        ("threshold", f"{t:.6g}"),
                        ("limit", "" if result.limit is None else str(result.limit)),
                        ("baseline", result.baseline or ""), ("passed", str(result.passed)),
                        ("exit_code", str(result.exit_code)),
                        ("samples", str(result.completeness.samples)),
                        ("planned", "" if (n := result.completeness.planned) is None else str(n)),
                        ("complete", "" if result.complete is None else str(result.complete))):
        ET.SubElement(props, "property", {"name": name, "value": xml_safe(value)})
    new = {_key(c.x, c.y) for c in result.new_blind_spots}
    counts = {"failure": 0, "skipped": 0}
    for c in result.cells:
        case = ET.SubElement(suite, "testcase", {"classname": classname, "name": c.name})
        if c.miou is None:
            ET.SubElement(case, "skipped", {"message": "no valid sample"})
            counts["skipped"] += 1
            continue
        if not c.blind:
            continue
        d = _digits(c.miou, t)
        text = (f"{c.name}: mIoU {c.miou:.{d}f} over {c.samples} samples is "
                f"{t - c.miou:.{d}f} below the threshold {t:.{d}f}")
        if result.baseline is not None and _key(c.x, c.y) not in new:
            tag, attrs = "skipped", {"message": "known blind spot, in the baseline"}
            text += f"; in the baseline {result.baseline}, so it does not fail the gate"
        elif result.baseline is None and result.passed:
            tag, attrs = "skipped", {"message": f"blind spot within --max-blind-spots "
                                                f"{result.limit}"}
            n = len(result.blind_spots)
            text += (f"; {n} blind spot{'s are' if n != 1 else ' is'} within the limit "
                     f"{result.limit}, so it does not fail the gate")
        else:
            tag, attrs = "failure", {"message": f"mIoU {c.miou:.{d}f} < {t:.{d}f}",
                                     "type": "BlindSpot"}
            if result.baseline is not None:
                text += " (new against the baseline)"
        ET.SubElement(case, tag, attrs).text = xml_safe(text)
        counts[tag] += 1
    # the counts readers show are those of the testcases written, placed before them
    suite.attrib.update({"failures": str(counts["failure"]), "errors": "0",
                         "skipped": str(counts["skipped"])})
    ET.indent(suite)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(suite, "unicode") + "\n"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):   # either missing, unreadable, or a NUL in a name
        return False


def _is_stream(path: Path, fd: int) -> bool:
    """Whether `path` is the regular file open as `fd` (a shell's `> FILE` or `2> FILE`)."""
    try:
        mine, theirs = os.fstat(fd), os.stat(path)
    except (OSError, ValueError):
        return False
    return (stat.S_ISREG(mine.st_mode) and (mine.st_dev, mine.st_ino)
            == (theirs.st_dev, theirs.st_ino))


def _store_files(run: str | Path) -> list[Path]:
    """The files of a run's store (as open_run finds it from a folder or the store itself)."""
    path = Path(run)
    folder = path.parent if path.name == STORE_NAME and not path.is_dir() else path
    return [folder / f"{STORE_NAME}{end}" for end in ("", "-wal", "-shm", "-journal")]


def check_outputs(run: str | Path, baseline: str | Path | None, junit: str | Path | None,
                  streams: tuple[tuple[str, int], ...] = ()) -> None:
    """FalsifyError before anything is read or written when an output would replace an input:
    `--junit` onto the run's store, the baseline, a folder or this command's redirected output
    (`streams`: name and descriptor), or a name not ending in .xml (a run's summary.json); or a
    `--baseline` file that is that output, emptied by the shell's `> FILE` before the gate
    could read it."""
    if baseline is not None and not Path(baseline).is_dir():
        for name, fd in streams:
            if _is_stream(Path(baseline), fd):
                raise FalsifyError(
                    f"--baseline {baseline}: is also where this command's {name} goes, "
                    "which a shell's `>` empties before the gate reads it; write the new "
                    "baseline to another file, then move it over the old one")
    if junit is None:
        return
    path = Path(junit)
    if path.is_dir():
        raise FalsifyError(f"--junit {path}: is a directory; name a file in it, e.g. "
                           f"{path / 'junit.xml'}")
    inputs = [(f, "the run's store") for f in _store_files(run)]
    if baseline is not None:
        inputs += ([(f, "the baseline run's store") for f in _store_files(baseline)]
                   if Path(baseline).is_dir() else [(Path(baseline), "the baseline")])
    for f, what in inputs:
        if _same_file(path, f):
            raise FalsifyError(f"--junit {path}: would replace {what} ({f}), which the gate "
                               "reads; write the JUnit XML to another file")
    for name, fd in streams:
        if _is_stream(path, fd):
            raise FalsifyError(f"--junit {path}: is also where this command's {name} goes; "
                               "the JUnit XML would replace what it prints: write them to "
                               "different files")
    if path.suffix.lower() != ".xml":   # RUN/summary.json or a map's .csv would be replaced
        raise FalsifyError(f"--junit {path}: must end in .xml")


def write_junit(result: GateResult, path: str | Path) -> None:
    """Write the JUnit XML atomically."""
    from falsify.fileio import write_text

    path = Path(path)
    if path.is_dir():
        raise FalsifyError(f"--junit {path}: is a directory")
    try:
        write_text(path, junit_xml(result))
    except OSError as exc:
        raise FalsifyError(f"--junit {path}: cannot write ({exc.strerror})") from None
