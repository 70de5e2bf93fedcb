"""Import a script of the repository (``bench/*.py``, ``scripts/*.py``) as a module, and the benchmarks'
shared helpers (``bench/common``), for tests."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Iterator

ROOT = Path(__file__).resolve().parents[1]


@contextmanager
def script_module(relative: str, name: str) -> Iterator[ModuleType]:
    """The script ``ROOT/relative`` imported as module ``name``: registered in ``sys.modules`` (its
    dataclasses look their module up there) and with its folder first on ``sys.path`` (as when it
    runs, so it imports its neighbours); both are undone on exit."""
    path = ROOT / relative
    folder = str(path.parent)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, folder)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.modules.pop(name, None)
        sys.path.remove(folder)


def bench_module(name: str) -> ModuleType:
    """``bench/common/<name>.py`` imported as ``common.<name>``, as a benchmark script imports it: ``bench/``
    goes on ``sys.path`` (and stays, so the helpers' own imports of each other resolve)."""
    bench = str(ROOT / "bench")
    if bench not in sys.path:
        sys.path.append(bench)
    return importlib.import_module(f"common.{name}")
