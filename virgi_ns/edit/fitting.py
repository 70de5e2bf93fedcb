"""How an edit's steps run: the optimizer and its schedule, the staged recipe's classifier, and the
recorded CUDA graphs the steps replay.

- :func:`heads_optimizer`: Adam over the trained tensors, at ``lr`` for the first :data:`LR_HOLD` of
  the steps and then by half a cosine to 0, the segmentation head at its own multiple of the rate
  (:func:`segmentation_rate`).
- :func:`classify_gaussians`: the ``staged`` recipe's first stage, the segmentation head trained as a
  classifier of the view's Gaussians.
- :class:`GraphedSteps`: a fit's steps recorded once as CUDA graphs and replayed.
- :class:`EditTiming`: what a fit took.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from virgi_ns.edit.config import EditConfig
from virgi_ns.edit.heads import SegmentationHead
from virgi_ns.edit.optim import EditAdam

LR_HOLD = 0.5
"""The share of a fit's steps at the full rate before the half cosine, which spans the rest: the fit
travels far first and settles after (a cosine from the first step travels half as far, too little where
the colour map starts far from the target)."""

LARGE_EDIT_SEG_RATE = 2.0
"""The joint recipe's segmentation head steps at this multiple of ``lr`` where the changed pixels are
more of the view than :attr:`EditConfig.changed_share` but not all of it: there each unchanged pixel
weighs more than a changed one, and together they pull the head down inside the recoloured object
too. Everywhere else it steps at ``lr``, as the copied layer does."""

SEG_LR = 1e-2
"""``staged``: learning rate of the segmentation classifier."""

SEG_PRIOR_SHARE = 0.2
"""``staged``: the share of the classifier's negative samples drawn from the whole scene, unlabelled
(most of a scene is not part of an edit): keeps the segmentation off what the edited view never showed
unless it resembles what the edit changed."""


@dataclass
class EditTiming:
    """What a fit took: the set-up (the view, or a retarget) and the steps, in seconds, how many steps
    ran and the last step's loss."""

    setup_s: float
    steps_s: float
    steps: int
    final_loss: float

    @property
    def total_s(self) -> float:
        return self.setup_s + self.steps_s


def sync(dev: torch.device) -> None:
    """Wait for ``dev``'s queue (a GPU's), so that wall-clock timings hold the work they time."""
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def segmentation_rate(cfg: EditConfig, changed_fraction: Optional[float]) -> float:
    """The joint recipe's segmentation head's rate as a multiple of ``lr``: :data:`LARGE_EDIT_SEG_RATE`
    where the changed pixels (``changed_fraction`` of the view; None: a whole-image fit) are more than
    ``cfg.changed_share`` of it but not all, else 1."""
    if changed_fraction is not None and cfg.changed_share < changed_fraction < 1.0:
        return LARGE_EDIT_SEG_RATE
    return 1.0


def heads_optimizer(cfg: EditConfig, trainable: list[Tensor], scales: list[float]) -> EditAdam:
    """Adam over ``trainable`` (each at its ``scales`` multiple of ``cfg.lr``) with the edit's
    schedule: ``lr`` for :data:`LR_HOLD` of ``cfg.steps``, at least two steps left to the half cosine
    (its first step is still at ``lr``, so the last step's rate is lower)."""
    hold = min(int(LR_HOLD * cfg.steps), max(cfg.steps - 2, 0))
    decay = max(cfg.steps - hold, 1)
    return EditAdam(trainable, lr=cfg.lr, decay_steps=decay, hold_steps=hold, scales=scales)


def gaussian_labels(pair: Tensor, weight: Tensor, on_changed: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Each of ``count`` Gaussians labelled by where its pixel weight lands: (label [U] bool, the share
    on changed pixels above one half; trust [U], its weight times how clear that share is).

    Args:
        pair: [E] the Gaussian of each contribution entry.
        weight: [E] its weight.
        on_changed: [E] bool, whether its pixel changed."""
    mass = torch.zeros(count, device=weight.device).index_add_(0, pair, weight)
    changed = torch.zeros(count, device=weight.device).index_add_(0, pair, weight * on_changed.float())
    share = changed / mass.clamp_min(1e-12)
    return share > 0.5, mass * (2.0 * share - 1.0).abs()


def classify_gaussians(seg: SegmentationHead, seg_input: Tensor, label: Tensor, trust: Tensor,
                       scene_samples: Callable[[Tensor], Tensor], scene_size: int, cfg: EditConfig,
                       warm: bool = False, steps: Optional[int] = None) -> Tensor:
    """The ``staged`` recipe's first stage: ``seg`` trained (in place) as a classifier of the view's
    Gaussians; returns its alpha [U, 1] on them, fixed for the layer's steps. ``cfg.seg_samples``
    Gaussians are drawn by ``trust`` (half from each class of ``label``), and :data:`SEG_PRIOR_SHARE` of
    the negatives from the whole scene (``scene_samples(indices)``: their head inputs, ``scene_size``
    Gaussians to draw from); ``steps`` (default ``cfg.seg_steps``) Adam steps of binary cross-entropy
    at :data:`SEG_LR`. ``warm``: on from the head's state instead of its fresh output bias. One class
    alone gives a constant alpha.

    Args:
        seg_input: [U, F+H] the view's Gaussians' head inputs.
        label, trust: [U] from :func:`gaussian_labels`."""
    dev = seg_input.device
    pos_w, neg_w = trust * label, trust * ~label
    for p in seg.parameters():
        p.requires_grad_(False)
    if float(pos_w.sum()) <= 0.0 or float(neg_w.sum()) <= 0.0:  # one class: a constant alpha
        torch.nn.init.zeros_(seg.l2.weight)
        torch.nn.init.constant_(seg.l2.bias, 8.0 if float(pos_w.sum()) > 0.0 else -8.0)
        return torch.sigmoid(seg.logits_of(seg_input))
    half = cfg.seg_samples // 2
    n_prior = int(round(half * SEG_PRIOR_SHARE))
    g = torch.Generator(device=dev).manual_seed(cfg.seed)
    idx = torch.cat([torch.multinomial(pos_w, half, replacement=True, generator=g),
                     torch.multinomial(neg_w, half - n_prior, replacement=True, generator=g)])
    x, y = seg_input[idx], label[idx].float()[:, None]
    if n_prior > 0:  # unlabelled Gaussians of the whole scene, as weak negatives
        anywhere = torch.randint(0, scene_size, (n_prior,), device=dev, generator=g)
        x = torch.cat([x, scene_samples(anywhere)])
        y = torch.cat([y, torch.zeros(n_prior, 1, device=dev)])
    if not warm:
        torch.nn.init.constant_(seg.l2.bias, 0.0)
    params = list(seg.parameters())
    for p in params:
        p.requires_grad_(True)
    opt = EditAdam(params, lr=SEG_LR)
    with torch.enable_grad():
        for _ in range(cfg.seg_steps if steps is None else steps):
            opt.zero_grad()
            torch.nn.functional.binary_cross_entropy_with_logits(seg.logits_of(x), y).backward()
            opt.step()
    for p in params:
        p.requires_grad_(False)
    return torch.sigmoid(seg.logits_of(seg_input))


def _record(step: Callable[[], Tensor], stream: torch.cuda.Stream, pool: Optional[tuple] = None
            ) -> tuple[torch.cuda.CUDAGraph, Tensor]:
    """``step`` recorded as a CUDA graph on ``stream`` (sharing ``pool``); returns the graph and the
    loss tensor it writes. ``torch.cuda.graph`` would also wait for the GPU and empty the allocator's
    caches first, which costs every fresh edit milliseconds and sends the next edit's allocations back
    to the driver; the eager step run before on ``stream`` has already warmed its libraries up."""
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.stream(stream):
        graph.capture_begin(pool=pool)
        try:
            loss = step()
        finally:
            graph.capture_end()
    return graph, loss


class GraphedSteps:
    """A fit's steps as recorded CUDA graphs: ``graphs[i]`` runs step ``i`` of every cycle of
    ``len(graphs)`` steps (one per pixel set, or one for all when the set is chosen on the device) and
    writes its loss into ``losses[i]``. They replay while the tensors they read stay the same."""

    def __init__(self, graphs: list, losses: list[Tensor]) -> None:
        self.graphs, self.losses = graphs, losses

    @staticmethod
    def record(step: Callable[[int], Tensor], count: int, device: torch.device
               ) -> tuple[Optional["GraphedSteps"], Tensor]:
        """(the recorded steps, the first step's loss): ``step(0)`` runs once eagerly on a side stream
        (it creates Adam's state and warms the libraries up), then ``step(i)`` is recorded for each of
        ``count`` graphs. Where a step cannot be recorded (a library's host sync) it warns and returns
        None: the caller runs the remaining steps eagerly."""
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            loss = step(0)
        torch.cuda.current_stream().wait_stream(side)
        graphs: list = []
        losses: list[Tensor] = []
        try:
            for b in range(count):
                g, loss_b = _record(lambda b=b: step(b), side, graphs[0].pool() if graphs else None)
                graphs.append(g)
                losses.append(loss_b)
        except RuntimeError as e:
            warnings.warn(f"edit steps run without CUDA graphs: {str(e).splitlines()[0]}")
            return None, loss
        return GraphedSteps(graphs, losses), loss

    def replay(self, start: int, n: int, progress: Optional[Callable[[int, int], None]] = None) -> Tensor:
        """Steps ``start`` to ``n - 1`` replayed in order (``progress(done, n)`` every 10 steps and at the
        end); returns the last step's loss."""
        count = len(self.graphs)
        for i in range(start, n):
            self.graphs[i % count].replay()
            if progress is not None and ((i + 1) % 10 == 0 or i + 1 == n):
                progress(i + 1, n)
        return self.losses[(n - 1) % count].clone()


def timed(dev: torch.device, work: Callable[[], None]) -> float:
    """Seconds ``work`` takes on ``dev`` (its queue waited for before and after)."""
    sync(dev)
    t0 = time.perf_counter()
    work()
    sync(dev)
    return time.perf_counter() - t0


__all__ = ["LARGE_EDIT_SEG_RATE", "LR_HOLD", "SEG_LR", "SEG_PRIOR_SHARE", "EditTiming", "GraphedSteps",
           "classify_gaussians", "gaussian_labels", "heads_optimizer", "segmentation_rate", "sync", "timed"]
