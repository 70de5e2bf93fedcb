"""How an edit's steps run: the optimizer and its schedule, the staged recipe's classifier, and the
recorded CUDA graphs the steps replay.

- :func:`schedule`: the learning rate, ``lr`` for the first :data:`LR_HOLD` of the steps and then half a
  cosine to 0; :func:`segmentation_rate`: the segmentation head's multiple of it.
- :func:`gaussian_labels`, :func:`classifier_samples`, :func:`classifier_step`, :func:`train_classifier`: the
  ``staged`` recipe's first stage, the segmentation head trained as a classifier of the view's Gaussians (its
  gradient in torch, :func:`classifier_gradients`, or on our kernels, :func:`written_out_gradients`);
  :class:`RecordedClassifier`: its step recorded once per device and shape and replayed by every edit.
- :func:`warm_up_and_record` (a :class:`Recording`), :func:`capture`, :class:`GraphedSteps`: steps recorded
  once as CUDA graphs and replayed.
- :class:`EditTiming`, :class:`Stopwatch`: what a fit took.
"""

from __future__ import annotations

import copy
import functools
import threading
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Iterator, Optional, Sequence

import torch
from torch import Tensor

from virgi_ns.edit.config import EditConfig
from virgi_ns.edit.heads import FusedHeads, SegmentationHead
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

CLASSIFIER_GRAPH_STEPS = 10
"""Steps of the classifier recorded in one CUDA graph: a step's work is a few small kernels, so replaying
one graph per step would leave the GPU waiting on the host's launches."""

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


def schedule(cfg: EditConfig) -> tuple[int, int]:
    """(hold, decay): the edit's learning rate stays at ``cfg.lr`` for ``hold`` steps, :data:`LR_HOLD` of
    ``cfg.steps`` with at least two steps left to the half cosine (its first step is still at ``lr``, so the
    last step's rate is lower), then falls to 0 over ``decay`` steps (:class:`~virgi_ns.edit.optim.EditAdam`'s
    ``hold_steps`` and ``decay_steps``)."""
    hold = min(int(LR_HOLD * cfg.steps), max(cfg.steps - 2, 0))
    return hold, max(cfg.steps - hold, 1)


def gaussian_labels(pair: Tensor, weight: Tensor, on_changed: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Each of ``count`` Gaussians labelled by where its pixel weight lands: (label [U] bool, the share
    on changed pixels above one half; trust [U], its weight times how clear that share is).

    Args:
        pair: [E] the Gaussian of each contribution entry (int32 or int64).
        weight: [E] its weight.
        on_changed: [E] bool, whether its pixel changed."""
    mass = torch.zeros(count, device=weight.device).index_add_(0, pair, weight)
    changed = torch.zeros(count, device=weight.device).index_add_(0, pair, weight * on_changed)
    share = changed / mass.clamp_min(1e-12)
    return share > 0.5, mass * (2.0 * share - 1.0).abs()


def classifier_samples(label: Tensor, trust: Tensor, cfg: EditConfig, scene_size: int
                       ) -> Optional[tuple[Tensor, Tensor]]:
    """What the ``staged`` recipe's classifier trains on: (indices [S] of the view's Gaussians, drawn by
    ``trust``, half from each class of ``label``; indices [R] of unlabelled Gaussians of the whole scene, of
    ``scene_size``, the :data:`SEG_PRIOR_SHARE` of the negatives that are weak negatives), ``cfg.seg_samples``
    in all, from a generator seeded with ``cfg.seed``; None where one class is empty (a constant alpha,
    :func:`constant_segmentation`).

    Args:
        label, trust: [U] from :func:`gaussian_labels`."""
    pos_w, neg_w = trust * label, trust * ~label
    pos, neg = torch.stack([pos_w.sum(), neg_w.sum()]).tolist()  # one read from the GPU
    if pos <= 0.0 or neg <= 0.0:
        return None
    half = cfg.seg_samples // 2
    n_prior = int(round(half * SEG_PRIOR_SHARE))
    g = torch.Generator(device=trust.device).manual_seed(cfg.seed)
    idx = torch.cat([torch.multinomial(pos_w, half, replacement=True, generator=g),
                     torch.multinomial(neg_w, half - n_prior, replacement=True, generator=g)])
    anywhere = torch.randint(0, scene_size, (n_prior,), device=trust.device, generator=g)
    return idx, anywhere


def constant_segmentation(seg: SegmentationHead, seg_input: Tensor, positive: bool) -> Tensor:
    """``seg`` set (in place) to a constant alpha, near 1 (``positive``) or near 0, frozen; returns it on the
    view's Gaussians ([U, 1]; ``seg_input`` [U, F+H])."""
    for p in seg.parameters():
        p.requires_grad_(False)
    torch.nn.init.zeros_(seg.l2.weight)
    torch.nn.init.constant_(seg.l2.bias, 8.0 if positive else -8.0)
    return torch.sigmoid(seg.logits_of(seg_input))


def classifier_gradients(seg: SegmentationHead, x: Tensor, y: Tensor) -> None:
    """The gradient of the classifier's loss (binary cross-entropy of ``seg``'s logits on ``x`` [S, F+H]
    against ``y`` [S, 1], the mean over the samples) in each of ``seg``'s parameters' ``.grad``, written
    out: autograd's result in fewer kernels, which a recorded step replays."""
    l1, l2 = seg.l1, seg.l2
    pre = torch.addmm(l1.bias, x, l1.weight.t())
    hidden = torch.relu(pre)
    d_logit = (torch.sigmoid(torch.addmm(l2.bias, hidden, l2.weight.t())) - y) / x.shape[0]
    l2.weight.grad = d_logit.t() @ hidden
    l2.bias.grad = d_logit.sum(0)
    d_pre = (d_logit @ l2.weight) * (pre > 0)
    l1.weight.grad = d_pre.t() @ x
    l1.bias.grad = d_pre.sum(0)


def written_out_gradients(seg: SegmentationHead, x: Tensor, y: Tensor) -> None:
    """:func:`classifier_gradients`' result from our kernels (``csrc/classifier.cu``): two kernels where torch
    runs a dozen, the same sums in every run. Where :func:`writes_out` says they run."""
    from virgi_ns.raster import cuda

    l1, l2 = seg.l1, seg.l2
    W, D = l1.weight.shape
    g = cuda.classifier_gradients(x, y, l1.weight, l1.bias, l2.weight, l2.bias)
    l1.weight.grad = g[: W * D].view(W, D)
    l1.bias.grad = g[W * D : W * D + W]
    l2.weight.grad = g[W * D + W : W * D + 2 * W].view(1, W)
    l2.bias.grad = g[W * D + 2 * W :]


def writes_out(seg: SegmentationHead, x: Tensor, cfg: EditConfig) -> bool:
    """Whether the classifier's gradient runs on our kernels (:func:`written_out_gradients`): with
    ``cfg.fused_heads``, float32 samples on a GPU, the extension built, a head the kernels take."""
    if not (cfg.fused_heads and x.dtype == torch.float32 and seg.l1.weight.dtype == torch.float32
            and FusedHeads.runs_on(seg, x.device)):
        return False
    from virgi_ns.raster import cuda

    return cuda.classifier_fits(x.shape[1], seg.width, x.device)


def classifier_step(seg: SegmentationHead, x: Tensor, y: Tensor, opt: EditAdam, written_out: bool = False) -> None:
    """One step of the classifier: its gradient (:func:`written_out_gradients` where ``written_out``, else
    :func:`classifier_gradients`), then ``opt``'s step."""
    (written_out_gradients if written_out else classifier_gradients)(seg, x, y)
    opt.step()


def train_classifier(seg: SegmentationHead, x: Tensor, y: Tensor, seg_input: Tensor, cfg: EditConfig,
                     warm: bool = False, steps: Optional[int] = None) -> Tensor:
    """The ``staged`` recipe's first stage: ``seg`` trained (in place) as a classifier of the inputs ``x``
    [S, F+H] with labels ``y`` [S, 1] (binary cross-entropy, Adam at :data:`SEG_LR`, ``steps`` steps, default
    ``cfg.seg_steps``, on all of them every step), then frozen; returns its alpha [U, 1] on the view's
    Gaussians (``seg_input``), fixed for the layer's steps. ``warm``: on from the head's state instead of
    its fresh output bias. Its gradient runs on our kernels where :func:`writes_out` says so. On a GPU with
    ``cfg.cuda_graphs`` the steps replay recorded CUDA graphs (the same kernels without a Python round trip
    each), recorded once per device and shape (:class:`RecordedClassifier`); where a step cannot be recorded
    they run eagerly."""
    if not warm:
        torch.nn.init.constant_(seg.l2.bias, 0.0)
    params = list(seg.parameters())
    for p in params:
        p.requires_grad_(False)
    n = cfg.seg_steps if steps is None else steps
    written_out = writes_out(seg, x, cfg)
    with torch.no_grad():
        if not (cfg.cuda_graphs and x.is_cuda and n > 2 and RecordedClassifier.train(seg, x, y, n, written_out)):
            opt = EditAdam(params, lr=SEG_LR)
            for _ in range(n):
                classifier_step(seg, x, y, opt, written_out)
            for p in params:
                p.grad = None
        return torch.sigmoid(seg.logits_of(seg_input))


class RecordedClassifier:
    """The ``staged`` classifier's step (:func:`classifier_step`, Adam at :data:`SEG_LR`) recorded as CUDA
    graphs of one step and of :data:`CLASSIFIER_GRAPH_STEPS` steps over tensors of its own, kept per device,
    shape (samples, inputs, width) and gradient (torch's or our kernels') so that an edit replays them
    instead of recording them again: :meth:`train` copies a head and its samples in, restarts Adam and
    replays the steps; the head gets the trained parameters back."""

    _kept: dict[tuple, "RecordedClassifier"] = {}
    _failed: set[tuple] = set()
    _lock = threading.Lock()

    def __init__(self, seg: SegmentationHead, x: Tensor, y: Tensor, written_out: bool) -> None:
        self.seg = copy.deepcopy(seg)
        self.params = list(self.seg.parameters())
        for p in self.params:
            p.requires_grad_(False)
        self.x, self.y = x.clone(), y.clone()
        self.opt = EditAdam(self.params, lr=SEG_LR)
        step = functools.partial(classifier_step, self.seg, self.x, self.y, self.opt, written_out)

        def several() -> None:
            for _ in range(CLASSIFIER_GRAPH_STEPS):
                step()

        recording = warm_up_and_record(step, [step, several], x.device)
        self.one, self.several = recording.graphs if recording.graphs else (None, None)
        self.error = recording.error

    @classmethod
    def train(cls, seg: SegmentationHead, x: Tensor, y: Tensor, steps: int, written_out: bool) -> bool:
        """``seg`` trained ``steps`` steps on ``x``, ``y`` by replays (of the step with our kernels where
        ``written_out``); False (nothing done) where the step cannot be recorded on this device (warned
        once), so that the caller runs it eagerly."""
        key = (x.device, tuple(x.shape), seg.width, written_out)
        with cls._lock:
            if key in cls._failed:
                return False
            rec = cls._kept.get(key)
            if rec is None:
                rec = cls(seg, x, y, written_out)
                if rec.one is None:
                    cls._failed.add(key)
                    warnings.warn(f"the segmentation classifier runs without a CUDA graph: {rec.error}")
                    return False
                cls._kept[key] = rec
            for mine, theirs in zip(rec.params, seg.parameters()):
                mine.copy_(theirs)
            rec.x.copy_(x)
            rec.y.copy_(y)
            rec.opt.restart()
            for _ in range(steps // CLASSIFIER_GRAPH_STEPS):
                rec.several.replay()
            for _ in range(steps % CLASSIFIER_GRAPH_STEPS):
                rec.one.replay()
            for mine, theirs in zip(rec.params, seg.parameters()):
                theirs.copy_(mine)
        return True


@dataclass
class Recording:
    """What :func:`warm_up_and_record` made: the warm-up's result (``first``), then either the graphs with each
    recorded call's result (``results``), or, where a kernel could not be recorded, ``graphs`` None and the
    error's first line (``error``)."""

    first: object
    graphs: Optional[list] = None
    results: list = field(default_factory=list)
    error: str = ""


def warm_up_and_record(warm_up: Callable[[], object], steps: Sequence[Callable[[], object]], device: torch.device
                       ) -> Recording:
    """``warm_up`` run once eagerly on a side stream (it creates Adam's state and warms the libraries
    up), then each of ``steps`` recorded into a CUDA graph of its own, sharing one memory pool; recording
    runs nothing. Where a kernel cannot be recorded (a library's host sync) the recording says why and the
    caller runs on eagerly."""
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        first = warm_up()
    torch.cuda.current_stream().wait_stream(side)
    graphs: list = []
    results: list = []
    try:
        for step in steps:
            graph = torch.cuda.CUDAGraph()
            with capture(graph, side, graphs[0].pool() if graphs else None):
                results.append(step())
            graphs.append(graph)
    except RuntimeError as e:
        return Recording(first, error=str(e).splitlines()[0])
    return Recording(first, graphs, results)


@contextmanager
def capture(graph: torch.cuda.CUDAGraph, stream: torch.cuda.Stream, pool: Optional[tuple] = None) -> Iterator[None]:
    """Record the work of the ``with`` body into ``graph`` on ``stream`` (sharing ``pool``).
    ``torch.cuda.graph`` would also wait for the GPU and empty the allocator's caches first, which costs every
    fresh edit milliseconds and sends the next edit's allocations back to the driver; an eager step run
    before on ``stream`` warms the libraries up instead."""
    with torch.cuda.stream(stream):
        graph.capture_begin(pool=pool)
        try:
            yield
        finally:
            graph.capture_end()


class GraphedSteps:
    """A fit's steps as recorded CUDA graphs: ``graphs[i]`` runs step ``i`` of every cycle of
    ``len(graphs)`` steps (one per pixel set, or one for all when the set is chosen on the device) and
    writes its loss into ``losses[i]``. They replay while the tensors they read stay the same."""

    def __init__(self, graphs: list, losses: list[Tensor]) -> None:
        self.graphs, self.losses = graphs, losses

    def replay(self, start: int, n: int, progress: Optional[Callable[[int, int], None]] = None) -> Tensor:
        """Steps ``start`` to ``n - 1`` replayed in order (``progress(done, n)`` every 10 steps and at the
        end); returns the last step's loss."""
        count = len(self.graphs)
        for i in range(start, n):
            self.graphs[i % count].replay()
            if progress is not None and ((i + 1) % 10 == 0 or i + 1 == n):
                progress(i + 1, n)
        return self.losses[(n - 1) % count].clone()


class Stopwatch:
    """Seconds of the ``with`` body's work on ``device`` (its queue waited for before and after):
    ``with Stopwatch(dev) as watch: ...``, then ``watch.seconds``."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.seconds = 0.0

    def __enter__(self) -> "Stopwatch":
        sync(self.device)
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        sync(self.device)
        self.seconds = time.perf_counter() - self._t0


__all__ = ["CLASSIFIER_GRAPH_STEPS", "LARGE_EDIT_SEG_RATE", "LR_HOLD", "SEG_LR", "SEG_PRIOR_SHARE", "EditTiming",
           "GraphedSteps", "Recording", "RecordedClassifier", "Stopwatch", "capture", "classifier_gradients",
           "classifier_samples", "classifier_step", "constant_segmentation", "gaussian_labels", "schedule",
           "segmentation_rate", "sync", "train_classifier", "warm_up_and_record", "writes_out",
           "written_out_gradients"]
