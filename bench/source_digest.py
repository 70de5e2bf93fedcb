"""The digest of the project's source files, recorded beside each GPU result: which code made the figures
where git cannot say it. The GPU machine runs a copy of the working tree whose git HEAD stays the
session's first, so the ``commit`` a result records there can be older than its code.

    python bench/source_digest.py            # this working tree's digest
    python bench/source_digest.py PATH       # another checkout's (e.g. a ``git worktree`` of a commit)

Two trees with the same digest hold the same source files, byte for byte."""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path
from typing import Optional

SOURCE_DIRS = ("virgi_ns", "csrc", "bench", "method_configs")
"""The folders whose files make a figure (the package, its CUDA sources, the benchmarks, the method's config)."""
SOURCE_SUFFIXES = (".py", ".cu", ".cuh", ".cpp", ".h", ".sh")


def source_digest(root: Optional[Path] = None) -> str:
    """sha256 over every source file's path (relative to ``root``, the project) and bytes, in path order;
    its first 16 hex digits."""
    root = Path(root) if root is not None else Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    files = sorted(p for d in SOURCE_DIRS if (root / d).is_dir() for p in (root / d).rglob("*")
                   if p.is_file() and p.suffix in SOURCE_SUFFIXES and "__pycache__" not in p.parts)
    for p in files:
        rel = p.relative_to(root).as_posix().encode()
        data = p.read_bytes()
        h.update(len(rel).to_bytes(8, "little") + rel + len(data).to_bytes(8, "little") + data)
    return h.hexdigest()[:16]


if __name__ == "__main__":
    print(source_digest(Path(sys.argv[1]) if len(sys.argv) > 1 else None))
