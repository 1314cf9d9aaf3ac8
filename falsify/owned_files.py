"""The list a command keeps of the files it wrote into a folder it shares with the user: each
name with its SHA-256, so that a later run replaces or removes only its own files, never a
user's file that happens to bear one of its names."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from falsify.errors import FalsifyError
from falsify.fileio import file_sha256, write_bytes, write_json


@dataclass(frozen=True)
class FileList:
    """A command's list file in its output folder: `{key: {file name: sha256}, ...header}`."""

    name: str       # the list's own file name, e.g. "calib-overlays.json"
    key: str        # the JSON key that holds the files, e.g. "overlays"
    command: str    # who writes it, for messages, e.g. "falsify calib"
    option: str = "--out"

    def read(self, out: Path) -> dict[str, str]:
        """The files an earlier run listed in `out` ({} when none did); FalsifyError when the
        list is not one this command wrote."""
        path = out / self.name
        if not path.exists():
            return {}
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:   # ValueError: undecodable text or bad JSON
            raise FalsifyError(f"{self.option} {path}: not a readable list of the files "
                               f"`{self.command}` wrote ({exc}); move it away (the files it "
                               f"lists are then kept) or give another {self.option}") from None
        files = raw.get(self.key) if isinstance(raw, dict) else None
        if not isinstance(files, dict) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in files.items()):
            raise FalsifyError(f"{self.option} {path}: expected {{\"{self.key}\": {{file name: "
                               f"sha256}}}} as `{self.command} {self.option}` writes it; move it "
                               f"away (the files it lists are then kept) or give another "
                               f"{self.option}")
        return files

    def check_targets(self, out: Path, names: Iterable[str], listed: dict[str, str]) -> None:
        """Refuse, before any work, a name this run will write that is held by a file the
        command did not write there (not listed, or changed since)."""
        for name in names:
            path = out / name
            if not (path.exists() or path.is_symlink()):
                continue
            if not _is_as_written(path, listed.get(name)):
                raise FalsifyError(f"{self.option} {out}: {name} is there and is not a file "
                                   f"`{self.command}` wrote (not in {self.name}, or changed "
                                   f"since); it would be overwritten: move it or give another "
                                   f"{self.option}")

    def replace(self, out: Path, files: dict[str, bytes], listed: dict[str, str],
                header: dict | None = None) -> None:
        """Remove every listed file that is still as written, list the new files, then write
        them: a stop at any point leaves no earlier run's file beside this run's, and every
        file of ours listed with its bytes (a file listed but absent was not reached)."""
        left = {}
        for name, digest in listed.items():
            path = out / name
            if Path(name).name != name or name == self.name:
                continue
            try:
                if _is_as_written(path, digest):
                    path.unlink()
            except OSError:   # kept, and listed again, so a later run still knows it is ours
                left[name] = digest
        new = {name: hashlib.sha256(data).hexdigest() for name, data in files.items()}
        write_json(out / self.name, {**(header or {}),
                                     self.key: dict(sorted({**left, **new}.items()))})
        for name, data in files.items():
            write_bytes(out / name, data)


def _is_as_written(path: Path, digest: str | None) -> bool:
    """A plain file (no link) whose bytes are the listed ones."""
    return (digest is not None and path.is_file() and not path.is_symlink()
            and file_sha256(path) == digest)
