"""The edit engine: one edited image of one view recolours the whole scene.

Geometry is frozen, so the edited view's pixels are a fixed linear map of per-Gaussian colours
(``pixel = A C + T bg``, :mod:`virgi_ns.raster.contract`). :class:`EditEngine` computes, once:
the view's contributions as a sparse matrix ``A`` (and ``A^T`` for the backward pass), the hash
features ``f`` and ``h_diff`` of the Gaussians the view sees, the colour ``c_d`` the current
stack gives them, and their specular ``c_s`` for this camera. Each optimisation step then trains
only a copy of the diffuse head and a segmentation head::

    c_d'  = W h_diff + b                       (W, b start as the base diffuse head, or, for a
                                                large edit, as M W, M b + t: see below)
    alpha = sigmoid(MLP_seg([f, h_diff]))      (starts near 0)
    c_d'' = alpha c_d' + (1 - alpha) c_d
    C'    = sigmoid(c_d'' + k c_s)
    loss  = L1(A C' + T bg, I_target)          (Adam; optionally on a subset of pixels per step)

``I_target`` is the edited image. When the unedited image is known too (``original``: the
training photo the user recoloured), only the pixels the user changed are fitted to the edit
(by default to the edited pixel moved by the model's reconstruction error there as the user's change
moves colours, ``changed_target="affine"``; or to the edited image's own pixels, the paper's);
every other pixel's
target is the scene's current render there. Otherwise the edit would also
"repair" the model's reconstruction error all over the view (the photo is not the render), and
that repair would leak into every view. An edited *render* needs no original: most of its pixels
equal the current render, which identifies the changed ones. The changed pixels carry half the
loss however few they are (``changed_share``), so a small edit is not outvoted by the many
pixels that ask for no change; optionally (``near_share``) the unchanged pixels next to the change
carry a part of the rest of their own, so a part of another colour inside a recoloured object is not
outvoted by the background. When the changed pixels cover at least a fifth of the view
(``map_init_min_share``), the copied layer starts from the affine colour map ``[M | t]`` that best
takes the current render's logits to the changed pixels' (least squares,
:func:`logit_colour_map`), so ``c_d'`` starts at ``M c_d + t``: a large recolour of many different
colours (a hue shift of 120 degrees is a channel permutation, exactly such a map) starts where
100 steps from the base layer do not reach.

That is the ``joint`` recipe (the paper's: both heads on the pixel loss). The ``staged`` recipe
(``EditConfig.recipe``) trains the segmentation first, as a classifier of the view's Gaussians
labelled by where their weight lands (changed pixels or not), so a part of another colour inside a
recoloured object is not outvoted by the object around it; it then fits the layer, from the colour
map, with the segmentation fixed. ``changed_target="transfer"`` fits the changed pixels to the
render moved by the user's change in logits, instead of to the edited photo's own pixels;
``changed_target="map"`` to the render changed as the user changed pixels of its colour
(:mod:`virgi_ns.edit.colour_change`), where that explains the user's change.

The result is an :class:`~virgi_ns.edit.stack.Edit` for the :class:`EditStack`. The engine reads
the model through a :class:`~virgi_ns.edit.scene.FrozenScene`; the view's pixels are split into
sparse batches by :mod:`virgi_ns.edit.pixels`.
"""

from __future__ import annotations

import copy
import functools
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Callable, Literal, Optional

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.colour.field import view_directions
from virgi_ns.edit.colour_change import fit_colour_change
from virgi_ns.edit.heads import FusedHeads, HeadsInputs
from virgi_ns.edit.optim import EditAdam
from virgi_ns.edit.pixels import PixelBatch, near_changed, parse_composite, pixel_batches, resolve_composite
from virgi_ns.edit.scene import FrozenScene
from virgi_ns.edit.stack import Edit, EditSource, EditStack, SegmentationHead, new_edit_info
from virgi_ns.errors import InputError
from virgi_ns.raster import Cameras, Request, composite


@dataclass
class EditConfig:
    """Knobs of one edit."""

    steps: int = 100
    """Adam steps. Where ``virgi-bench accuracy-time`` finds the knee on beercan: propagation and miss
    PSNR level off by then (bench/RESULTS.md, "Accuracy against time")."""
    lr: float = 2e-2
    """Learning rate of both heads."""
    lr_schedule: str = "cosine"
    """``cosine``: ``lr`` for the first ``lr_hold`` of the steps, then by half a cosine to 0 at ``steps``,
    counted over every :meth:`EditEngine.fit` of one target (a retarget starts it again): the fit
    settles where a constant rate leaves it moving, and fits of one edit spread less (bench/RESULTS.md,
    "Why one fit's spread"); steps past ``steps`` move nothing. ``constant``: ``lr`` at every step
    (the default before run sets 23 and 24)."""
    lr_hold: float = 0.5
    """With ``lr_schedule="cosine"``: the fraction of ``steps`` at the full rate before the half cosine
    (which then spans the remaining steps), so the fit travels far first and settles after: a cosine
    from the first step travels half as far, too little where the colour map starts far from the target.
    It passed the rule written before run sets 23 and 24, as did the cosine over 200 steps, which the
    rule's tie-break preferred but which breaks the 50 ms edit at 1M Gaussians (bench/RESULTS.md,
    "Edit"). 0: the decay starts at the first step."""
    seg_rate_scale: float = 1.0
    """The joint recipe: the segmentation head's learning rate as a multiple of ``lr`` (the copied
    layer keeps ``lr``). The two heads can trade a soft segmentation against a larger colour change
    (the render sees their product), and which of them moves faster decides where the fit ends:
    ``lr`` raised for both softened the segmentation (bench/RESULTS.md, "Edit")."""
    map_seg_rate_scale: float = 1.0
    """The joint recipe, where the copied layer starts from the colour map (a large edit,
    ``map_init_min_share``): ``seg_rate_scale`` is multiplied by this. There the layer starts near its
    target and what is left to fit is mostly where the segmentation lands; from the base layer the
    layer must travel far, and a faster head racing it moved small objects' fits (bench/RESULTS.md,
    "Edit")."""
    large_edit_seg_rate_scale: float = 2.0
    """The joint recipe, where the changed pixels cover more of the view than ``changed_share`` but not
    all of it: there each unchanged pixel weighs more than a changed one, and together they pull the
    segmentation head down inside the recoloured object too, so ``seg_rate_scale`` is multiplied by
    this. A faster head
    sharpens the segmentation there and passed the rule of run sets 36 and 37; where nothing pulls it
    down, a faster head can run into the sigmoid's flat tail (bench/RESULTS.md, "Edit"). 1: the rate
    of every other edit. Off with ``changed_share_floor``, which weighs every pixel alike there."""
    seg_width: int = 64
    """Hidden width of the segmentation head."""
    seg_init_bias: float = -4.0
    """Initial output bias of the segmentation head (alpha starts at sigmoid of it)."""
    pixel_batches: int = 4
    """Split the view's pixels into this many random sets and use one per step (1: the whole
    image every step); 4 is as accurate as 1 and cheaper per step (bench/RESULTS.md, "Edit")."""
    batch_composite: str = "auto"
    """How a step applies its pixel set's sparse matrix ``A`` (pixels x Gaussians) to the colours, and
    ``A^T`` to the gradient (:mod:`virgi_ns.edit.pixels`): ``fused`` (one CUDA kernel for the
    composite and the L1 loss, reading the view's own entries, and one that gathers the gradient per
    Gaussian over the entries sorted by Gaussian once per edit: no matrix per set, and one recorded
    graph for every set; the torch reference on a CPU), ``fused_atomics`` (the same loss kernel
    scattering the gradient by one atomic per entry), ``csr`` (cuSPARSE, int64
    indices), ``csr32`` (int32 indices), ``csr4`` (int32, colours padded to 4 columns), ``csr_cm``
    (int32, colours column-major), ``segment`` (gather, weight, ``torch.segment_reduce`` per pixel /
    per Gaussian), ``index_add`` (gather, weight, ``index_add_``: atomics), ``embedding_bag`` (one
    fused gather-weight-sum kernel each way); or ``FWD/BWD``, one matrix kind per pass (e.g.
    ``embedding_bag/index_add``); ``auto`` (the default): the fastest on a GPU by
    ``bench/edit_step.py`` (``fused``), ``csr`` on a CPU. All give the same edit up to float rounding."""
    seed: int = 0
    """Seeds the segmentation head's initialisation and the pixel sets."""
    unchanged_tol: float = 3.0 / 255.0
    """Pixels whose colour moved by at most this (every channel) from the image the user started
    from (the original, or the current render) are not part of the edit: their target is the current
    render. Covers an 8-bit round trip; strong JPEG compression of the edited image can exceed it
    (noise then counts as a change: save edits as PNG)."""
    changed_share: float = 0.5
    """With an ``original`` image: the share of the loss carried by the changed pixels (the rest by
    the unchanged ones), whatever their numbers; a small edit would otherwise be outvoted by the
    many pixels asking for no change."""
    changed_share_floor: bool = False
    """Take ``changed_share`` as a floor: an edit that changes more of the view than ``changed_share``
    gives its changed pixels their own fraction of the loss (every pixel's equal weight, but for
    ``near_share``'s split of the unchanged pixels' part), so the
    few unchanged pixels of a large edit are not each weighted up over a changed one (a 90% edit's
    unchanged tenth otherwise weighs 9 times as much per pixel, and pulls the segmentation down over
    the object). Off: on cup it sharpened the segmentation on the object but spread it over the
    similar-coloured surface beside it, which the heavy unchanged pixels had kept out (bench/RESULTS.md,
    "Edit"). An edit that changes at most ``changed_share`` of the view fits exactly as without it."""
    near_share: float = 0.0
    """With the changed pixels known: the part of the unchanged pixels' share of the loss carried by
    the unchanged pixels within ``near_radius`` of a changed one (a part of another colour inside the
    recoloured object, the object's rim), the far ones carrying the rest; 0 (the default): every
    unchanged pixel weighs the same, so a small part inside the object is a sliver of a loss that is
    mostly background."""
    near_radius: float = 0.015
    """``near_share``: how far from a changed pixel an unchanged one counts as near, as a fraction of
    the view's shorter side (rounded up to whole pixels)."""
    changed_target: Literal["change", "transfer", "map", "affine", "edited"] = "affine"
    """What the changed pixels are fitted to when the unedited image is a photo (``original``):
    ``affine`` (the default): the edited pixel moved by the model's reconstruction error there, as
    the user's change would move it: ``edited + J (render - original)``, with ``J`` the slope of the
    best affine fit of the edited colours to the original ones over all changed pixels
    (:func:`change_slope`); exact for a change that is affine in colour (a hue shift of 120 degrees
    permutes the channels), first order for any other; chosen over ``map`` on two fresh run sets
    by a rule fixed before they ran (bench/RESULTS.md, "Edit");
    ``change``: the current render plus the change the user made (edited - original, clamped to
    [0, 1]), so the photo's detail the model never reproduced is not fitted as part of the edit;
    ``transfer``: the same change as a shift of logits, ``sigmoid(logit(render) + logit(edited) -
    logit(original))`` (colours clamped to [0.02, 0.98]), which keeps the render's colour where the
    change saturates;
    ``map`` (the previous default): the render changed as the user changed pixels of the same colour
    in the photo (the change learnt as a function of colour, :mod:`virgi_ns.edit.colour_change`), on
    the changed pixels that function explains; the others as ``map_fallback`` says; its grid's
    interpolation error is larger than a small reconstruction error (bench/RESULTS.md, "Edit");
    ``edited``: the edited image itself (the paper's: the photo's detail the model never reproduced
    goes into the edit; with ``change`` the photo's colour delta lands on the render's base colour
    where the two differ; ``transfer`` helps the edits that cover most of the view and loses on
    small ones).
    The same thing for an edited render (original = render); no effect with ``whole_image``."""
    map_levels: int = 1
    """``changed_target="map"``: grid levels of the colour map, 1 (17 points per axis) to 3 (17, 33
    and 65: at each colour the coarsest level that is one change answers, so a colour that a coarse
    cell mixes with others changed differently, near a rule's threshold, can still use the map;
    :mod:`virgi_ns.edit.colour_change`). Selectable, not the default (bench/RESULTS.md, "Edit")."""
    map_fallback: Literal["edited", "change"] = "change"
    """``changed_target="map"``: the target of a changed pixel the colour map does not explain (or
    that is not one change at the render's colour): ``change`` (the default), the current render
    plus that pixel's own change (edited - original, clamped), which keeps the model's
    reconstruction error out of the target there too; ``edited``, the edited image's pixel. Chosen
    on a fresh run set by a rule fixed before it ran (bench/RESULTS.md, "Edit")."""
    map_gate: Literal["spread", "error"] = "spread"
    """``changed_target="map"``: where the map's change is trusted at a render colour: ``spread``
    (the default), where the changes the user made near that colour are one change (their spread
    within a quarter of the change); ``error``, also where that spread is below the pixel's own
    render-photo difference (largest channel), the error the edited pixel would bring as its
    target: small changes near a rule's threshold, refused by the relative test, then use the map.
    Measured, not the default: it made cup worse (bench/RESULTS.md, "Edit")."""
    whole_image: bool = False
    """Fit every pixel to the edited image (no original, no edited-render detection)."""
    map_init: bool = True
    """For a large edit (``map_init_min_share``), start the copied last layer from the affine colour
    map, in logit space, that best takes the current render to the target on the changed pixels
    (least squares, a 3x4 matrix): the layer then starts at ``M c_d + t`` instead of ``c_d`` (``c_d`` of
    the base layer: with earlier edits in the stack the map is fitted on their render but applied
    to the base layer, an approximate start). A hue
    shift of 120 or 240 degrees, or any channel mix, is such a map exactly; other edits start close
    to it. No effect when the changed pixels are unknown (``whole_image``, or an edited image that
    matches neither the original nor the render)."""
    map_init_min_share: float = 0.2
    """The share of the view's pixels an edit must change for ``map_init``: the map helps a large,
    many-coloured recolour; when it already gives a small edit its colour, the segmentation head
    fits the edited view's pixels literally and spreads less over the rest of the object (on the
    CPU test scene a 7x7-pixel patch then recolours only its own spot). On the evaluation set the
    gate is within 0.2 dB of always or never using the map on beercan and cup (bench/RESULTS.md,
    "The suspects, measured apart")."""
    render_match_min: float = 0.5
    """Without an ``original``: when at least this share of the edited image's pixels equal the
    current render (within ``unchanged_tol``), the image is an edited render and only the other
    pixels are fitted to it (as with an original); otherwise every pixel is."""
    recipe: Literal["joint", "staged"] = "joint"
    """How the two heads are fitted. ``joint`` (the paper's recipe): both heads trained together on
    the pixel loss. ``staged``: the segmentation first, as a classifier of which Gaussians the edit
    changed (each visible Gaussian labelled by the share of its pixel weight on changed pixels and
    trusted in proportion to its weight and to how clear that share is; the two classes weigh the
    same, so a part of another colour inside a recoloured object is not outvoted by the object),
    then the copied layer, from the colour map of the changed pixels, on the pixel loss with the
    segmentation fixed. Needs the changed pixels (a whole-image fit falls back to ``joint``)."""
    seg_steps: int = 300
    """``staged``: Adam steps of the segmentation classifier."""
    seg_lr: float = 1e-2
    """``staged``: learning rate of the segmentation classifier."""
    seg_samples: int = 65536
    """``staged``: Gaussians drawn (by their label weight, half from each class) to train the
    classifier on; every step uses all of them."""
    seg_prior_share: float = 0.2
    """``staged``: the share of the negative class drawn from the whole scene, unlabelled (most of a
    scene is not part of an edit): keeps the segmentation off what the edited view never showed
    unless it resembles what the edit changed."""

    fused_heads: bool = True
    """On a GPU with the ``fused`` kind and the joint recipe, the heads' forward and backward as written
    out in :mod:`virgi_ns.edit.heads` (two cuBLAS products and two kernels) instead of through autograd:
    the same step up to float rounding, in a fraction of the kernels."""
    cuda_graphs: bool = True
    """On a GPU, record each pixel set's step once as a CUDA graph and replay it (the same kernels,
    without a Python and launch round trip per kernel); a first fit of a few steps runs eagerly, and
    later fits replay the recorded steps while a warm retarget keeps them valid."""

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Refuse values no edit can run with (also called by the engine: fields may be set later)."""
        if self.changed_target not in ("change", "transfer", "map", "affine", "edited"):
            raise ValueError(f"EditConfig.changed_target must be 'change', 'transfer', 'map', 'affine' or 'edited', "
                             f"got {self.changed_target!r}")
        if self.map_gate not in ("spread", "error"):
            raise ValueError(f"EditConfig.map_gate must be 'spread' or 'error', got {self.map_gate!r}")
        if self.map_fallback not in ("edited", "change"):
            raise ValueError(f"EditConfig.map_fallback must be 'edited' or 'change', got {self.map_fallback!r}")
        if not 1 <= self.map_levels <= 3:
            raise ValueError(f"EditConfig.map_levels must be 1, 2 or 3, got {self.map_levels}")
        parse_composite(self.batch_composite)  # ValueError naming the kinds
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"EditConfig.lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}")
        if not self.seg_rate_scale > 0.0:
            raise ValueError(f"EditConfig.seg_rate_scale must be > 0, got {self.seg_rate_scale}")
        if not self.map_seg_rate_scale > 0.0:
            raise ValueError(f"EditConfig.map_seg_rate_scale must be > 0, got {self.map_seg_rate_scale}")
        if not self.large_edit_seg_rate_scale > 0.0:
            raise ValueError(f"EditConfig.large_edit_seg_rate_scale must be > 0, got {self.large_edit_seg_rate_scale}")
        if not 0.0 <= self.lr_hold < 1.0:
            raise ValueError(f"EditConfig.lr_hold must be in [0, 1), got {self.lr_hold}")
        if self.recipe not in ("joint", "staged"):
            raise ValueError(f"EditConfig.recipe must be 'joint' or 'staged', got {self.recipe!r}")
        if self.seg_steps < 0 or self.seg_samples < 2:
            raise ValueError(f"EditConfig: seg_steps must be >= 0 and seg_samples >= 2 "
                             f"(got {self.seg_steps}, {self.seg_samples})")
        if not 0.0 <= self.seg_prior_share < 1.0:
            raise ValueError(f"EditConfig.seg_prior_share must be in [0, 1), got {self.seg_prior_share}")
        if self.steps < 0 or self.pixel_batches < 1:
            raise ValueError(f"EditConfig: steps must be >= 0 and pixel_batches >= 1 "
                             f"(got {self.steps}, {self.pixel_batches})")
        if not 0.0 <= self.map_init_min_share <= 1.0:
            raise ValueError(f"EditConfig.map_init_min_share must be in [0, 1], got {self.map_init_min_share}")
        if not 0.0 < self.changed_share < 1.0:
            raise ValueError(f"EditConfig.changed_share must be in (0, 1), got {self.changed_share}")
        if not 0.0 <= self.near_share < 1.0 or self.near_radius < 0.0:
            raise ValueError(f"EditConfig: near_share must be in [0, 1) and near_radius >= 0 "
                             f"(got {self.near_share}, {self.near_radius})")


@dataclass
class EditTiming:
    setup_s: float
    steps_s: float
    steps: int
    final_loss: float

    @property
    def total_s(self) -> float:
        return self.setup_s + self.steps_s


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _logit(x: Tensor, eps: float = 0.02) -> Tensor:
    return torch.logit(x.clamp(eps, 1.0 - eps))


def _render_plus_change(render: Tensor, edited: Tensor, original: Tensor) -> Tensor:
    """The render moved by the user's change of each pixel, ``edited - original`` (clamped to [0, 1]):
    ``changed_target="change"``, and the colour map's ``map_fallback="change"``."""
    return (render + (edited - original)).clamp(0.0, 1.0)


SLOPE_RIDGE = (1.0 / 255.0) ** 2
"""Ridge of :func:`change_slope`: along a direction of colour in which the changed pixels vary by less
than one 8-bit level the photo says little of how the change varies, so the slope there shrinks
towards 0 (no correction: the render plus the pixel's own change)."""


SLOPE_MIN_PIXELS = 64
"""Fewest changed pixels :func:`change_slope` fits a slope to: the fit has 12 parameters, and with
fewer than about five pixels each a chance correlation of a few dabs of paint fits as well as a
colour rule; a smaller edit gets no slope (the render plus each pixel's own change)."""


def change_slope(original: Float[Tensor, "N 3"], edited: Float[Tensor, "N 3"]) -> Float[Tensor, "3 3"]:
    """``J``, the slope of the best affine fit ``edited ~ J original + b`` over these pixels (least
    squares, the slope's excess over identity ridged by :data:`SLOPE_RIDGE`): how the user's change
    moves with the colour it starts from. The excess is scaled by the share of the change's variance
    the fit explains, adjusted for the fit's 4 parameters per channel (R^2 above 0.99 on every scene
    of the evaluation set), so a change that is no function of colour (strokes of paint) gets no
    slope from colours that only happen to correlate with it; under :data:`SLOPE_MIN_PIXELS`, identity."""
    o = original.reshape(-1, 3).double()
    n = o.shape[0]
    eye = torch.eye(3, dtype=original.dtype, device=original.device)
    if n < SLOPE_MIN_PIXELS:
        return eye
    d = edited.reshape(-1, 3).double() - o
    o, d = o - o.mean(0), d - d.mean(0)
    total = (d ** 2).sum()
    if total <= 0:  # one change for every pixel: nothing varies with colour
        return eye
    cov = o.T @ o / n + SLOPE_RIDGE * torch.eye(3, dtype=o.dtype, device=o.device)
    excess = torch.linalg.solve(cov, o.T @ d / n).T
    unexplained = ((d - o @ excess.T) ** 2).sum() / total
    explained = (1.0 - unexplained * (n - 1) / (n - 4)).clamp(0.0, 1.0)
    return eye + (explained * excess).to(original.dtype)


def changed_pixels_target(cfg: EditConfig, render: Float[Tensor, "H W 3"], edited: Float[Tensor, "H W 3"],
                          original: Float[Tensor, "H W 3"], changed: Tensor) -> tuple[Tensor, Optional[float]]:
    """What the pixels a user changed in a photo (``original`` -> ``edited``; ``changed`` [H,W]) are
    fitted to, by ``cfg.changed_target`` (:class:`EditConfig`), as an image (read on the changed
    pixels only); and, for ``map``, the share of changed pixels the colour map answered."""
    changed = changed.reshape(render.shape[:-1])
    kind = cfg.changed_target
    if kind == "change":
        return _render_plus_change(render, edited, original), None
    if kind == "transfer":
        return torch.sigmoid(_logit(render) + _logit(edited) - _logit(original)), None
    if kind == "affine":
        slope = change_slope(original[changed], edited[changed])
        return (edited + (render - original) @ slope.T).clamp(0.0, 1.0), None
    if kind == "map":
        # the render changed by the colour map of the user's change where the map explains that
        # pixel's change and is one change at the render's colour (virgi_ns.edit.colour_change);
        # elsewhere the edited pixel, or with map_fallback="change" the render plus that pixel's change
        change = fit_colour_change(original, edited, levels=cfg.map_levels)
        flat_o, flat_e, flat_r = original.reshape(-1, 3), edited.reshape(-1, 3), render.reshape(-1, 3)
        own = (flat_r - flat_o).abs().amax(-1) if cfg.map_gate == "error" else None
        mapped, one = change.apply_where_one_change(flat_r, own)
        use = change.explains(flat_o, flat_e) & one
        fallback = flat_e if cfg.map_fallback == "edited" else _render_plus_change(flat_r, flat_e, flat_o)
        target = torch.where(use[:, None], mapped, fallback).reshape(edited.shape)
        return target, float(use[changed.reshape(-1)].float().mean())
    return edited, None


@functools.lru_cache(maxsize=4)
def _pixel_subset(n: int, k: int, seed: int) -> Tensor:
    """The first ``k`` of a permutation of ``n`` drawn on the CPU with ``seed`` (the same on every
    device). Kept for the next call: a live drag asks for the same subset at every change, and the
    permutation of a megapixel view takes tens of milliseconds."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    return torch.randperm(n, generator=g)[:k]


GLOBAL_RNG_LOCK = threading.Lock()
"""Held while the global CPU random state is seeded or forked here, so that another thread (the
warm-up, :mod:`virgi_ns.edit.warmup`) cannot draw from it between a seed and its use."""


@functools.lru_cache(maxsize=8)
def _fresh_segmentation(feature_dim: int, hidden_dim: int, width: int, init_bias: float, seed: int,
                        device: torch.device) -> SegmentationHead:
    """A fresh segmentation head drawn on the CPU with ``seed`` (the same on every device), moved to
    ``device`` and kept there for the next edit of the same shape: building it took about a
    millisecond of every edit's set-up, and moving it waits for the GPU's queue. Callers copy it."""
    with GLOBAL_RNG_LOCK, torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        head = SegmentationHead(feature_dim, hidden_dim, width, init_bias)
    return head.to(device)


def logit_colour_map(source: Float[Tensor, "N 3"], target: Float[Tensor, "N 3"], seed: int = 0,
                     max_pixels: int = 1 << 16, eps: float = 0.02, ridge: float = 0.05,
                     ridge_floor: float = 0.01) -> Float[Tensor, "3 4"]:
    """The affine map ``[M | t]`` with ``logit(target) ~ M logit(source) + t``: least squares over at
    most ``max_pixels`` pixels drawn with ``seed``, colours clamped to [eps, 1 - eps] before the
    logit. M is pulled towards the identity by a ridge of ``ridge`` x the source's mean logit
    variance + ``ridge_floor``: the directions in which the pixels hardly vary (a patch of one
    colour) leave M near the identity and the shift to t, instead of fitting their noise."""
    n = source.shape[0]
    if n > max_pixels:
        pick = _pixel_subset(n, max_pixels, seed).to(source.device)
        source, target = source[pick], target[pick]
    x = torch.logit(source.double().clamp(eps, 1.0 - eps))
    y = torch.logit(target.double().clamp(eps, 1.0 - eps))
    xm, ym = x.mean(0), y.mean(0)
    xc, yc = x - xm, y - ym
    cxx, cxy = xc.T @ xc / x.shape[0], xc.T @ yc / x.shape[0]
    lam = ridge * float(torch.diagonal(cxx).mean()) + ridge_floor
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    Mt = torch.linalg.solve(cxx + lam * eye, cxy + lam * eye)  # M^T: y ~ x M^T
    t = ym - xm @ Mt
    return torch.cat([Mt.T, t[:, None]], 1).float()  # [3, 4]


def _record(step: Callable[[], Tensor], stream: torch.cuda.Stream, pool: Optional[tuple] = None
            ) -> tuple[torch.cuda.CUDAGraph, Tensor]:
    """``step`` recorded as a CUDA graph on ``stream`` (sharing ``pool``); returns the graph and the
    loss tensor it writes. ``torch.cuda.graph`` would also wait for the GPU and empty the allocator's
    caches first, which cost every fresh edit milliseconds and sent the next edit's allocations back
    to the driver; the eager step run before on ``stream`` has already warmed its libraries up."""
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.stream(stream):
        graph.capture_begin(pool=pool)
        try:
            loss = step()
        finally:
            graph.capture_end()
    return graph, loss


class EditEngine:
    """Fits one edit of ``scene`` from ``edited`` [H,W,3] (float, [0,1]) seen by ``camera`` (one
    view). The stack's current edits and specular strength are the starting point; see the
    module docstring. Usage: ``edit, timing = EditEngine(...).fit()``.

    ``changed`` [H,W] (bool): the pixels the edit changed, when the caller knows them (a pick's
    selection); they are then not detected from ``original`` or the render. ``edited=None`` sets up
    the view only (its contributions, features and render, :attr:`current`): :meth:`retarget` then
    gives the target, and again for every new target of the same view (a live drag)."""

    def __init__(
        self,
        scene: FrozenScene,
        camera: Cameras,
        edited: Optional[Float[Tensor, "H W 3"]],
        stack: Optional[EditStack] = None,
        cfg: Optional[EditConfig] = None,
        source: Optional[EditSource] = None,
        original: Optional[Float[Tensor, "H W 3"]] = None,
        changed: Optional[Tensor] = None,
    ) -> None:
        self.scene = scene
        self.cfg = cfg or EditConfig()
        self.stack = stack
        if len(camera) != 1:
            raise ValueError(f"EditEngine: one camera expected, got {len(camera)}")
        W, H = int(camera.widths[0]), int(camera.heights[0])
        if edited is not None:
            self._check_images(edited, original, changed, W, H)
        self.cfg.check()
        self.camera = camera
        self.source = source or EditSource("", camera.Ks[0], camera.viewmats[0], W, H, "")
        self.changed_fraction = 1.0
        self.mode = "whole image"  # what the loss fits (set by _set_target)
        self.fingerprint = stack.fingerprint if stack is not None else scene.fingerprint()
        self.batches: list[PixelBatch] = []
        self._changed: Optional[Tensor] = None
        self._target: Optional[Tensor] = None  # the last target image [H,W,3]
        dev = scene.device
        _sync(dev)
        t0 = time.perf_counter()
        self._setup_view()
        if edited is not None:
            self._set_target(edited.to(dev, torch.float32),
                             None if original is None else original.to(dev, torch.float32),
                             None if changed is None else changed.to(dev), warm=False)
        _sync(dev)
        self.setup_s = time.perf_counter() - t0

    @staticmethod
    def _check_images(edited: Tensor, original: Optional[Tensor], changed: Optional[Tensor], W: int, H: int) -> None:
        if edited.ndim != 3 or edited.shape[-1] != 3:
            raise InputError(f"the edited image must be H x W x 3, got shape {tuple(edited.shape)}")
        if tuple(edited.shape[:2]) != (H, W):
            raise InputError(f"the edited image is {edited.shape[1]}x{edited.shape[0]} but the camera renders "
                             f"{W}x{H}")
        if original is not None and tuple(original.shape) != tuple(edited.shape):
            raise InputError(f"the original image is {tuple(original.shape)}, the edited one {tuple(edited.shape)}")
        if changed is not None and (tuple(changed.shape) != (H, W) or changed.dtype != torch.bool):
            raise ValueError(f"EditEngine: changed must be a bool [{H}, {W}] mask, got {changed.dtype} "
                             f"{tuple(changed.shape)}")

    # ------------------------------------------------------------------ setup
    @torch.no_grad()
    def _setup_view(self) -> None:
        """The view's contributions, the visible Gaussians' features and colours, and its render."""
        sc = self.scene
        dev = sc.device
        cams = self.camera.to(dev, torch.float32)
        contrib = sc.contributions(cams, Request.whole_images(cams))
        if contrib.pair_gaussian.numel() == 0:
            raise InputError("the edit's camera sees none of the scene")
        self.contrib = contrib
        g = contrib.pair_gaussian.to(dev)
        self.gaussians = g
        fld = sc.field
        means = sc.means[g].float()
        self.feats, h1, h2 = sc.gaussian_features(g)
        self.h_diff = h2
        c_d = fld.diffuse(h2).float()
        self.c_d_base = c_d
        self.c_d = self.stack.diffuse(self.feats, self.h_diff, c_d) if self.stack is not None else c_d
        dirs = view_directions(means, cams.camera_centers()[0].to(means).expand_as(means))
        self.c_s = fld.specular(self.feats, dirs, h1, h2).float()
        self.k = self.stack.specular_strength if self.stack is not None else 1.0
        if sc.file_colours is not None:  # the Gaussians' own colours under the field's change
            offset, c_s = sc.file_colours.for_edit(g, dirs, c_d, self.k)
            self.c_d, self.c_s = self.c_d + offset.float(), c_s.float()
        self.background = sc.background.to(dev, torch.float32).reshape(3)
        # the view's render through the stack [H,W,3]: what unchanged pixels keep
        self.current = composite(torch.sigmoid(self.c_d + self.k * self.c_s), contrib, self.background)[0]
        self.seg = copy.deepcopy(_fresh_segmentation(self.feats.shape[1], self.h_diff.shape[1], self.cfg.seg_width,
                                                     self.cfg.seg_init_bias, self.cfg.seed, torch.device(dev)))
        self.seg_input = self.seg.inputs(self.feats, self.h_diff)
        head = fld.diffuse_head
        self.weight = head.weight.detach().float().clone().requires_grad_(True)
        self.bias = head.bias.detach().float().clone().requires_grad_(True)
        self.alpha_fixed: Optional[Tensor] = None
        self.opt: Optional[EditAdam] = None
        self._graphs: Optional[list] = None  # the recorded steps (_fit_graphed)
        self._heads: Optional[FusedHeads] = None  # the written-out heads (_set_heads), else autograd
        self.colour_map: Optional[Tensor] = None
        self.map_explained: Optional[float] = None  # changed_target="map": share of changed pixels it explains
        self.recipe = self.cfg.recipe

    def _changed_pixels(self, edited: Tensor, original: Optional[Tensor]
                        ) -> tuple[Optional[Tensor], str, Optional[int]]:
        """(changed [H,W,1] or None for a whole-image fit, what they were found against, how many
        pixels are changed, or None). The counts are read from the GPU once."""
        cfg, current = self.cfg, self.current

        def off(ref: Tensor) -> Tensor:
            return (edited - ref).abs().amax(-1, keepdim=True) > cfg.unchanged_tol

        off_render = off(current)
        P = off_render.numel()
        if original is not None:
            off_orig = off(original)
            n_orig, n_render = torch.stack([off_orig.sum(), off_render.sum()]).tolist()
            if n_orig <= n_render:
                return off_orig, "original", n_orig
            return off_render, "current render", n_render  # e.g. a render edited for a training view
        n_render = int(off_render.sum())
        if 1.0 - n_render / P >= cfg.render_match_min:
            return off_render, "current render", n_render
        return None, "current render", None

    @torch.no_grad()
    def _set_target(self, edited: Tensor, original: Optional[Tensor], given: Optional[Tensor], warm: bool,
                    seg_steps: Optional[int] = None) -> None:
        """The loss's target from ``edited`` (see the module docstring), the pixel batches, and the
        heads' start: fresh, or (``warm``) from the current fit (:meth:`retarget`)."""
        cfg, current = self.cfg, self.current
        changed, ref = (given[..., None], "selection") if given is not None else (None, "")
        n_changed = None  # how many pixels changed: counted once (reading it waits for the GPU)
        if changed is not None:
            n_changed = int(changed.sum())
        elif not cfg.whole_image:
            changed, ref, n_changed = self._changed_pixels(edited, original)
        self.mode = "whole image"
        self.changed_fraction = 1.0
        self.map_explained = None
        if changed is not None:  # untouched pixels: the current render is their target
            if n_changed == 0:
                raise InputError("the selection is empty: nothing to edit" if ref == "selection" else
                                 f"the edited image does not differ from the {ref}: nothing to edit")
            self.mode = {"original": "changed pixels (original given" + {
                "change": ", render + change)", "transfer": ", render + logit change)",
                "affine": ", edited + its slope x (render - photo))",
                "map": ", render + colour map of the change" + (
                    ", else render + change)" if cfg.map_fallback == "change" else ")")}.get(
                    cfg.changed_target, ", edited image)"),
                "selection": "changed pixels (a selection)"}.get(ref, "changed pixels (an edited render)")
            if ref == "original":
                edited, self.map_explained = changed_pixels_target(cfg, current, edited, original, changed[..., 0])
            edited = torch.where(changed, edited, current)
            self.changed_fraction = n_changed / changed.numel()
        flat = None if changed is None else changed.reshape(-1)
        kind = resolve_composite(cfg.batch_composite, edited.device)
        same = warm and self.batches and self.batches[0].composite == kind and (
            flat is None) == (self._changed is None) and (flat is None or torch.equal(flat, self._changed))
        previous = self._target if same else None  # the last target of the same pixels (a live drag)
        if same:  # the same pixel sets and weights: only the targets move (in place: recorded steps read them)
            for b in self.batches:
                b.target.copy_(edited.reshape(-1, 3) if b.pixels is None else edited.reshape(-1, 3)[b.pixels])
        else:
            near = (near_changed(changed[..., 0], cfg.near_radius).reshape(-1)
                    if changed is not None and cfg.near_share > 0.0 else None)
            share = cfg.changed_share
            if cfg.changed_share_floor and flat is not None:
                share = max(share, self.changed_fraction)
            self.batches = pixel_batches(self.contrib, edited.reshape(-1, 3), self.background, cfg.pixel_batches,
                                         cfg.seed, flat, share, kind, n_changed, near, cfg.near_share)
            for b in self.batches:
                if b.pixels is None:  # the whole image: its own copy, which a warm retarget writes into
                    b.target = b.target.clone()
            self._graphs = None
        self.recipe = cfg.recipe if changed is not None else "joint"
        staged = self.recipe == "staged"
        # the copied layer: from the colour map of the changed pixels (EditConfig.map_init), else
        # the base layer (a fresh fit) or where the last fit left it (warm), moved by the colour map
        # from the last target to this one when only the colours of the same pixels changed
        self.colour_map = None
        head = self.scene.field.diffuse_head
        if changed is not None and (staged or (cfg.map_init and self.changed_fraction >= cfg.map_init_min_share)):
            self.colour_map = logit_colour_map(current.reshape(-1, 3)[flat], edited.reshape(-1, 3)[flat], cfg.seed)
            # (fitted on the current render, earlier edits and specular included, but applied to
            # the base layer: with a stack, c_d' starts at M c_d_base + t; only a starting point)
            self._set_layer_mapped(self.colour_map, head.weight.detach().float(), head.bias.detach().float())
        elif not warm:
            self.weight.copy_(head.weight.detach().float())
            self.bias.copy_(head.bias.detach().float())
        elif previous is not None and flat is not None:
            self._set_layer_mapped(logit_colour_map(previous.reshape(-1, 3)[flat], edited.reshape(-1, 3)[flat],
                                                    cfg.seed), self.weight, self.bias)
        if staged and not (same and self.alpha_fixed is not None):
            self._fit_segmentation(flat, warm=warm and self.alpha_fixed is not None,
                                   steps=cfg.seg_steps if seg_steps is None else seg_steps)
        elif not staged and self.alpha_fixed is not None:  # back to the joint recipe: alpha trains again
            self.alpha_fixed = None
            self._graphs = None
            for p in self.seg.parameters():
                p.requires_grad_(True)
        self._changed = flat
        self._target = edited
        self._set_heads()
        trainable = [self.weight, self.bias] + ([] if staged else list(self.seg.parameters()))
        seg_scale = float(cfg.seg_rate_scale) * (float(cfg.map_seg_rate_scale) if self.colour_map is not None else 1.0)
        if (flat is not None and not cfg.changed_share_floor
                and cfg.changed_share < self.changed_fraction < 1.0):  # each unchanged pixel outweighs a changed one
            seg_scale *= float(cfg.large_edit_seg_rate_scale)
        scales = [1.0, 1.0] + [seg_scale] * (len(trainable) - 2)
        if (self.opt is not None and [id(p) for p in self.opt.params] == [id(p) for p in trainable]
                and self.opt.scales == scales):
            self.opt.restart()  # the same tensors, which recorded steps read and write
        else:
            hold, decay = 0, None
            if cfg.lr_schedule == "cosine":
                # the cosine's first step is still at lr: leave it two, so that the last step's rate is lower
                hold = min(int(cfg.lr_hold * cfg.steps), max(cfg.steps - 2, 0))
                decay = max(cfg.steps - hold, 1)
            self.opt = EditAdam(trainable, lr=cfg.lr, decay_steps=decay, hold_steps=hold, scales=scales)
            self._graphs = None

    def _set_heads(self) -> None:
        """The written-out heads (EditConfig.fused_heads) where they run: the joint recipe's step on the
        fused kind's pixel sets on a GPU; otherwise None (autograd). A change drops the recorded steps."""
        sets = self.batches[0].sets if self.batches else None
        use = (self.cfg.fused_heads and self.alpha_fixed is None and sets is not None
               and FusedHeads.runs_on(self.seg, self.h_diff.device))
        if use == (self._heads is not None):
            return
        inputs = HeadsInputs(self.seg_input, self.feats.shape[1], self.c_d, self.c_s, self.k)
        self._heads = FusedHeads(self.seg, self.weight, self.bias, inputs) if use else None
        self._graphs = None

    def _set_layer_mapped(self, colour_map: Tensor, weight: Tensor, bias: Tensor) -> None:
        """The copied layer set to ``weight``, ``bias`` followed by the logit colour map ``[M | t]``
        (in place: recorded steps read the layer)."""
        M, t = colour_map[:, :3], colour_map[:, 3]
        new_weight, new_bias = M @ weight, M @ bias + t  # before writing: weight may be the layer itself
        self.weight.copy_(new_weight)
        self.bias.copy_(new_bias)

    def retarget(self, edited: Float[Tensor, "H W 3"], changed: Optional[Tensor] = None,
                 original: Optional[Float[Tensor, "H W 3"]] = None, seg_steps: Optional[int] = None) -> None:
        """A new target for the same view, warm-started from the current fit (the live drag of a pick):
        the view's contributions and features are kept; the pixel batches too when the changed
        pixels are the same, and so is a staged segmentation, which otherwise trains on from where it
        is (``seg_steps``: how long; default the config's); the layer starts from the new target's
        colour map where a fresh fit would (staged, or a large edit), else where the last fit left
        it, moved by the colour map from the last target to this one when the changed pixels are the
        same (a new colour for the same selection); Adam starts afresh. :meth:`fit` then runs the steps."""
        W, H = int(self.camera.widths[0]), int(self.camera.heights[0])
        self._check_images(edited, original, changed, W, H)
        dev = self.scene.device
        _sync(dev)
        t0 = time.perf_counter()
        self._set_target(edited.to(dev, torch.float32), None if original is None else original.to(dev, torch.float32),
                         None if changed is None else changed.to(dev), warm=True, seg_steps=seg_steps)
        _sync(dev)
        self.setup_s = time.perf_counter() - t0

    def _fit_segmentation(self, changed: Tensor, warm: bool = False, steps: Optional[int] = None) -> None:
        """The ``staged`` recipe's first stage (EditConfig.recipe): the segmentation head trained as
        a classifier of the view's Gaussians, then its alpha fixed for the layer's steps; ``warm``:
        on from the head's current state (:meth:`retarget`) instead of from its fresh start."""
        cfg, c = self.cfg, self.contrib
        dev = self.h_diff.device
        U = self.gaussians.numel()
        pair, w = c.pair.to(dev).long(), c.weight.detach().to(dev).float()
        mass = torch.zeros(U, device=dev).index_add_(0, pair, w)
        on_changed = torch.zeros(U, device=dev).index_add_(0, pair, w * changed[c.pixel.to(dev).long()].float())
        share = on_changed / mass.clamp_min(1e-12)
        trust = mass * (2.0 * share - 1.0).abs()
        label = share > 0.5
        pos_w, neg_w = trust * label, trust * ~label
        for p in self.seg.parameters():
            p.requires_grad_(False)
        if float(pos_w.sum()) <= 0.0 or float(neg_w.sum()) <= 0.0:  # one class: a constant alpha
            torch.nn.init.zeros_(self.seg.l2.weight)
            torch.nn.init.constant_(self.seg.l2.bias, 8.0 if float(pos_w.sum()) > 0.0 else -8.0)
            self._set_alpha_fixed(torch.sigmoid(self.seg.logits_of(self.seg_input)))
            return
        half = cfg.seg_samples // 2
        n_prior = int(round(half * cfg.seg_prior_share))
        g = torch.Generator(device=dev).manual_seed(cfg.seed)
        idx = torch.cat([torch.multinomial(pos_w, half, replacement=True, generator=g),
                         torch.multinomial(neg_w, half - n_prior, replacement=True, generator=g)])
        x, y = self.seg_input[idx], label[idx].float()[:, None]
        if n_prior > 0:  # unlabelled Gaussians of the whole scene, as weak negatives
            anywhere = torch.randint(0, self.scene.means.shape[0], (n_prior,), device=dev, generator=g)
            f, _, h2 = self.scene.gaussian_features(anywhere)
            x = torch.cat([x, self.seg.inputs(f, h2)])
            y = torch.cat([y, torch.zeros(n_prior, 1, device=dev)])
        if not warm:
            torch.nn.init.constant_(self.seg.l2.bias, 0.0)
        params = list(self.seg.parameters())
        for p in params:
            p.requires_grad_(True)
        opt = EditAdam(params, lr=cfg.seg_lr)
        with torch.enable_grad():
            for _ in range(cfg.seg_steps if steps is None else steps):
                opt.zero_grad()
                torch.nn.functional.binary_cross_entropy_with_logits(self.seg.logits_of(x), y).backward()
                opt.step()
        for p in params:
            p.requires_grad_(False)
        self._set_alpha_fixed(torch.sigmoid(self.seg.logits_of(self.seg_input)))

    def _set_alpha_fixed(self, alpha: Tensor) -> None:
        """The staged recipe's fixed alpha, written in place when there is one (recorded steps read it)."""
        if self.alpha_fixed is None:
            self.alpha_fixed = alpha
            self._graphs = None
        else:
            self.alpha_fixed.copy_(alpha)

    # ------------------------------------------------------------------ steps
    def colours(self) -> tuple[Tensor, Tensor]:
        """(C' [U,3], alpha [U,1]) of the view's Gaussians under the current heads."""
        alpha = self.alpha_fixed if self.alpha_fixed is not None else torch.sigmoid(self.seg.logits_of(self.seg_input))
        c_dp = torch.nn.functional.linear(self.h_diff, self.weight, self.bias)
        c_dd = alpha * c_dp + (1.0 - alpha) * self.c_d
        return torch.sigmoid(c_dd + self.k * self.c_s), alpha

    def step(self, i: int) -> Tensor:
        """Step ``i`` of a fit: one Adam step on pixel set ``i % len(self.batches)`` (the ``fused`` kind
        takes the set its device counter names, which :meth:`fit` keeps equal to it)."""
        if self._heads is not None:  # the fused kind's sets and the written-out heads
            loss = self._heads.step(self.batches[0].sets)
            self.opt.step()
            return loss
        self.opt.zero_grad()
        C, _ = self.colours()
        loss = self.batches[i % len(self.batches)].loss(C)
        loss.backward()
        self.opt.step()
        return loss.detach()

    def fit(self, steps: Optional[int] = None, progress: Optional[Callable[[int, int], None]] = None
            ) -> tuple[Edit, EditTiming]:
        """Run the steps; returns the edit and its timing. ``progress(done, total)`` is called
        every 10 steps (it never forces a GPU sync)."""
        n = self.cfg.steps if steps is None else int(steps)
        dev = self.scene.device
        _sync(dev)
        t0 = time.perf_counter()
        loss = torch.zeros((), device=dev)
        sets = self.batches[0].sets
        if sets is not None:  # the fused kind picks its set on the device: step 0 takes the first
            sets.restart()
        with torch.enable_grad():  # callers may hold a no_grad context (viewer threads, scripts)
            done = 0
            if self.cfg.cuda_graphs and dev.type == "cuda" and (n > 2 * len(self.batches) or (self._graphs and n > 0)):
                done, loss = self._fit_graphed(n, progress)
            for i in range(done, n):
                loss = self.step(i)
                if progress is not None and ((i + 1) % 10 == 0 or i + 1 == n):
                    progress(i + 1, n)
        _sync(dev)
        steps_s = time.perf_counter() - t0
        timing = EditTiming(self.setup_s, steps_s, n, float(loss))
        return self.edit(timing), timing

    @torch.no_grad()
    def fit_loss(self) -> float:
        """The loss the steps minimise, on every pixel set at once under the current heads (each set's
        loss, averaged): a figure a fit knows about itself, steadier than its last step's, which
        saw one set."""
        C, _ = self.colours()
        return float(torch.stack([b.reference_loss(C) for b in self.batches]).mean())

    def _fit_graphed(self, n: int, progress: Optional[Callable[[int, int], None]]) -> tuple[int, Tensor]:
        """Up to ``n`` steps as replays of recorded CUDA graphs, in the eager order: one graph per
        pixel set, or one for all when the sets are chosen on the device (the ``fused`` kind).
        The graphs are recorded at the first such fit, after one eager step on a side stream (it
        creates Adam's state and warms the libraries up), and replayed by later fits while the
        tensors they read stay the same (a warm :meth:`retarget` writes its targets, alpha and
        Adam's state in place; anything else drops them). Returns (steps done, last loss): where a
        graph cannot be recorded, only the first step is done and the caller runs the rest eagerly."""
        ng = 1 if self.batches[0].sets is not None else len(self.batches)
        start = 0
        if not self._graphs:
            side = torch.cuda.Stream(self.scene.device)
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                loss = self.step(0)
            torch.cuda.current_stream().wait_stream(side)
            graphs: list = []
            losses: list[Tensor] = []
            try:
                for b in range(ng):
                    g, loss_b = _record(functools.partial(self.step, b), side, graphs[0].pool() if graphs else None)
                    graphs.append(g)
                    losses.append(loss_b)
            except RuntimeError as e:  # a kernel that cannot be recorded (a library's host sync)
                warnings.warn(f"edit steps run without CUDA graphs: {str(e).splitlines()[0]}")
                self.cfg.cuda_graphs = False
                return 1, loss
            self._graphs, start = [graphs, losses], 1
        graphs, losses = self._graphs
        for i in range(start, n):
            graphs[i % ng].replay()
            if progress is not None and ((i + 1) % 10 == 0 or i + 1 == n):
                progress(i + 1, n)
        return n, losses[(n - 1) % ng].clone()

    def edit(self, timing: Optional[EditTiming] = None) -> Edit:
        """The current heads as an :class:`Edit` (copies)."""
        extra = {} if self.map_explained is None else {"map_explained": self.map_explained}
        times = ({"steps": timing.steps, "setup_s": timing.setup_s, "steps_s": timing.steps_s,
                  "loss": timing.final_loss} if timing is not None else {})
        info = new_edit_info(k=self.k, changed_fraction=self.changed_fraction, fit=self.mode, recipe=self.recipe,
                             start="colour map" if self.colour_map is not None else "unedited layer", **extra, **times)
        return Edit(self.weight.detach().clone(), self.bias.detach().clone(), copy.deepcopy(self.seg).eval(),
                    self.source, self.fingerprint, info)

    @torch.no_grad()
    def preview(self) -> dict[str, Tensor]:
        """The edited view under the current heads: ``rgb`` [H,W,3] and ``alpha`` [H,W,1]."""
        C, alpha = self.colours()
        bg = self.scene.background.to(C)
        return {"rgb": composite(C, self.contrib, bg)[0], "alpha": composite(alpha, self.contrib)[0]}


__all__ = ["EditConfig", "EditEngine", "EditTiming", "change_slope", "changed_pixels_target", "logit_colour_map"]
