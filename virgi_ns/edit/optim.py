"""Adam for an edit's few small tensors, through torch's own fused Adam kernel.

``torch.optim.Adam(fused=True)`` runs the same kernel, but building any ``torch.optim`` optimizer
imports ``torch._dynamo`` (the optimizer's methods are wrapped to keep the compiler out of them),
a cost the first edit of every CLI call and viewer session would pay. :class:`EditAdam` keeps Adam's
state itself and calls the kernel (``torch._fused_adam_``) directly; where that kernel is missing it
falls back to ``torch.optim.Adam``.
"""

from __future__ import annotations

import math
from typing import Iterable, Optional, Sequence

import torch
from torch import Tensor


def _has_fused_kernel(params: list[Tensor]) -> bool:
    """Whether torch's fused Adam kernel runs on these parameters' devices: CUDA, and the CPU from
    torch 2.4 on."""
    if not hasattr(torch, "_fused_adam_"):
        return False
    major, minor = (int(v) for v in torch.__version__.split(".")[:2])
    return all(p.device.type == "cuda" or (p.device.type == "cpu" and (major, minor) >= (2, 4)) for p in params)


class EditAdam:
    """Adam (no weight decay, no AMSGrad) over ``params``; capturable in a CUDA graph: the step counts
    live on the parameters' device and nothing reads them on the host. ``decay_steps``: the learning
    rate falls from ``lr`` at the first step to 0 after that many by half a cosine (computed on the
    device from the step count, so a recorded step replays it); None keeps it constant. ``hold_steps``:
    steps at the full rate before the decay starts (the decay then spans ``decay_steps`` more).
    ``scales``: one factor per parameter on the rate (default 1 each), e.g. one head faster than
    the other; the schedule scales them alike."""

    def __init__(self, params: Iterable[Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8, decay_steps: Optional[int] = None, hold_steps: int = 0,
                 scales: Optional[Sequence[float]] = None) -> None:
        self.params = list(params)
        self.lr, self.betas, self.eps = float(lr), betas, float(eps)
        self.scales = [1.0] * len(self.params) if scales is None else [float(v) for v in scales]
        if len(self.scales) != len(self.params) or any(not v > 0.0 for v in self.scales):
            raise ValueError(f"EditAdam: scales must be one positive factor per parameter, got {scales}")
        # parameters grouped by their factor: one fused kernel call per group
        self._groups = {v: [i for i, w in enumerate(self.scales) if w == v] for v in dict.fromkeys(self.scales)}
        if decay_steps is not None and decay_steps < 1:
            raise ValueError(f"EditAdam: decay_steps must be >= 1, got {decay_steps}")
        if hold_steps < 0 or (hold_steps and decay_steps is None):
            raise ValueError(f"EditAdam: hold_steps must be >= 0 and needs decay_steps, got {hold_steps}")
        self.decay_steps, self.hold_steps = decay_steps, int(hold_steps)
        self._host_steps = 0  # the fallback's step count (it sets its learning rate on the host)
        self._fallback = None if _has_fused_kernel(self.params) else torch.optim.Adam(
            [{"params": [self.params[i] for i in idx], "lr": lr * v, "scale": v} for v, idx in self._groups.items()],
            lr=lr, betas=betas, eps=eps)
        self.exp_avg = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in self.params]
        self.steps = [torch.zeros((), dtype=torch.float32, device=p.device) for p in self.params]
        self._lr = torch.full((), self.lr, dtype=torch.float32, device=self.params[0].device)
        self._scaled_lr = {v: torch.full((), self.lr * v, dtype=torch.float32, device=self.params[0].device)
                           for v in self._groups if v != 1.0}

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step`` (0: the first) after a (re)start."""
        if self.decay_steps is None:
            return self.lr
        done = min(max(step - self.hold_steps, 0), self.decay_steps) / self.decay_steps
        return 0.5 * self.lr * (1.0 + math.cos(math.pi * done))

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        if self._fallback is not None:
            for group in self._fallback.param_groups:
                group["lr"] = self.lr_at(self._host_steps) * group.get("scale", 1.0)
            self._host_steps += 1
            self._fallback.step()
            return
        grads = [p.grad for p in self.params]
        if any(g is None for g in grads):
            raise RuntimeError("EditAdam.step: a parameter has no gradient")
        torch._foreach_add_(self.steps, 1.0)
        decayed = self.decay_steps is not None
        if decayed:  # lr_at(steps - 1), on the device
            done = (self.steps[0] - 1.0 - self.hold_steps).clamp(0.0, float(self.decay_steps)) / float(self.decay_steps)
            torch.mul(torch.cos(done * math.pi) + 1.0, 0.5 * self.lr, out=self._lr)
            for v, t in self._scaled_lr.items():
                torch.mul(self._lr, v, out=t)
        for v, idx in self._groups.items():
            lr = (self._lr if v == 1.0 else self._scaled_lr[v]) if decayed else self.lr * v
            pick = (lambda ts: ts) if len(idx) == len(self.params) else (lambda ts: [ts[i] for i in idx])
            torch._fused_adam_(pick(self.params), pick(grads), pick(self.exp_avg), pick(self.exp_avg_sq), [],
                               pick(self.steps), lr=lr, beta1=self.betas[0], beta2=self.betas[1], weight_decay=0.0,
                               eps=self.eps, amsgrad=False, maximize=False)

    def state_tensors(self) -> list[Tensor]:
        """Every tensor of Adam's state (moments and step counts)."""
        if self._fallback is not None:
            return [v for state in self._fallback.state.values() for v in state.values() if torch.is_tensor(v)]
        return self.exp_avg + self.exp_avg_sq + self.steps

    def restart(self) -> None:
        """A fresh Adam's state (no moments, step 0), written in place: recorded steps read these tensors."""
        for t in self.state_tensors():
            t.zero_()
        self._host_steps = 0


__all__ = ["EditAdam"]
