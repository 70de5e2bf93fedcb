"""An edit's heads: the segmentation head, and both heads' step written out for the GPU.

- :class:`SegmentationHead`: ``alpha = sigmoid(MLP_seg([f, h_diff]))``, which Gaussians an edit
  recolours; :func:`fresh_segmentation`, a fresh one drawn from a seed.
- :class:`FusedLayer`: one step of the staged recipe (the copied layer alone, the segmentation fixed) on
  the GPU, two kernels of ours and one cuBLAS product.
- :class:`FusedHeads`: one step of the joint recipe's two heads (the segmentation head and the copied
  last diffuse layer, :mod:`virgi_ns.edit.engine`) on the GPU. Through autograd a step's heads are
  dozens of small kernels; here the same step is two cuBLAS products and two kernels of ours
  (``csrc/edit_heads.cu``)::

    pre    = x W1^T + b1                           x = [f, h_diff] (constant during an edit)
    alpha  = sigmoid(relu(pre) . w2 + b2)
    c_dp   = Wd h_diff + bd
    C      = sigmoid(alpha c_dp + (1 - alpha) c_d + k c_s)
    loss, dL/dC                                     the fused pixel loss (FusedSets)
    rows   = [dL/dpre, dL/dc_dp, 0]  [U, S + 4]    and the sums of dL/db1, dL/dw2, dL/db2, dL/dbd
    rows^T x                                        dL/dW1 and, in its h_diff columns, dL/dWd

then the same Adam step on the same tensors as the autograd step. :func:`reference_forward` and
:func:`reference_backward` are that step in torch, the specification the kernels are tested against
(and autograd against it).
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor, nn


class SegmentationHead(nn.Module):
    """``alpha = sigmoid(l2(relu(l1([f, h_diff]))))``: which Gaussians an edit recolours.

    The output bias starts at ``init_bias`` (negative) and the output weights near zero, so a
    fresh head gives ``alpha ~ sigmoid(init_bias)`` everywhere: the edit starts as a no-op."""

    def __init__(self, feature_dim: int, hidden_dim: int, width: int = 64, init_bias: float = -4.0) -> None:
        super().__init__()
        self.feature_dim, self.hidden_dim, self.width = feature_dim, hidden_dim, width
        self.l1 = nn.Linear(feature_dim + hidden_dim, width)
        self.l2 = nn.Linear(width, 1)
        nn.init.normal_(self.l2.weight, std=1e-2)
        nn.init.constant_(self.l2.bias, init_bias)

    def inputs(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"]) -> Float[Tensor, "N FH"]:
        """``[f, h_diff]``, the head's input (constant during an edit, so callers may cache it)."""
        return torch.cat([feats.to(self.l1.weight.dtype), h_diff.to(self.l1.weight.dtype)], dim=-1)

    def logits_of(self, x: Float[Tensor, "N FH"]) -> Float[Tensor, "N 1"]:
        return self.l2(torch.relu(self.l1(x)))

    def logits(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"]) -> Float[Tensor, "N 1"]:
        return self.logits_of(self.inputs(feats, h_diff))

    def forward(self, feats: Float[Tensor, "N F"], h_diff: Float[Tensor, "N H"]) -> Float[Tensor, "N 1"]:
        return torch.sigmoid(self.logits(feats, h_diff))


GLOBAL_RNG_LOCK = threading.Lock()
"""Held while the global CPU random state is seeded or forked here, so that another thread (the
warm-up, :mod:`virgi_ns.edit.warmup`) cannot draw from it between a seed and its use."""


@functools.lru_cache(maxsize=8)
def fresh_segmentation(feature_dim: int, hidden_dim: int, width: int, init_bias: float, seed: int,
                       device: torch.device) -> SegmentationHead:
    """A fresh segmentation head drawn on the CPU with ``seed`` (the same on every device), moved to
    ``device`` and kept there for the next edit of the same shape (building it and moving it waits for
    the GPU's queue). Callers copy it."""
    with GLOBAL_RNG_LOCK, torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        head = SegmentationHead(feature_dim, hidden_dim, width, init_bias)
    return head.to(device)


MAX_WIDTH = 256
"""The widest segmentation head the kernels take (``kMaxHeadsWidth`` in ``csrc/kernels.h``)."""


@dataclass
class HeadsInputs:
    """What a step's heads read besides their parameters: the head input ``x = [f, h_diff]`` [U, Dx]
    (h_diff from column ``hd_offset``), the stack's diffuse logits ``cd`` and the specular logits
    ``cs`` [U, 3] of the view's Gaussians, and the specular strength ``k``."""

    x: Tensor
    hd_offset: int
    cd: Tensor
    cs: Tensor
    k: float

    def for_kernels(self) -> tuple[Tensor, Tensor, Tensor]:
        """``x``, ``cd`` and ``cs`` as the kernels read them: float32 and contiguous."""
        return self.x.float().contiguous(), self.cd.float().contiguous(), self.cs.float().contiguous()


def reference_forward(seg: SegmentationHead, weight: Tensor, bias: Tensor, inp: HeadsInputs) -> dict[str, Tensor]:
    """The heads' forward in torch: ``pre``, ``alpha`` [U], ``cdp`` and the colours ``C`` [U, 3]."""
    pre = torch.addmm(seg.l1.bias, inp.x, seg.l1.weight.t())
    alpha = torch.sigmoid(torch.relu(pre) @ seg.l2.weight[0] + seg.l2.bias[0])
    H = weight.shape[1]
    cdp = inp.x[:, inp.hd_offset : inp.hd_offset + H] @ weight.t() + bias
    a = alpha[:, None]
    return {"pre": pre, "alpha": alpha, "cdp": cdp, "C": torch.sigmoid(a * cdp + (1 - a) * inp.cd + inp.k * inp.cs)}


def reference_backward(fwd: dict[str, Tensor], grad_c: Tensor, seg: SegmentationHead, inp: HeadsInputs,
                       H: int) -> dict[str, Tensor]:
    """The gradients of the loss to every parameter from ``grad_c`` = dL/dC [U, 3], by hand: the
    kernels' specification. Keys: ``l1.weight``, ``l1.bias``, ``l2.weight``, ``l2.bias``, ``weight``,
    ``bias`` (the copied layer)."""
    C, alpha, cdp, pre = fwd["C"], fwd["alpha"], fwd["cdp"], fwd["pre"]
    dz = grad_c * C * (1 - C)
    d_alpha = (dz * (cdp - inp.cd)).sum(1)
    d_logit = d_alpha * alpha * (1 - alpha)
    d_pre = torch.where(pre > 0, d_logit[:, None] * seg.l2.weight[0], torch.zeros_like(pre))
    d_cdp = alpha[:, None] * dz
    hd = inp.x[:, inp.hd_offset : inp.hd_offset + H]
    return {"l1.weight": d_pre.t() @ inp.x, "l1.bias": d_pre.sum(0),
            "l2.weight": (d_logit @ torch.relu(pre))[None], "l2.bias": d_logit.sum()[None],
            "weight": d_cdp.t() @ hd, "bias": d_cdp.sum(0)}


class FusedHeads:
    """One step of the joint recipe's heads on the GPU (``seg``, and the copied layer ``weight``,
    ``bias``, all trained in place), around the fused pixel loss of :class:`FusedSets`; sets each
    parameter's ``.grad`` for the caller's Adam step. No host sync: the step records in a CUDA graph."""

    def __init__(self, seg: SegmentationHead, weight: Tensor, bias: Tensor, inp: HeadsInputs) -> None:
        self.seg, self.weight, self.bias, self.inp = seg, weight, bias, inp
        self.x, self.cd, self.cs = inp.for_kernels()

    @staticmethod
    def runs_on(seg: SegmentationHead, colours_device: torch.device) -> bool:
        """Whether the kernels run here: a CUDA device, our extension built, a head no wider than they take."""
        if colours_device.type != "cuda" or seg.width > MAX_WIDTH:
            return False
        from virgi_ns.raster import cuda

        return cuda.available()[0]

    def step(self, sets) -> Tensor:
        """The loss of the set ``sets`` (:class:`FusedSets`) names (advancing its counter), and every
        parameter's gradient in its ``.grad``."""
        from virgi_ns.raster import cuda

        l1, l2 = self.seg.l1, self.seg.l2
        S, H = l1.weight.shape[0], self.weight.shape[1]
        with torch.no_grad():
            pre = torch.addmm(l1.bias, self.x, l1.weight.t())
            C, alpha, cdp = cuda.edit_heads_forward(pre, self.x, l2.weight, l2.bias, self.weight, self.bias, self.cd,
                                                    self.cs, self.inp.k, self.inp.hd_offset)
            loss, grad_c = sets.loss_and_padded_grad(C)
            rows, sums = cuda.edit_heads_backward(grad_c, C, alpha, cdp, self.cd, pre, l2.weight)
            products = torch.mm(rows.t(), self.x)  # [S + 4, Dx]: W1's gradient, then the layer's rows
            off = self.inp.hd_offset
            l1.weight.grad = products[:S]
            l1.bias.grad = sums[:S]
            l2.weight.grad = sums[S : 2 * S].view(1, S)
            l2.bias.grad = sums[2 * S : 2 * S + 1]
            self.bias.grad = sums[2 * S + 1 :]
            self.weight.grad = products[S : S + 3, off : off + H].contiguous()
        return loss[0]


class FusedLayer:
    """One step of the staged recipe on the GPU: the copied layer ``weight``, ``bias`` alone (trained in
    place), the segmentation fixed at ``alpha`` [U, 1] (read at every step: a retarget writes it in place),
    around the fused pixel loss of :class:`FusedSets`; sets the layer's ``.grad``. Two kernels of ours and
    one cuBLAS product; no host sync."""

    def __init__(self, alpha: Tensor, weight: Tensor, bias: Tensor, inp: HeadsInputs) -> None:
        self.alpha, self.weight, self.bias, self.inp = alpha, weight, bias, inp
        self.x, self.cd, self.cs = inp.for_kernels()

    def step(self, sets) -> Tensor:
        """The loss of the set ``sets`` names (advancing its counter), and the layer's gradient in its ``.grad``."""
        from virgi_ns.raster import cuda

        H, off = self.weight.shape[1], self.inp.hd_offset
        with torch.no_grad():
            alpha = self.alpha.view(-1)
            C, _ = cuda.edit_layer_forward(alpha, self.x, self.weight, self.bias, self.cd, self.cs, self.inp.k, off)
            loss, grad_c = sets.loss_and_padded_grad(C)
            rows, sums = cuda.edit_layer_backward(grad_c, C, alpha)
            self.weight.grad = torch.mm(rows.t(), self.x)[:3, off : off + H].contiguous()
            self.bias.grad = sums[:3]
        return loss[0]


__all__ = ["GLOBAL_RNG_LOCK", "FusedHeads", "FusedLayer", "HeadsInputs", "SegmentationHead", "fresh_segmentation",
           "reference_backward", "reference_forward"]
