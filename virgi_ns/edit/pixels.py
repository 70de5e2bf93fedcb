"""The edited view's pixels as sparse linear maps of per-Gaussian colours, split into batches.

Geometry is frozen, so a view's pixels are ``A C + T bg`` with ``A`` fixed
(:mod:`virgi_ns.raster.contract`). :func:`pixel_batches` cuts the view into random pixel sets,
each with its own rows of ``A`` as a CSR matrix and its transpose; :class:`SparseRender` applies
``A`` with the transpose precomputed for the backward pass, so no scatter with atomics runs.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from virgi_ns.raster import Contributions


class SparseRender(torch.autograd.Function):
    """``A @ C`` with ``A`` a constant CSR matrix; the backward pass uses a precomputed ``A^T``
    (CSR too), so no scatter with atomics runs in either direction."""

    @staticmethod
    def forward(ctx, colours: Tensor, A: Tensor, At: Tensor) -> Tensor:  # type: ignore[override]
        ctx.At = At
        return A @ colours

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        return ctx.At @ grad.contiguous(), None, None


def _csr(rows: Tensor, cols: Tensor, vals: Tensor, shape: tuple[int, int]) -> Tensor:
    """CSR matrix from entries already sorted by row."""
    crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=shape[0]), 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.sparse_csr_tensor(crow, cols, vals, shape, check_invariants=False)


@dataclass
class PixelBatch:
    A: Tensor  # [p, U] CSR
    At: Tensor  # [U, p] CSR
    background: Tensor  # [p, 3] T * bg
    target: Tensor  # [p, 3]
    weight: Optional[Tensor] = None  # [p] per-pixel loss weights summing to 1 (None: the plain mean)
    pixels: Optional[Tensor] = None  # [p] the view's pixels in this batch (None: all, in order)


def _group_weights(changed: Optional[Tensor], share: float) -> Optional[Tensor]:
    """Per-pixel loss weights [p] summing to 1: the ``changed`` pixels carry ``share`` of the loss and
    the others the rest, whatever their numbers (all of it when one group is empty)."""
    if changed is None:
        return None
    n_c = int(changed.sum())
    n_u = changed.numel() - n_c
    if n_c == 0 or n_u == 0:
        return torch.full(changed.shape, 1.0 / max(changed.numel(), 1), device=changed.device)
    return torch.where(changed, share / n_c, (1.0 - share) / n_u).float()


def pixel_batches(contrib: Contributions, target: Tensor, bg: Tensor, n_batches: int, seed: int,
                   changed: Optional[Tensor] = None, share: float = 0.5) -> list[PixelBatch]:
    """Split the view's pixels into ``n_batches`` random, equally sized sets, each with its own
    rows of ``A`` (pixels ascending within a set) and its own ``A^T``. With ``changed`` [P] (the
    pixels an edit changed) the changed and the other pixels are each spread evenly over the sets,
    and within every set the changed ones carry ``share`` of the loss (:func:`_group_weights`)."""

    dev, dt = target.device, target.dtype
    P = contrib.num_pixels
    U = int(contrib.pair_gaussian.shape[0])
    # int64 indices: backends may hand int32 (CUDA), and the CSR index arrays must share one dtype
    if n_batches == 1:  # the whole image: entries are already grouped by pixel
        pix, pair = contrib.pixel.to(dev).long(), contrib.pair.to(dev).long()
        w = contrib.weight.detach().to(dev, dt)
        t_order = torch.argsort(pair * P + pix)
        T = contrib.transmittance.detach().to(dev, dt)
        return [PixelBatch(_csr(pix, pair, w, (P, U)), _csr(pair[t_order], pix[t_order], w[t_order], (U, P)),
                            T[:, None] * bg[None, :], target, _group_weights(changed, share))]
    # drawn on the view's device (a CPU permutation of a megapixel view costs tens of milliseconds)
    gen = torch.Generator(device=dev).manual_seed(seed)
    batch_of = torch.empty(P, dtype=torch.long, device=dev)
    if changed is None:
        batch_of[torch.randperm(P, generator=gen, device=dev)] = torch.arange(P, device=dev) % n_batches
    else:  # stratified: each set gets its part of the changed pixels and of the others
        ch = changed.to(dev)
        for idx in (ch.nonzero().flatten(), (~ch).nonzero().flatten()):
            perm = torch.randperm(len(idx), generator=gen, device=dev)
            batch_of[idx[perm]] = torch.arange(len(idx), device=dev) % n_batches
    # local row of each pixel: its rank among its batch's pixels, in ascending pixel order
    order = torch.argsort(batch_of, stable=True)
    counts = torch.bincount(batch_of, minlength=n_batches)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.empty(P, dtype=torch.long, device=dev)
    local[order] = torch.arange(P, device=dev) - starts[batch_of[order]]
    pix, pair = contrib.pixel.to(dev).long(), contrib.pair.to(dev).long()
    w = contrib.weight.detach().to(dev, dt)
    eb = batch_of[pix]
    e_order = torch.argsort(eb, stable=True)  # entries stay in pixel order within a batch
    e_counts = torch.bincount(eb, minlength=n_batches).tolist()
    T = contrib.transmittance.detach().to(dev, dt)
    out = []
    e0 = 0
    for b in range(n_batches):
        sel = e_order[e0 : e0 + e_counts[b]]
        e0 += e_counts[b]
        rows, cols, vals = local[pix[sel]], pair[sel], w[sel]
        p_b = int(counts[b])
        A = _csr(rows, cols, vals, (p_b, U))
        t_order = torch.argsort(cols * max(p_b, 1) + rows)
        At = _csr(cols[t_order], rows[t_order], vals[t_order], (U, p_b))
        pixels = order[int(starts[b]) : int(starts[b]) + p_b]
        out.append(PixelBatch(A, At, T[pixels, None] * bg[None, :], target[pixels],
                               None if changed is None else _group_weights(changed[pixels], share), pixels))
    return out



__all__ = ["PixelBatch", "SparseRender", "pixel_batches"]
