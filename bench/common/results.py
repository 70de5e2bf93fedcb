"""Where a benchmark's figures come from, and how they are written.

- :func:`git_commit`: the checkout's git HEAD. On the GPU machine it is the session's first HEAD, whatever
  tree was sent, so a result also records
- :func:`source_digest`: a digest of the source files that ran; two trees with the same digest hold the same
  source files, byte for byte (``python bench/common/results.py [CHECKOUT]`` prints a checkout's).
- :func:`write_json`: a result written atomically.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path
from typing import Optional

from virgi_ns.errors import atomic_path

ROOT = Path(__file__).resolve().parents[2]
SOURCE_DIRS = ("virgi_ns", "csrc", "bench", "method_configs")
"""The folders whose files make a figure (the package, its CUDA sources, the benchmarks, the method's config)."""
SOURCE_SUFFIXES = (".py", ".cu", ".cuh", ".cpp", ".h", ".sh")


def source_digest(root: Optional[Path] = None) -> str:
    """sha256 over every source file's path (relative to ``root``, default this checkout) and bytes, in path
    order; its first 16 hex digits."""
    root = Path(root) if root is not None else ROOT
    h = hashlib.sha256()
    files = sorted(p for d in SOURCE_DIRS if (root / d).is_dir() for p in (root / d).rglob("*")
                   if p.is_file() and p.suffix in SOURCE_SUFFIXES and "__pycache__" not in p.parts)
    for p in files:
        rel = p.relative_to(root).as_posix().encode()
        data = p.read_bytes()
        h.update(len(rel).to_bytes(8, "little") + rel + len(data).to_bytes(8, "little") + data)
    return h.hexdigest()[:16]


def git_commit() -> Optional[str]:
    """The checkout's git commit (None outside a git checkout)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, cwd=ROOT)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def provenance() -> dict:
    """``commit`` and ``source_digest``, for a result's JSON."""
    return {"commit": git_commit(), "source_digest": source_digest()}


def safe_name(text: str, keep: str = "._") -> str:
    """``text`` as a file name: every character but letters, digits and ``keep`` written as '_'."""
    return "".join(ch if ch.isalnum() or ch in keep else "_" for ch in text)


def write_json(path: Path, result: dict, console=None) -> None:
    """``result`` as indented JSON at ``path`` (folders made, written atomically); ``console`` says so."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1, default=float))
    if console is not None:
        console.print(f"wrote {path}")


if __name__ == "__main__":
    print(source_digest(Path(sys.argv[1]) if len(sys.argv) > 1 else None))
