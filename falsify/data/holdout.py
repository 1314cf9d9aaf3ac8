"""Held-out scans: the data a user only reports on, which nothing may fit, train or choose on.

A split manifest (TOML) names held-out scans by their content (`[[holdout.scan]]` entries with
sha256 and bytes) or by where they are (`paths` and SemanticKITTI `sequences`, relative to the
manifest's folder). Scans are matched by content, so a held-out scan reached through a symlink
or a copy is still held out. Manifests come from `--holdout FILE`, the FALSIFY_HOLDOUT variable
(paths joined by the OS's separator) and a `splits.toml` in a scan's folder or any folder above
it; a SemanticKITTI root without one holds out the official split (08 validation, 11-21 test).
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from falsify.data.range_npy import npy_files
from falsify.errors import FalsifyError
from falsify.fileio import file_sha256, parse_toml, read_bytes
from falsify.world.real_scans import sequence_dirs, sequence_files

MANIFEST_NAME = "splits.toml"
HOLDOUT_VARIABLE = "FALSIFY_HOLDOUT"
# SemanticKITTI's official split: 08 validates, 11-21 are the test set (labels withheld).
SEMANTICKITTI_HELD_OUT = ("08", *(f"{q}" for q in range(11, 22)))
SCAN_SUFFIXES = (".bin", ".npy")


@dataclass(frozen=True)
class HeldOutScan:
    """One held-out scan: its content's SHA-256 and size, how it was named, and the manifest
    (or rule) that holds it out."""

    sha256: str
    size: int
    name: str
    source: str


@dataclass(frozen=True)
class HeldOutFile:
    """A held-out scan on disk, hashed only when a candidate has its size."""

    path: Path
    size: int
    source: str


class Holdout:
    """The held-out scans of some manifests; `check` refuses files whose content is one."""

    def __init__(self, scans: Sequence[HeldOutScan] = (), files: Sequence[HeldOutFile] = ()):
        self.scans = tuple(scans)
        self.files = tuple(files)
        self._hashes: dict[Path, str] = {}

    def __bool__(self) -> bool:
        return bool(self.scans or self.files)

    def _hash(self, path: Path) -> str:
        key = path.resolve()
        if key not in self._hashes:
            self._hashes[key] = file_sha256(key)
        return self._hashes[key]

    def match(self, path: str | Path) -> HeldOutScan | None:
        """The held-out scan whose content `path` holds, or None."""
        path = Path(path)
        size = path.stat().st_size
        sizes = [s for s in self.scans if s.size == size]
        files = [f for f in self.files if f.size == size]
        if not sizes and not files:
            return None
        digest = self._hash(path)
        for s in sizes:
            if s.sha256 == digest:
                return s
        for f in files:
            if f.path.resolve() == path.resolve() or self._hash(f.path) == digest:
                return HeldOutScan(digest, size, str(f.path), f.source)
        return None

    def held_out(self, paths: Iterable[str | Path]) -> list[Path]:
        """The paths that are held-out scans, in order."""
        return [Path(p) for p in paths if self.match(p) is not None]

    def check(self, paths: Iterable[str | Path], what: str) -> None:
        """FalsifyError naming the first path that is a held-out scan: `what` (a command's data,
        say `fit-world's scans`) may never hold one."""
        for p in paths:
            hit = self.match(p)
            if hit is not None:
                same = "" if Path(hit.name).resolve() == Path(p).resolve() else (
                    f", the same bytes as {hit.name}")
                raise FalsifyError(f"{p}: a held-out scan ({hit.source}{same}) is only ever "
                                   f"reported on; {what} may not hold it")


def load_manifest(path: str | Path) -> Holdout:
    """The held-out scans a split manifest names; FalsifyError naming the file or key at
    fault."""
    path = Path(path)
    if not path.exists():
        raise FalsifyError(f"{path}: no such split manifest")
    raw = parse_toml(read_bytes(path, "split manifest"), path, "TOML split manifest")
    extra = sorted(set(raw) - {"holdout"})
    if extra or not isinstance(raw.get("holdout"), dict):
        raise FalsifyError(f"{path}: {'unknown key ' + repr(extra[0]) if extra else 'no'} "
                           "[holdout] table; a split manifest holds [holdout] with sequences, "
                           "paths and [[holdout.scan]] entries")
    table = raw["holdout"]
    unknown = sorted(set(table) - {"sequences", "paths", "scan"})
    if unknown:
        raise FalsifyError(f"{path}: holdout.{unknown[0]}: unknown key; allowed: sequences, "
                           "paths, scan")
    source = str(path)
    base = path.parent
    scans = [_scan_entry(e, path, i) for i, e in enumerate(_list(table, "scan", path, dict))]
    files: list[HeldOutFile] = []
    for q in _list(table, "sequences", path, str):
        found = sequence_dirs(base) or {}
        if q not in found:
            raise FalsifyError(f"{path}: holdout.sequences: {q!r} is not a sequence under "
                               f"{base} (found: {', '.join(found) or 'none'})")
        files += [HeldOutFile(f, f.stat().st_size, source) for f in sequence_files(found[q])]
    for p in _list(table, "paths", path, str):
        target = base / p
        if not target.exists():
            raise FalsifyError(f"{path}: holdout.paths: {p!r}: no such file or folder")
        found_files = [target] if target.is_file() else sorted(
            f for f in target.rglob("*") if f.suffix in SCAN_SUFFIXES)
        files += [HeldOutFile(f, f.stat().st_size, source) for f in found_files]
    return Holdout(scans, files)


def _list(table: dict, key: str, path: Path, kind: type) -> list:
    value = table.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, kind) for v in value):
        raise FalsifyError(f"{path}: holdout.{key}: expected a list of "
                           f"{'tables' if kind is dict else 'strings'}")
    return value


def _scan_entry(entry: dict, path: Path, i: int) -> HeldOutScan:
    where = f"{path}: holdout.scan[{i}]"
    digest, size, name = entry.get("sha256"), entry.get("bytes"), entry.get("name", "")
    if not isinstance(digest, str) or len(digest) != 64 or any(
            c not in "0123456789abcdef" for c in digest):
        raise FalsifyError(f"{where}.sha256: expected 64 lowercase hex digits")
    if isinstance(size, bool) or not isinstance(size, int) or size < 0:
        raise FalsifyError(f"{where}.bytes: expected the file's size in bytes (an integer)")
    if not isinstance(name, str):
        raise FalsifyError(f"{where}.name: expected a string")
    return HeldOutScan(digest, size, name or digest[:12], str(path))


def default_holdout(root: Path) -> Holdout:
    """A SemanticKITTI root's official split held out: its sequences 08 and 11-21."""
    found = sequence_dirs(root) or {}
    source = f"SemanticKITTI's official split under {root} (08, 11-21); a {MANIFEST_NAME} there " \
             "overrides it"
    return Holdout(files=[HeldOutFile(f, f.stat().st_size, source)
                          for q in SEMANTICKITTI_HELD_OUT if q in found
                          for f in sequence_files(found[q])])


def holdout_for(paths: Iterable[str | Path], manifests: Sequence[str | Path] = ()) -> Holdout:
    """The held-out scans that apply to `paths`: the manifests named, those in FALSIFY_HOLDOUT,
    and for each folder above a path its splits.toml or, on a SemanticKITTI root without one,
    the official split."""
    named = [*manifests, *filter(None, os.environ.get(HOLDOUT_VARIABLE, "").split(os.pathsep))]
    parts = [load_manifest(m) for m in named]
    seen: set[Path] = set()
    for p in paths:
        for folder in Path(p).resolve().parents:
            if folder in seen:
                break
            seen.add(folder)
            if (folder / MANIFEST_NAME).is_file():
                parts.append(load_manifest(folder / MANIFEST_NAME))
                break
            if (folder / "sequences").is_dir() and sequence_dirs(folder):
                parts.append(default_holdout(folder))
                break
    return Holdout([s for h in parts for s in h.scans], [f for h in parts for f in h.files])


def check_not_held_out(paths: Sequence[str | Path], manifests: Sequence[str | Path],
                       what: str) -> None:
    """FalsifyError naming the first of `paths` that a manifest (or a data root's own split)
    holds out."""
    holdout_for(paths, manifests).check(paths, what)


def check_each_once(paths: Sequence[str | Path], what: str) -> None:
    """FalsifyError naming a scan that `what` (say `fit-world's scans`) holds twice, by path or
    by content: a fit would weigh it double. Only files of equal size are hashed."""
    by_size: dict[int, list[Path]] = {}
    for p in map(Path, paths):
        by_size.setdefault(p.stat().st_size, []).append(p)
    for same_size in (g for g in by_size.values() if len(g) > 1):
        seen: dict[str, Path] = {}
        for p in same_size:
            first = seen.setdefault(file_sha256(p), p)
            if first is not p:
                same = "given twice" if p.resolve() == first.resolve() else \
                    f"the same bytes as {first}"
                raise FalsifyError(f"{p}: {same}; {what} take each scan once")


def _sampled_digest(path: Path, blocks: int = 8, block: int = 4096) -> tuple[int, str]:
    """A file's size and the SHA-256 of `blocks` blocks spread over it: equal for equal files,
    cheap enough for every training scan (a full hash confirms a match)."""
    size = path.stat().st_size
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for k in range(blocks):
            f.seek(max(0, (size - block) * k // max(1, blocks - 1)))
            digest.update(f.read(block))
    return size, digest.hexdigest()


def check_apart(trained: Sequence[str | Path], watched: Sequence[str | Path],
                what: str) -> None:
    """FalsifyError naming a scan of `watched` (say --val-data) that is one of `trained`, by
    path or by content: a checkpoint chosen on its own training scans is chosen on nothing."""
    by_path = {Path(p).resolve(): Path(p) for p in trained}
    for p in map(Path, watched):
        if p.resolve() in by_path:
            raise FalsifyError(f"{what} {p}: also a --data scan ({by_path[p.resolve()]}); "
                               "validate on scans the training does not see")
    wanted: dict[tuple[int, str], Path] = {_sampled_digest(Path(p)): Path(p) for p in watched}
    for t in map(Path, trained):
        v = wanted.get(_sampled_digest(t))
        if v is not None and file_sha256(v) == file_sha256(t):
            raise FalsifyError(f"{what} {v}: the same bytes as --data scan {t}; validate on "
                               "scans the training does not see")


def scans_under(paths: Sequence[str | Path], sequences: list[str] | None = None
                ) -> list[tuple[Path, str]]:
    """(file, name) of every scan the paths name: .npy and .bin files, folders of them and
    SemanticKITTI roots (only `sequences`, when given); names are relative to the folder that
    holds each path as given (links kept), so a manifest says no more of where its data sits."""
    from falsify.world.real_scans import real_scans
    out: list[tuple[Path, str]] = []
    for p in map(Path, paths):
        if not p.exists():
            raise FalsifyError(f"{p}: no such file or folder")
        npys = [p] if p.suffix == ".npy" else npy_files(p) if p.is_dir() else []
        files = npys or [f for _, f, _, _ in real_scans([str(p)], sequences
                                                         if sequence_dirs(p) else None)]
        base = Path(os.path.abspath(p)).parent
        out += [(f, Path(os.path.abspath(f)).relative_to(base).as_posix()) for f in files]
    return out


# What a TOML basic string or comment may not hold raw: control characters but tab (TOML 1.0).
_TOML_CONTROL = re.compile("[\x00-\x08\x0a-\x1f\x7f]")


def toml_string(text: str) -> str:
    """`text` as a TOML basic string (TOML 1.0). Not json.dumps: JSON writes a character beyond
    U+FFFF as a surrogate pair (\\ud83d\\ude00), which TOML refuses, so the manifest of a file
    named so could not be read back. A name's undecoded bytes (surrogateescape, as an ASCII
    locale decodes a UTF-8 name) are decoded as UTF-8; what is not UTF-8 becomes U+FFFD."""
    try:
        raw = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:   # a surrogate no file system decoding made
        raw = text.encode("utf-8", "surrogatepass")
    text = raw.decode("utf-8", "replace")
    text = text.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + _TOML_CONTROL.sub(lambda m: f"\\u{ord(m.group()):04x}", text) + '"'


def manifest_text(scans: Sequence[tuple[Path, str]], note: str = "") -> str:
    """A split manifest holding out `scans` ((file, name) pairs) by content (sha256, size)."""
    lines = ["# Held-out scans: only ever reported on; falsify refuses to fit, train or choose",
             "# on them (matched by content, wherever they are)."]
    lines += [f"# {_TOML_CONTROL.sub(' ', line)}" for line in note.splitlines()]
    lines += ["[holdout]", ""]
    for p, name in scans:
        lines += ["[[holdout.scan]]", f"name = {toml_string(name)}",
                  f'sha256 = "{file_sha256(p)}"', f"bytes = {p.stat().st_size}", ""]
    return "\n".join(lines)
