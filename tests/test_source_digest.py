"""bench/common/results.py: the source digest follows the source files' paths and bytes and nothing else."""

from __future__ import annotations

import hashlib

from script_module import bench_module


def test_the_digest_follows_source_files_only(tmp_path):
    sd = bench_module("results")
    (tmp_path / "virgi_ns" / "__pycache__").mkdir(parents=True)
    (tmp_path / "csrc").mkdir()
    (tmp_path / "virgi_ns" / "a.py").write_bytes(b"x = 1\n")
    (tmp_path / "csrc" / "k.cu").write_bytes(b"// k\n")
    first = sd.source_digest(tmp_path)
    # independently: sha256 over (length, path, length, bytes) of each file in path order
    h = hashlib.sha256()
    for rel, data in (("csrc/k.cu", b"// k\n"), ("virgi_ns/a.py", b"x = 1\n")):
        h.update(len(rel).to_bytes(8, "little") + rel.encode() + len(data).to_bytes(8, "little") + data)
    assert first == h.hexdigest()[:16]
    # neither results, caches, other folders nor other kinds of file move it
    (tmp_path / "virgi_ns" / "__pycache__" / "a.cpython-311.pyc").write_bytes(b"\0")
    (tmp_path / "virgi_ns" / "notes.md").write_text("notes")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "b.py").write_text("y = 2")
    assert sd.source_digest(tmp_path) == first
    # a byte of a source file does, and so does a file's name
    (tmp_path / "virgi_ns" / "a.py").write_bytes(b"x = 2\n")
    assert sd.source_digest(tmp_path) != first
    (tmp_path / "virgi_ns" / "a.py").write_bytes(b"x = 1\n")
    (tmp_path / "virgi_ns" / "a.py").rename(tmp_path / "virgi_ns" / "b.py")
    assert sd.source_digest(tmp_path) != first
