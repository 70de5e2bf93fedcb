"""Which base run an edit belongs to: a short hash of its frozen Gaussians and colour field, the same on any
device, that every edit file and ``stack.json`` carry (an edit of another run is refused)."""

from __future__ import annotations

import hashlib
from typing import Iterable

import torch
from torch import Tensor, nn


def run_fingerprint(tensors: Iterable[Tensor], samples: int = 1 << 16) -> str:
    """A short hash of a base run: shapes, dtypes and a strided sample of every tensor (the frozen
    geometry and the colour field's state). Equal runs give equal fingerprints on any device."""
    h = hashlib.sha256()
    for t in tensors:
        t = t.detach()
        h.update(f"{tuple(t.shape)}|{str(t.dtype)}|".encode())
        flat = t.reshape(-1)
        stride = max(1, flat.numel() // samples)
        sample = flat[::stride][:samples].to("cpu", torch.float64)
        h.update(sample.numpy().tobytes())
    return h.hexdigest()[:16]


def field_fingerprint(means: Tensor, field_module: nn.Module, extra: Iterable[Tensor] = ()) -> str:
    """Fingerprint of frozen means + every tensor of the colour field's state dict (+ ``extra``)."""
    sd = field_module.state_dict()
    return run_fingerprint([means, *extra, *(sd[k] for k in sorted(sd))])


__all__ = ["field_fingerprint", "run_fingerprint"]
