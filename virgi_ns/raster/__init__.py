"""Frozen-geometry rasterizer: contribution lists for whole images or tile batches.

``rasterize`` picks a backend: ``"cuda"`` (our kernels in ``csrc/``) when a GPU is present and
the extension builds, otherwise ``"reference"`` (pure torch, the specification), with one notice.
"""

from __future__ import annotations

import sys

import torch
from torch import Tensor

from virgi_ns.raster.contract import Cameras, Contributions, Request, composite, composite_depth, expected_depth

__all__ = ["Cameras", "Contributions", "Request", "composite", "composite_depth", "expected_depth", "rasterize", "resolve_backend"]

_NOTICE_GIVEN = False


def _notice(message: str) -> None:
    print(f"virgi-ns: {message}", file=sys.stderr)


def resolve_backend(backend: str, device: torch.device) -> str:
    """'auto' -> 'cuda' when the tensors are on a GPU and our extension loads, else 'reference'."""
    global _NOTICE_GIVEN
    if backend not in ("auto", "reference", "cuda"):
        raise ValueError(f"unknown rasterizer backend {backend!r} (auto, reference or cuda)")
    if backend == "reference":
        return backend
    if device.type != "cuda":
        if backend == "cuda":
            raise RuntimeError("the cuda rasterizer backend needs the Gaussians on a CUDA device")
        if not _NOTICE_GIVEN:
            _NOTICE_GIVEN = True
            _notice("no GPU in use; rendering with the torch reference rasterizer (exact, slow)")
        return "reference"
    from virgi_ns.raster import cuda as cuda_backend

    ok, why = cuda_backend.available()
    if ok:
        return "cuda"
    if backend == "cuda":
        raise RuntimeError(f"the cuda rasterizer backend is unavailable: {why}")
    if not _NOTICE_GIVEN:
        _NOTICE_GIVEN = True
        _notice(f"CUDA rasterizer unavailable ({why}); using the torch reference")
    return "reference"


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, cameras: Cameras, request: Request,
              backend: str = "auto") -> Contributions:
    """Contributions of N Gaussians to the pixels of ``request``.

    ``means`` [N,3]; ``quats`` [N,4] wxyz (normalised inside); ``scales`` [N,3] standard
    deviations (already exponentiated); ``opacities`` [N] in [0,1] (already sigmoided).
    """
    which = resolve_backend(backend, means.device)
    if which == "cuda":
        from virgi_ns.raster import cuda as cuda_backend

        return cuda_backend.rasterize(means, quats, scales, opacities, cameras, request)
    from virgi_ns.raster import reference

    return reference.rasterize(means, quats, scales, opacities, cameras, request)
