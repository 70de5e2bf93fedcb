"""The edit heads' written-out backward (virgi_ns.edit.heads): the torch reference against autograd in
float64 on the CPU; on a GPU, the kernels against that reference (a whole edit with them against the
same edit through autograd: tests/test_edit.py)."""

from __future__ import annotations

import pytest
import torch

from virgi_ns.edit.heads import FusedHeads, HeadsInputs, reference_backward, reference_forward
from virgi_ns.edit.stack import SegmentationHead

F_DIM, H_DIM, WIDTH, U = 20, 24, 40, 300  # widths unlike the defaults', and a width not a multiple of 32


def _heads(dtype: torch.dtype, device: str = "cpu", seed: int = 0):
    """A segmentation head, a copied layer and their inputs, with every quantity of order one (the
    output weights not near zero, so alpha varies and every gradient is far from vanishing)."""
    g = torch.Generator().manual_seed(seed)
    seg = SegmentationHead(F_DIM, H_DIM, WIDTH, init_bias=0.3)
    with torch.no_grad():
        for p in seg.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    seg = seg.to(device, dtype)
    weight = (torch.randn(3, H_DIM, generator=g) * 0.3).to(device, dtype).requires_grad_(True)
    bias = (torch.randn(3, generator=g) * 0.3).to(device, dtype).requires_grad_(True)
    x = torch.randn(U, F_DIM + H_DIM, generator=g).to(device, dtype)
    inp = HeadsInputs(x, F_DIM, torch.randn(U, 3, generator=g).to(device, dtype),
                      torch.randn(U, 3, generator=g).to(device, dtype), 0.7)
    grad_c = torch.randn(U, 3, generator=g).to(device, dtype)
    return seg, weight, bias, inp, grad_c


def _autograd(seg, weight, bias, inp, grad_c) -> dict:
    """The engine's own forward (EditEngine.colours) through autograd."""
    alpha = torch.sigmoid(seg.logits_of(inp.x))
    c_dp = torch.nn.functional.linear(inp.x[:, F_DIM:], weight, bias)
    C = torch.sigmoid(alpha * c_dp + (1.0 - alpha) * inp.cd + inp.k * inp.cs)
    params = {"l1.weight": seg.l1.weight, "l1.bias": seg.l1.bias, "l2.weight": seg.l2.weight,
              "l2.bias": seg.l2.bias, "weight": weight, "bias": bias}
    grads = torch.autograd.grad((C * grad_c).sum(), list(params.values()))
    return {"C": C.detach(), **dict(zip(params, grads))}


def test_the_written_out_backward_is_autograds_in_float64():
    seg, weight, bias, inp, grad_c = _heads(torch.float64)
    want = _autograd(seg, weight, bias, inp, grad_c)
    with torch.no_grad():
        fwd = reference_forward(seg, weight, bias, inp)
        got = reference_backward(fwd, grad_c, seg, inp, H_DIM)
    assert torch.allclose(fwd["C"], want["C"], rtol=0, atol=1e-14)
    for name, g in got.items():
        assert g.shape == want[name].shape, name
        assert float(want[name].abs().max()) > 1e-2, name  # a gradient that could be wrong
        assert torch.allclose(g, want[name], rtol=1e-12, atol=1e-13), name
    # some Gaussians' hidden units are off: the relu's gradient is part of what was checked
    assert 0.2 < float((fwd["pre"] > 0).double().mean()) < 0.8


class _Sets:
    """Stands in for FusedSets: a fixed gradient to the colours, padded to 4 columns."""

    def __init__(self, grad_c: torch.Tensor) -> None:
        self.grad = torch.nn.functional.pad(grad_c, (0, 1)).contiguous()

    def loss_and_padded_grad(self, colours):
        return colours.sum()[None], self.grad


def _gpu_kernels() -> bool:
    if not torch.cuda.is_available():
        return False
    from virgi_ns.raster import cuda

    return cuda.available()[0]


@pytest.mark.gpu
@pytest.mark.skipif(not _gpu_kernels(), reason="needs a CUDA GPU and the extension")
def test_the_kernels_match_the_float64_reference_on_a_gpu():
    seg, weight, bias, inp, grad_c = _heads(torch.float32, "cuda")
    heads = FusedHeads(seg, weight, bias, inp)
    heads.step(_Sets(grad_c))
    with torch.no_grad():  # the oracle: the reference in float64 from the same float32 values
        seg64 = SegmentationHead(F_DIM, H_DIM, WIDTH).to("cuda", torch.float64)
        seg64.load_state_dict({k: v.double() for k, v in seg.state_dict().items()})
        inp64 = HeadsInputs(inp.x.double(), F_DIM, inp.cd.double(), inp.cs.double(), inp.k)
        fwd = reference_forward(seg64, weight.double(), bias.double(), inp64)
        want = reference_backward(fwd, grad_c.double(), seg64, inp64, H_DIM)
    got = {"l1.weight": seg.l1.weight.grad, "l1.bias": seg.l1.bias.grad, "l2.weight": seg.l2.weight.grad,
           "l2.bias": seg.l2.bias.grad, "weight": weight.grad, "bias": bias.grad}
    for name, g in got.items():
        scale = float(want[name].abs().max())
        assert g.shape == want[name].shape, name
        assert float((g.double() - want[name]).abs().max()) <= 1e-5 * scale, name
