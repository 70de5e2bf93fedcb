"""The edit stack's manifest (``<run>/edits/stack.json``) read and changed without torch.

The manifest holds the order of the edits, their enable flags, the specular strength ``k`` and the
run's fingerprint; since it also holds each edit's ``info`` (steps, timings), listing a stack and
undoing, resetting, enabling or disabling its edits touch only this file and the edit files' names.
``virgi-edit list|undo|reset|enable|disable|specular`` use it, so a fresh process imports neither
torch nor nerfstudio for them. :class:`virgi_ns.edit.stack.EditStack` reads and writes the same file
through :func:`read_manifest` and :func:`write_manifest`.

Every change writes the manifest first (atomically) and removes files after, so an interrupted
command leaves at worst an unused edit file, never a manifest naming a missing one.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from virgi_ns.errors import InputError, atomic_path

MANIFEST = "stack.json"
EDITS_DIR = "edits"
MANIFEST_FORMAT = "virgi-edit-stack"

__all__ = ["EDITS_DIR", "MANIFEST", "Manifest", "edits_dir", "read_manifest", "remove_edit_files", "write_manifest"]


def edits_dir(run_dir: str | Path) -> Path:
    """Where a run's edits live: ``<run>/edits``."""
    return Path(run_dir) / EDITS_DIR


@dataclass
class Manifest:
    """The stack as its manifest records it: ``entries`` are dicts with ``file``, ``enabled``,
    ``image``, ``camera`` and (written since it was added) ``info``."""

    directory: Path
    fingerprint: str = ""
    specular_strength: float = 1.0
    entries: list[dict] = field(default_factory=list)
    exists: bool = False
    """Whether the file was there when read."""

    # ------------------------------------------------------------- operations
    def _index(self, number: int) -> int:
        n = len(self.entries)
        if not 1 <= number <= n:
            raise InputError(f"no edit number {number}: the stack holds {n} edit(s)" + (f" (1..{n})" if n else ""))
        return number - 1

    def undo(self) -> dict:
        """Remove the last edit (manifest first, then its files); returns its entry."""
        if not self.entries:
            raise InputError("nothing to undo: the edit stack is empty")
        last = self.entries.pop()
        self.write()
        remove_edit_files(self.directory, last["file"])
        return last

    def reset(self) -> int:
        """Remove every edit and set ``k`` back to 1; returns how many were removed."""
        files = [e["file"] for e in self.entries]
        self.entries = []
        self.specular_strength = 1.0
        self.write()
        for f in files:
            remove_edit_files(self.directory, f)
        return len(files)

    def set_enabled(self, number: int, enabled: bool) -> None:
        self.entries[self._index(number)]["enabled"] = bool(enabled)
        self.write()

    def set_specular_strength(self, k: float) -> None:
        if not (k >= 0.0 and k < float("inf")):
            raise InputError(f"specular strength must be a finite number >= 0, got {k}")
        self.specular_strength = float(k)
        self.write()

    def write(self) -> None:
        write_manifest(self.directory, self.fingerprint, self.specular_strength, self.entries)


def read_manifest(run_dir: str | Path) -> Manifest:
    """The manifest of ``<run_dir>/edits`` (an empty one when there is none); one that cannot be
    read raises :class:`InputError`."""
    d = edits_dir(run_dir)
    path = d / MANIFEST
    if not path.is_file():
        return Manifest(d)
    try:
        m = json.loads(path.read_text())
        entries = [dict(it) for it in m["edits"]]
        for it in entries:
            it["file"] = str(it["file"])
            it["enabled"] = bool(it.get("enabled", True))
        k = float(m.get("specular_strength", 1.0))
        fp = str(m["fingerprint"])
    except Exception as e:  # noqa: BLE001 - any unreadable manifest is the same user error
        raise InputError(f"{path} is not a virgi edit stack ({type(e).__name__})") from None
    return Manifest(d, fp, k, entries, True)


def write_manifest(directory: Path, fingerprint: str, specular_strength: float, entries: list[dict]) -> None:
    """Write ``stack.json`` atomically (never half-written; the previous one survives a failure)."""
    m = {"format": MANIFEST_FORMAT, "version": 1, "fingerprint": fingerprint, "specular_strength": specular_strength,
         "edits": entries}
    with atomic_path(Path(directory) / MANIFEST) as tmp:
        tmp.write_text(json.dumps(m, indent=1))


def remove_edit_files(directory: Path, file: str) -> None:
    """An edit's file and the pictures saved beside it (``<stem>_*.png``, a pick's)."""
    directory = Path(directory)
    (directory / file).unlink(missing_ok=True)
    for p in directory.glob(f"{Path(file).stem}_*.png"):
        p.unlink(missing_ok=True)
