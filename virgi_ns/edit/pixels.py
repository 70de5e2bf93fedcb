"""The edited view's pixels as sparse linear maps of per-Gaussian colours, split into sets.

Geometry is frozen, so a view's pixels are ``A C + T bg`` with ``A`` fixed
(:mod:`virgi_ns.raster.contract`). :func:`pixel_batches` cuts the view into random pixel sets, one
:class:`PixelBatch` each (its rows of ``A``, background, target and loss weights), in one of two kinds
(:attr:`EditConfig.batch_composite`):

- ``csr``: each set's ``A`` and ``A^T`` as sparse CSR matrices (:class:`CompositeOp`), built once and
  applied by sparse products: the reference, on any device;
- ``fused``: no matrix per set (:class:`FusedSets`): on a GPU one kernel reads the view's own entries for
  the step's pixels and gives the loss and each pixel's signs, and a second gathers the gradient per
  Gaussian over the entries sorted by Gaussian once per edit; the step's set is a counter on the device,
  so one recorded CUDA graph replays every set. Elsewhere the same sums run in torch.

Both run without a host sync and with shapes fixed, so a step can be recorded as a CUDA graph, and give
the same loss and gradient up to the order of float sums.
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from virgi_ns.raster import Contributions


AUTO_GPU = "fused"
"""What ``"auto"`` picks on a GPU where the package's CUDA extension is available; elsewhere ``"csr"``."""


def resolve_composite(name: str, device: torch.device) -> str:
    """``name`` (``auto``, ``csr`` or ``fused``) with ``auto`` replaced by the kind for ``device``."""
    if name != "auto":
        return name
    if torch.device(device).type != "cuda":
        return "csr"
    from virgi_ns.raster import cuda

    return AUTO_GPU if cuda.available()[0] else "csr"


class _CsrProduct(torch.autograd.Function):
    """``A @ C`` by a sparse CSR product; the backward pass ``A^T @ grad`` by the precomputed transpose."""

    @staticmethod
    def forward(ctx, colours: Tensor, op: "CompositeOp") -> Tensor:  # type: ignore[override]
        ctx.op = op
        return op.matrix @ colours

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        return ctx.op.transpose @ grad.contiguous(), None


class CompositeOp:
    """A set's constant ``A`` [p, U] and its transpose as sparse CSR matrices (int64 indices), built once:
    ``op(C)`` is ``A @ C`` [p, k] with an explicit backward. ``rows``, ``cols``, ``vals`` [nnz]: the
    entries, sorted by row (pixel)."""

    kind = "csr"

    def __init__(self, rows: Tensor, cols: Tensor, vals: Tensor, p: int, U: int) -> None:
        self.shape = (p, U)
        rows, cols = rows.long(), cols.long()
        self.matrix = csr_matrix(row_offsets(rows, p, torch.long), cols, vals, (p, U))
        # the entries sorted by Gaussian (pixels ascending within one: rows are sorted already); int32
        # keys sort in half the time of int64 ones
        t_order = torch.argsort(cols.int(), stable=True)
        rows_t, cols_t, vals_t = rows[t_order], cols[t_order], vals[t_order]
        self.transpose = csr_matrix(row_offsets(cols_t, U, torch.long), rows_t, vals_t, (U, p))

    def __call__(self, colours: Tensor) -> Tensor:
        return _CsrProduct.apply(colours, self)


def row_offsets(sorted_rows: Tensor, n: int, dtype: torch.dtype) -> Tensor:
    """[n+1] the start of each of ``n`` rows' entries in ``sorted_rows`` [nnz] (and the end), as ``dtype``."""
    out = torch.zeros(n + 1, dtype=torch.long, device=sorted_rows.device)
    out[1:] = torch.cumsum(torch.bincount(sorted_rows, minlength=n), 0)
    return out.to(dtype)


def csr_matrix(crow: Tensor, cols: Tensor, vals: Tensor, shape: tuple[int, int]) -> Tensor:
    """A sparse CSR matrix of ``shape`` from its row offsets [rows+1], column indices and values [nnz]
    (unchecked: the callers build them sorted)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.sparse_csr_tensor(crow, cols, vals, shape, check_invariants=False)


class _FusedLoss(torch.autograd.Function):
    """The loss of the pixel set :class:`FusedSets`' counter names, with its gradient to the colours
    computed in the same pass (an L1 loss's gradient is known with the pixel)."""

    @staticmethod
    def forward(ctx, colours: Tensor, sets: "FusedSets") -> Tensor:  # type: ignore[override]
        loss, grad = sets.loss_and_grad(colours)
        ctx.save_for_backward(grad)
        return loss

    @staticmethod
    def backward(ctx, g: Tensor):  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        return grad * g, None


def _to_device(host: Tensor, dev: torch.device) -> Tensor:
    """A small CPU tensor on ``dev`` without waiting for the GPU's queue (a copy from pageable memory
    waits for it): through pinned memory, asynchronously."""
    if torch.device(dev).type != "cuda":
        return host.to(dev)
    return host.pin_memory().to(dev, non_blocking=True)


class FusedSets:
    """The pixel sets of the ``fused`` kind: every set's rows in one array ordered by set (``rows``:
    the view's pixels; ``background``, ``target``, ``loss_weight`` alike, each set's slice being its
    :class:`PixelBatch`'s), read with the view's own entries (``pixel_offsets``, ``pair``,
    ``weight``), so nothing is built per set. Which set a step uses is a counter on the device, set
    ``counter % len(starts) - 1`` and advanced by each :meth:`loss`: one recorded CUDA graph of a step
    replays every set in turn. :meth:`restart` sets it to the first set.

    On a GPU the gradient is summed per Gaussian over every set's entries sorted by Gaussian
    (:attr:`by_gaussian`, built here, once); where those cannot be built (None) the loss kernel scatters
    it with one atomic per entry instead: the same loss and gradient up to the order of float sums."""

    kind = "fused"

    def __init__(self, contrib: Contributions, rows: Tensor, starts: list[int], background: Tensor, target: Tensor,
                 loss_weight: Tensor, U: int) -> None:
        dev = target.device
        offsets = getattr(contrib, "pixel_offsets", None)
        self.pixel_offsets = (offsets if offsets is not None else
                              row_offsets(contrib.pixel.to(dev).long(), contrib.num_pixels, torch.long)).to(dev).long()
        self.pair = contrib.pair.to(dev, torch.int32).contiguous()
        self.weight = contrib.weight.detach().to(dev, torch.float32).contiguous()
        self.rows, self.background, self.target, self.loss_weight = rows, background, target, loss_weight
        self.starts_host = starts
        self.starts = _to_device(torch.tensor(starts, dtype=torch.long), dev)
        self.counter = torch.zeros(1, dtype=torch.long, device=dev)
        self.max_rows = max(b - a for a, b in zip(starts[:-1], starts[1:]))
        self.U = U
        self._kernel: Optional[bool] = None
        self.by_gaussian: Optional[list[Tensor]] = None  # (t_start, t_gauss, t_row, t_w): the gathered kernel's
        if self._use_kernel(target):
            self.by_gaussian = self._sorted_by_gaussian()

    def _sorted_by_gaussian(self) -> Optional[list[Tensor]]:
        """The gathered kernel's entries (:func:`virgi_ns.raster.cuda.edit_by_gaussian`), or None, with a
        warning, where they cannot be built: more entries or bins than int32 indices reach, or too
        little free GPU memory for their 12 bytes an entry. The steps then scatter the gradient
        instead (the same loss and gradient)."""
        from virgi_ns.raster.cuda import edit_by_gaussian

        limit = 2**31 - 1
        why = None
        if self.pair.numel() >= limit or len(self) * self.U >= limit:
            why = f"{self.pair.numel():,} entries over {len(self)} x {self.U:,} bins exceed int32 indices"
        else:
            try:
                return edit_by_gaussian(self.pair, self.weight, self.pixel_offsets, self.rows, self.starts,
                                        self.loss_weight, self.U)
            except torch.cuda.OutOfMemoryError:
                why = f"too little free GPU memory for {self.pair.numel():,} entries sorted by Gaussian"
        warnings.warn(f"edit steps scatter their gradient (an atomic per entry): {why}")
        return None

    def __len__(self) -> int:
        return len(self.starts_host) - 1

    def restart(self) -> None:
        self.counter.zero_()

    def loss(self, colours: Tensor) -> Tensor:
        """The loss of the counter's set (a scalar, differentiable in ``colours`` [U, 3]); advances the counter."""
        return _FusedLoss.apply(colours, self)

    def _use_kernel(self, on: Tensor) -> bool:
        """Whether the steps run our CUDA kernels (``on``: a tensor on the sets' device)."""
        if self._kernel is None:
            from virgi_ns.raster import cuda

            self._kernel = on.is_cuda and cuda.available()[0]
        return self._kernel

    def loss_and_padded_grad(self, colours: Tensor) -> tuple[Tensor, Tensor]:
        """(loss [1], its gradient [U, 4], the last column padding) of the counter's set, by the CUDA
        kernel (GPU only; :meth:`loss_and_grad` is the reference); advances the counter."""
        from virgi_ns.raster.cuda import edit_l1_step

        return edit_l1_step(colours, self.pair, self.weight, self.pixel_offsets, self.rows, self.starts, self.counter,
                            self.background, self.target, self.loss_weight, self.max_rows, self.by_gaussian)

    def loss_and_grad(self, colours: Tensor) -> tuple[Tensor, Tensor]:
        """(loss, its gradient [U, 3]) of the counter's set; advances the counter. The CUDA kernel on a
        GPU (no host sync), else the same sums in torch (the reference, which reads the counter)."""
        colours = colours.detach().float().contiguous()
        if self._use_kernel(colours):
            loss, grad = self.loss_and_padded_grad(colours)
            return loss[0], grad[:, :3]
        s = int(self.counter) % len(self)
        self.counter += 1
        a, b = self.starts_host[s], self.starts_host[s + 1]
        img, entries, local = self._composite(colours, a, b)
        err = img + self.background[a:b] - self.target[a:b]
        k = self.loss_weight[a:b, None] / 3.0
        g = (k * torch.sign(err)).to(colours.dtype)
        grad = torch.zeros(self.U, 3, dtype=colours.dtype, device=colours.device)
        grad.index_add_(0, self.pair[entries].long(), self.weight[entries, None] * g[local])
        return (k * err.abs()).sum(), grad

    def _composite(self, colours: Tensor, a: int, b: int) -> tuple[Tensor, Tensor, Tensor]:
        """(``A @ colours`` over rows ``a:b``, the entries read, the local row of each)."""
        rows = self.rows[a:b]
        first, count = self.pixel_offsets[rows], self.pixel_offsets[rows + 1] - self.pixel_offsets[rows]
        local = torch.repeat_interleave(torch.arange(b - a, device=rows.device), count)
        before = torch.cumsum(count, 0) - count
        entries = torch.repeat_interleave(first - before, count) + torch.arange(local.numel(), device=rows.device)
        terms = self.weight[entries, None].to(colours.dtype) * colours[self.pair[entries].long()]
        img = torch.zeros(b - a, colours.shape[1], dtype=colours.dtype, device=colours.device)
        return img.index_add(0, local, terms), entries, local

    def render(self, colours: Tensor, s: int) -> Tensor:
        """``A @ colours`` over set ``s``'s rows (differentiable; tests and benchmarks)."""
        return self._composite(colours, self.starts_host[s], self.starts_host[s + 1])[0]


@dataclass
class PixelBatch:
    """One pixel set of the view: its ``A`` [p, U] (``op``: a :class:`CompositeOp`, or the :class:`FusedSets`
    every set of the ``fused`` kind shares), and per pixel its background ``T bg``, target and loss weight."""

    op: "CompositeOp | FusedSets"  # the batch's A [p, U] and how it is applied (FusedSets: shared by every set)
    background: Tensor  # [p, 3] T * bg
    target: Tensor  # [p, 3]
    weight: Optional[Tensor] = None  # [p] per-pixel loss weights summing to 1 (None: the plain mean)
    pixels: Optional[Tensor] = None  # [p] the view's pixels in this batch (None: all, in order)
    index: int = 0  # which set of the view's this is

    @property
    def composite(self) -> str:
        return self.op.kind

    @property
    def sets(self) -> Optional[FusedSets]:
        """The ``fused`` kind's sets, which every batch of the view shares (None for ``csr``)."""
        return self.op if isinstance(self.op, FusedSets) else None

    def render(self, colours: Tensor) -> Tensor:
        """``A @ colours`` [p, 3] by the batch's composite kind, differentiable in ``colours``."""
        if self.sets is not None:
            return self.sets.render(colours, self.index)
        return self.op(colours)

    def render_transpose(self, grad: Tensor) -> Tensor:
        """``A^T @ grad`` [U, 3]: what :meth:`render`'s backward pass computes (for benchmarks)."""
        if self.sets is not None:
            C = torch.zeros(self.sets.U, grad.shape[1], dtype=grad.dtype, device=grad.device, requires_grad=True)
            with torch.enable_grad():
                return torch.autograd.grad(self.render(C), C, grad)[0]
        return self.op.transpose @ grad.contiguous()

    def loss(self, colours: Tensor) -> Tensor:
        """The step's loss on this batch: the (weighted) mean over its pixels and channels of
        ``|A colours + background - target|``. For the ``fused`` kind the set the device counter
        names (:class:`FusedSets`), which the engine keeps equal to this batch's."""
        if self.sets is not None:
            return self.sets.loss(colours)
        return self.reference_loss(colours)

    def reference_loss(self, colours: Tensor) -> Tensor:
        """The same loss on this batch by torch sums, for every kind (the ``fused`` kind's counter is
        neither read nor advanced)."""
        err = (self.render(colours) + self.background - self.target).abs()
        return err.mean() if self.weight is None else (err.mean(-1) * self.weight).sum()


def _group_weights(changed: Optional[Tensor], share: float, n_changed: Optional[int] = None,
                   keep: Optional[Tensor] = None) -> Optional[Tensor]:
    """Per-pixel loss weights [p] summing to 1: the ``changed`` [p] pixels carry ``share`` of the loss and
    the others the rest, whatever their numbers (all of it when one group is empty). ``n_changed``:
    how many are changed, when the caller knows it (counting them waits for the GPU). ``keep`` [p]:
    relative weights of the unchanged pixels within their share (None: each the same)."""
    if changed is None:
        return None
    n_c = int(changed.sum()) if n_changed is None else n_changed
    n_u = changed.numel() - n_c
    if n_c == 0 or n_u == 0:
        return torch.full(changed.shape, 1.0 / max(changed.numel(), 1), device=changed.device)
    if keep is None:
        return torch.where(changed, share / n_c, (1.0 - share) / n_u).float()
    keep = torch.where(changed, torch.zeros((), device=keep.device), keep.float())
    return torch.where(changed, share / n_c, (1.0 - share) * keep / keep.sum().clamp_min(1e-30)).float()


def pixel_batches(contrib: Contributions, target: Tensor, bg: Tensor, n_batches: int, seed: int,
                  changed: Optional[Tensor] = None, share: float = 0.5, composite: str = "csr",
                  n_changed: Optional[int] = None, keep: Optional[Tensor] = None) -> list[PixelBatch]:
    """Split the view's pixels into ``n_batches`` random, equally sized sets, each with its own rows of
    ``A`` (pixels ascending within a set). With ``changed`` the changed and the other pixels are each
    spread evenly over the sets, and within every set the changed ones carry ``share`` of the loss.

    Args:
        contrib: the view's contribution lists (one view, P pixels).
        target: [P, 3] each pixel's target.
        bg: [3] the background colour.
        n_batches: how many sets (1: the whole view).
        seed: seeds the split.
        changed: [P] bool, the pixels an edit changed (None: every pixel weighs the same).
        share: the changed pixels' share of each set's loss.
        composite: ``csr``, ``fused`` or ``auto`` (:func:`resolve_composite`).
        n_changed: how many pixels ``changed`` marks, when the caller has counted them.
        keep: [P] relative weights of the unchanged pixels within each set's share of them (None: each
            the same; :func:`~virgi_ns.edit.targets.unchanged_pixel_weights`).

    Returns:
        One :class:`PixelBatch` per set."""
    composite = resolve_composite(composite, target.device)
    if composite not in ("csr", "fused"):
        raise ValueError(f"pixel_batches: composite must be 'auto', 'csr' or 'fused', got {composite!r}")
    dev, dt = target.device, target.dtype
    P = contrib.num_pixels
    U = int(contrib.pair_gaussian.shape[0])
    T = contrib.transmittance.detach().to(dev, dt)
    if n_batches == 1 and composite == "csr":  # the whole image: entries are already grouped by pixel
        pix, pair = contrib.pixel.to(dev).long(), contrib.pair.to(dev).long()
        w = contrib.weight.detach().to(dev, dt)
        op = CompositeOp(pix, pair, w, P, U)
        return [PixelBatch(op, T[:, None] * bg[None, :], target, _group_weights(changed, share, n_changed, keep))]
    if changed is not None and n_changed is None:
        n_changed = int(changed.sum())
    batch_of = _assign_sets(P, n_batches, seed, changed, dev, n_changed)
    # the sets' pixels one after another, ascending within a set
    order = torch.argsort(batch_of, stable=True)
    if composite == "fused":
        return _fused_batches(contrib, order, T, bg, target, changed, share, U, n_batches, n_changed, keep)
    counts = torch.bincount(batch_of, minlength=n_batches)
    starts = torch.cumsum(counts, 0) - counts
    # local row of each pixel: its rank among its batch's pixels, in ascending pixel order
    local = torch.empty(P, dtype=torch.long, device=dev)
    local[order] = torch.arange(P, device=dev) - starts[batch_of[order]]
    # int64 indices: backends may hand int32 (CUDA), and the CSR index arrays must share one dtype
    pix, pair = contrib.pixel.to(dev).long(), contrib.pair.to(dev).long()
    w = contrib.weight.detach().to(dev, dt)
    eb = batch_of[pix]
    e_order = torch.argsort(eb.int(), stable=True)  # entries stay in pixel order within a batch
    e_counts = torch.bincount(eb, minlength=n_batches).tolist()
    out = []
    e0 = 0
    for b in range(n_batches):
        sel = e_order[e0 : e0 + e_counts[b]]
        e0 += e_counts[b]
        rows, cols, vals = local[pix[sel]], pair[sel], w[sel]
        p_b = int(counts[b])
        op = CompositeOp(rows, cols, vals, p_b, U)
        pixels = order[int(starts[b]) : int(starts[b]) + p_b]
        out.append(PixelBatch(op, T[pixels, None] * bg[None, :], target[pixels],
                              None if changed is None else _group_weights(
                                  changed[pixels], share, keep=None if keep is None else keep[pixels]), pixels, b))
    return out


def _split_sizes(n: int, n_sets: int) -> list[int]:
    """How many of ``n`` items each set gets when item ``j`` goes to set ``j % n_sets``."""
    return [n // n_sets + (s < n % n_sets) for s in range(n_sets)]


def _assign_sets(P: int, n_batches: int, seed: int, changed: Optional[Tensor], dev: torch.device,
                 n_changed: Optional[int] = None) -> Tensor:
    """[P] the set of each pixel: a random split into equal sets (stratified by ``changed``: each set
    gets its part of the changed pixels and of the others), drawn on the view's device (a CPU
    permutation of a megapixel view costs tens of milliseconds); ``n_changed``: ``changed``'s count,
    when known (the groups are then found without waiting for the GPU)."""
    if n_batches == 1:
        return torch.zeros(P, dtype=torch.long, device=dev)
    gen = torch.Generator(device=dev).manual_seed(seed)
    batch_of = torch.empty(P, dtype=torch.long, device=dev)
    if changed is None:
        batch_of[torch.randperm(P, generator=gen, device=dev)] = torch.arange(P, device=dev) % n_batches
    else:
        ch = changed.to(dev)
        n_c = int(ch.sum()) if n_changed is None else n_changed
        # the changed pixels, then the others, each ascending
        grouped = torch.argsort((~ch).to(torch.uint8), stable=True)
        for idx in (grouped[:n_c], grouped[n_c:]):
            perm = torch.randperm(len(idx), generator=gen, device=dev)
            batch_of[idx[perm]] = torch.arange(len(idx), device=dev) % n_batches
    return batch_of


def _fused_batches(contrib: Contributions, order: Tensor, T: Tensor, bg: Tensor, target: Tensor,
                   changed: Optional[Tensor], share: float, U: int, n_sets: int,
                   n_changed: Optional[int], keep: Optional[Tensor] = None) -> list[PixelBatch]:
    """The ``fused`` kind's batches: slices of one :class:`FusedSets` (no per-set matrices). Each set's
    size, and its share of the changed pixels, follow from the split of :func:`_assign_sets` on the
    host, so nothing here waits for the GPU."""
    P = order.numel()
    if changed is None:
        counts, changed_counts = _split_sizes(P, n_sets), None
    else:
        changed_counts = _split_sizes(n_changed, n_sets)
        counts = [c + o for c, o in zip(changed_counts, _split_sizes(P - n_changed, n_sets))]
    starts = [0, *itertools.accumulate(counts)]
    background = (T[order, None] * bg[None, :]).contiguous()
    rows_target = target[order].contiguous()
    loss_weight = torch.empty(P, dtype=torch.float32, device=order.device)
    for s, (a, b) in enumerate(zip(starts[:-1], starts[1:])):
        loss_weight[a:b] = (1.0 / max(b - a, 1)) if changed is None else _group_weights(
            changed[order[a:b]], share, changed_counts[s], None if keep is None else keep[order[a:b]])
    sets = FusedSets(contrib, order, starts, background, rows_target, loss_weight, U)
    return [PixelBatch(sets, background[a:b], rows_target[a:b],
                       None if changed is None else loss_weight[a:b], order[a:b], i)
            for i, (a, b) in enumerate(zip(starts[:-1], starts[1:]))]


__all__ = ["AUTO_GPU", "CompositeOp", "FusedSets", "PixelBatch", "csr_matrix", "pixel_batches", "resolve_composite",
           "row_offsets"]
