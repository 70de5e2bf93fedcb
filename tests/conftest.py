"""Shared test fixtures and rules.

- **Real data** (``../shared/data`` beside the checkout, or the folder ``$VIRGI_SHARED_DATA`` names):
  only through the :func:`shared_data` fixture, which skips a test where a file it needs is absent.
  Every test using it is marked ``shared_data`` (``test_clone.py`` re-runs them with the folder empty
  and missing), and a test that opens or lists anything in that folder without the fixture fails:
  a clone has no such folder.
- **The venv's commands**: :func:`venv_command` finds them beside ``sys.executable``.
- **GPU tests** (``-m gpu``) skip without a CUDA GPU.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path
from typing import Optional

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA_ENV = "VIRGI_SHARED_DATA"


def shared_data_root() -> Path:
    """Where the real data is looked for: ``$VIRGI_SHARED_DATA``, else ``../shared/data`` beside the checkout."""
    env = os.environ.get(SHARED_DATA_ENV)
    return Path(env) if env else REPO.parent / "shared" / "data"


class SharedData:
    """The real captures and splats (:func:`shared_data_root`). ``need("fern/poses_bounds.npy",
    "fern/images_8")`` returns the first path and skips the test unless every one exists;
    ``shared_data / "fern"`` is ``need("fern")``."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def need(self, first: str, *more: str) -> Path:
        missing = [p for p in (first, *more) if not (self.root / p).exists()]
        if missing:
            pytest.skip(f"real data not found: {self.root / missing[0]}")
        return self.root / first

    def __truediv__(self, part: str) -> Path:
        return self.need(part)


@pytest.fixture(scope="session")
def shared_data() -> SharedData:
    """The real data beside the checkout; each test names the files it needs (see :class:`SharedData`)."""
    return SharedData(shared_data_root())


def venv_command(name: str, module: Optional[str] = None) -> list[str]:
    """The command line of the venv's console script ``name`` (beside ``sys.executable``), else
    ``python -m module``; skips the test where neither exists."""
    exe = Path(sys.executable).with_name(name)
    if exe.is_file():
        return [str(exe)]
    if module is not None:
        return [sys.executable, "-m", module]
    pytest.skip(f"{name} is not installed beside {sys.executable}")


# ------------------------------------------------------------ who may read the real data
_state = threading.local()
_current: dict = {"item": None}
_ROOTS: tuple[str, ...] = ()


def _watched_roots() -> tuple[str, ...]:
    root = shared_data_root()
    out = {str(root.absolute())}
    try:
        out.add(str(root.resolve()))
    except OSError:
        pass
    return tuple(sorted(p.rstrip(os.sep) + os.sep for p in out))


def _audit(event: str, args: tuple) -> None:
    """Refuse opening or listing anything under the real data's folder outside a test that asked
    for it (through :func:`shared_data`)."""
    if event not in ("open", "os.listdir", "os.scandir") or not _ROOTS or not args:
        return
    path = args[0]
    if isinstance(path, int) or path is None:
        return
    if getattr(_state, "inside", False):
        return
    _state.inside = True
    try:
        p = os.fsdecode(path)
        if not os.path.isabs(p):
            p = os.path.abspath(p)
        if not (p + os.sep).startswith(_ROOTS):
            return
        item = _current["item"]
        if item is not None and "shared_data" in item.keywords:
            return
        who = item.nodeid if item is not None else "collection"
        raise RuntimeError(f"{who} reads {p} without the shared_data fixture: a clone has no "
                           f"{shared_data_root()} (ask for the files through shared_data, or use the bundled scene)")
    finally:
        _state.inside = False


def pytest_configure(config) -> None:
    global _ROOTS
    _ROOTS = _watched_roots()
    if not getattr(sys, "_virgi_audit_installed", False):  # audit hooks cannot be removed: one per process
        sys.addaudithook(_audit)
        sys._virgi_audit_installed = True  # type: ignore[attr-defined]


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item) -> None:
    _current["item"] = item


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem) -> None:
    _current["item"] = None


def pytest_collection_modifyitems(config, items):
    skip_gpu = pytest.mark.skip(reason="needs a CUDA GPU")
    gpu = torch.cuda.is_available()
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.shared_data)
        if not gpu and "gpu" in item.keywords:
            item.add_marker(skip_gpu)
