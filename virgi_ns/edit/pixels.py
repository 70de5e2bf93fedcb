"""The edited view's pixels as sparse linear maps of per-Gaussian colours, split into batches.

Geometry is frozen, so a view's pixels are ``A C + T bg`` with ``A`` fixed
(:mod:`virgi_ns.raster.contract`). :func:`pixel_batches` cuts the view into random pixel sets,
each with its own rows of ``A`` (:class:`CompositeOp`, which also holds what ``A^T`` needs for the
backward pass).

How a batch applies ``A`` (and ``A^T`` in the backward pass) is ``EditConfig.batch_composite``, one
of :data:`COMPOSITES` (or ``"FWD/BWD"``: one kind for each pass; ``"csr"`` on both, cuSPARSE with a
precomputed transpose, is the reference). Every kind is built once per batch
and then runs without a host sync and with shapes fixed, so a step can be recorded as a CUDA graph.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple, Optional

import torch
from torch import Tensor

from virgi_ns.raster import Contributions


COMPOSITES = {
    "csr": "cuSPARSE CSR x dense: A and a precomputed A^T, int64 indices (the original)",
    "csr32": "as csr with int32 indices (half the index traffic)",
    "csr4": "as csr32 with the dense operand padded to 4 columns (16-byte rows)",
    "csr_cm": "as csr32 with the dense operand column-major",
    "segment": "gather x[cols] * vals, then torch.segment_reduce over each row's entries (A^T: by Gaussian)",
    "index_add": "gather x[cols] * vals, then index_add_ by row (atomics; A^T: the same entries, by Gaussian)",
    "embedding_bag": "torch.embedding_bag, mode sum with per-sample weights: gather, weight and sum in one kernel",
}
"""The kinds of :attr:`EditConfig.batch_composite` (a name, or ``"FWD/BWD"`` for one kind per pass)."""

_CSR_KINDS = ("csr", "csr32", "csr4", "csr_cm")


AUTO_GPU = "segment/csr32"
"""What ``"auto"`` picks on a GPU: the fastest kinds that gave csr's edit in ``bench/edit_step.py``
(bench/RESULTS.md, "Edit"); on a CPU ``"auto"`` is ``"csr"``."""


def resolve_composite(name: str, device: torch.device) -> str:
    """``name`` with ``"auto"`` replaced by the kinds for ``device``."""
    if name != "auto":
        return name
    return AUTO_GPU if torch.device(device).type == "cuda" else "csr"


def parse_composite(name: str) -> tuple[str, str]:
    """``"segment"`` -> ``("segment", "segment")``; ``"embedding_bag/index_add"`` -> the forward and the
    backward kind. Raises ValueError for a kind not in :data:`COMPOSITES`."""
    if name == "auto":
        return parse_composite(AUTO_GPU)
    parts = str(name).split("/")
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or any(p not in COMPOSITES for p in parts):
        raise ValueError(f"EditConfig.batch_composite must be 'auto' or one of {', '.join(COMPOSITES)} (or 'FWD/BWD', "
                         f"one of them for each pass), got {name!r}")
    return parts[0], parts[1]


class _Side(NamedTuple):
    """One ordering of a sparse map's entries, out[target[j]] += vals[j] * x[gather[j]], out [n, k]."""

    n: int
    gather: Tensor  # [nnz] rows of x
    vals: Tensor  # [nnz]
    target: Optional[Tensor] = None  # [nnz] rows of out, sorted (segment, embedding_bag) or any (index_add)
    offsets: Optional[Tensor] = None  # [n+1] where each row of out starts (entries sorted by target)
    csr: Optional[Tensor] = None  # the map as a CSR matrix [n, len(x)]


def _apply(kind: str, side: _Side, x: Tensor) -> Tensor:
    """``out = M @ x`` for the map ``side`` by ``kind`` (no host sync, shapes fixed by ``side``)."""
    if kind in ("csr", "csr32"):
        return side.csr @ x
    if kind == "csr4":
        return (side.csr @ torch.nn.functional.pad(x, (0, 1)))[:, : x.shape[1]]
    if kind == "csr_cm":
        return side.csr @ x.t().contiguous().t()
    if side.gather.numel() == 0:  # no entry: nothing to gather (segment_reduce refuses empty data on some builds)
        return x.new_zeros(side.n, x.shape[1])
    if kind == "embedding_bag":
        return torch.embedding_bag(x, side.gather, side.offsets, False, 0, False, side.vals, True, None)[0]
    terms = x.index_select(0, side.gather) * side.vals[:, None]
    if kind == "segment":
        return torch.segment_reduce(terms, "sum", offsets=side.offsets, unsafe=True)
    if kind == "index_add":
        return x.new_zeros(side.n, x.shape[1]).index_add_(0, side.target, terms)
    raise ValueError(f"unknown composite kind {kind!r}")


class _BatchRender(torch.autograd.Function):
    """``A @ C`` by the operator's forward kind; the backward pass ``A^T @ grad`` by its backward kind."""

    @staticmethod
    def forward(ctx, colours: Tensor, op: "CompositeOp") -> Tensor:  # type: ignore[override]
        ctx.op = op
        return _apply(op.fwd, op.forward_side, colours)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        op = ctx.op
        return _apply(op.bwd, op.backward_side, grad.contiguous()), None


class CompositeOp:
    """A batch's constant ``A`` [p, U] applied by the kinds ``kind`` names (:func:`parse_composite`),
    with every index array the two passes need built here, once: ``op(C)`` is ``A @ C`` with an
    explicit backward. ``rows``, ``cols``, ``vals``: the entries, sorted by row (pixel)."""

    def __init__(self, kind: str, rows: Tensor, cols: Tensor, vals: Tensor, p: int, U: int) -> None:
        self.kind = kind
        self.fwd, self.bwd = parse_composite(kind)
        self.shape = (p, U)
        nnz = rows.numel()
        small = max(nnz, p, U) < 2**31 - 1
        idx = torch.int64 if "csr" in (self.fwd, self.bwd) or not small else torch.int32
        rows, cols = rows.to(idx), cols.to(idx)
        crow = _offsets(rows, p, idx)
        if self.fwd == "index_add":
            self.forward_side = _Side(p, cols, vals, target=rows)
        else:
            self.forward_side = _Side(p, cols, vals, rows, crow,
                                      _csr_of(crow, cols, vals, (p, U)) if self.fwd in _CSR_KINDS else None)
        if self.bwd == "index_add":  # the same entries, the roles of rows and columns swapped
            self.backward_side = _Side(U, rows, vals, target=cols)
        else:  # the entries sorted by Gaussian (pixels ascending within one: rows are sorted already)
            t_order = torch.argsort(cols, stable=True)
            rows_t, cols_t, vals_t = rows[t_order], cols[t_order], vals[t_order]
            ccol = _offsets(cols_t, U, idx)
            self.backward_side = _Side(U, rows_t, vals_t, cols_t, ccol,
                                       _csr_of(ccol, rows_t, vals_t, (U, p)) if self.bwd in _CSR_KINDS else None)

    def __call__(self, colours: Tensor) -> Tensor:
        return _BatchRender.apply(colours, self)


def _offsets(sorted_rows: Tensor, n: int, dtype: torch.dtype) -> Tensor:
    """[n+1] start of each row's entries in ``sorted_rows`` (and the end)."""
    out = torch.zeros(n + 1, dtype=torch.long, device=sorted_rows.device)
    out[1:] = torch.cumsum(torch.bincount(sorted_rows, minlength=n), 0)
    return out.to(dtype)


def _csr_of(crow: Tensor, cols: Tensor, vals: Tensor, shape: tuple[int, int]) -> Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.sparse_csr_tensor(crow, cols, vals, shape, check_invariants=False)


@dataclass
class PixelBatch:
    op: CompositeOp  # the batch's A [p, U] and how it is applied
    background: Tensor  # [p, 3] T * bg
    target: Tensor  # [p, 3]
    weight: Optional[Tensor] = None  # [p] per-pixel loss weights summing to 1 (None: the plain mean)
    pixels: Optional[Tensor] = None  # [p] the view's pixels in this batch (None: all, in order)

    @property
    def composite(self) -> str:
        return self.op.kind

    def render(self, colours: Tensor) -> Tensor:
        """``A @ colours`` [p, 3] by the batch's composite kind, differentiable in ``colours``."""
        return self.op(colours)

    def render_transpose(self, grad: Tensor) -> Tensor:
        """``A^T @ grad`` [U, 3]: what :meth:`render`'s backward pass computes (for benchmarks)."""
        return _apply(self.op.bwd, self.op.backward_side, grad.contiguous())


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
                   changed: Optional[Tensor] = None, share: float = 0.5, composite: str = "csr") -> list[PixelBatch]:
    """Split the view's pixels into ``n_batches`` random, equally sized sets, each with its own
    rows of ``A`` (pixels ascending within a set) and its own ``A^T``. With ``changed`` [P] (the
    pixels an edit changed) the changed and the other pixels are each spread evenly over the sets,
    and within every set the changed ones carry ``share`` of the loss (:func:`_group_weights`).
    ``composite``: how each batch applies ``A`` (:data:`COMPOSITES`, :func:`parse_composite`)."""

    composite = resolve_composite(composite, target.device)
    parse_composite(composite)
    dev, dt = target.device, target.dtype
    P = contrib.num_pixels
    U = int(contrib.pair_gaussian.shape[0])
    # int64 indices: backends may hand int32 (CUDA), and the CSR index arrays must share one dtype
    if n_batches == 1:  # the whole image: entries are already grouped by pixel
        pix, pair = contrib.pixel.to(dev).long(), contrib.pair.to(dev).long()
        w = contrib.weight.detach().to(dev, dt)
        T = contrib.transmittance.detach().to(dev, dt)
        op = CompositeOp(composite, pix, pair, w, P, U)
        return [PixelBatch(op, T[:, None] * bg[None, :], target, _group_weights(changed, share))]
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
        op = CompositeOp(composite, rows, cols, vals, p_b, U)
        pixels = order[int(starts[b]) : int(starts[b]) + p_b]
        out.append(PixelBatch(op, T[pixels, None] * bg[None, :], target[pixels],
                              None if changed is None else _group_weights(changed[pixels], share), pixels))
    return out


__all__ = ["AUTO_GPU", "COMPOSITES", "CompositeOp", "PixelBatch", "parse_composite", "pixel_batches",
           "resolve_composite"]
