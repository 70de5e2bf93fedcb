"""Work-arounds, applied on import, for nerfstudio 1.1.5 on today's torch.

Checkpoints: since torch 2.6, ``torch.load`` defaults to ``weights_only=True``, which refuses any global
that is not allow-listed. nerfstudio's learning-rate schedulers compute their factors with numpy, so the
learning rates stored in a checkpoint (optimizer ``param_groups[*]["lr"]`` and scheduler ``_last_lr``) are
``numpy.float64`` scalars. Unpickling one needs exactly three globals: numpy's scalar reconstructor,
``numpy.dtype`` and the float64 dtype class. We allow those and nothing else, so ``ns-eval``,
``ns-viewer``, ``ns-render`` and ``--load-dir`` keep safe loading and need no environment variable.

This module is imported by our method configs and our dataparser, and nerfstudio imports every
registered entry point while discovering methods and dataparsers, so the allow-list is in place before
any nerfstudio command loads a checkpoint.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable, List, Tuple, Union

import numpy as np
import torch

# The module paths numpy's scalar reconstructor is pickled under: numpy 1.x writes ``numpy.core``,
# numpy 2.x writes ``numpy._core``. A checkpoint written with either must load with either.
_SCALAR_PATHS = ("numpy.core.multiarray.scalar", "numpy._core.multiarray.scalar")


def _numpy_scalar_reconstructor() -> Callable[..., Any]:
    """numpy's ``multiarray.scalar`` without touching the deprecated ``numpy.core`` alias on numpy 2."""
    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            return importlib.import_module(module).scalar
        except (ImportError, AttributeError):
            continue
    raise ImportError("numpy's multiarray.scalar was not found")


def checkpoint_safe_globals() -> List[Union[Callable[..., Any], Tuple[Callable[..., Any], str]]]:
    """The numpy globals a nerfstudio checkpoint needs, each under every name it may be pickled as."""
    scalar = _numpy_scalar_reconstructor()
    entries: List[Union[Callable[..., Any], Tuple[Callable[..., Any], str]]] = [(scalar, p) for p in _SCALAR_PATHS]
    entries.append(np.dtype)
    entries.append(type(np.dtype(np.float64)))  # numpy.dtypes.Float64DType (numpy >= 1.25)
    return entries


def _weights_only_is_default() -> bool:
    """True on torch versions whose ``torch.load`` defaults to safe (weights-only) loading."""
    return hasattr(torch.serialization, "add_safe_globals")


def apply() -> None:
    """Allow-list the numpy globals of nerfstudio checkpoints for ``torch.load`` (idempotent)."""
    if _weights_only_is_default():
        torch.serialization.add_safe_globals(checkpoint_safe_globals())


apply()
