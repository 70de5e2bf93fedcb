"""The settings of one edit (:class:`EditConfig`).

Each field is a choice a user has a reason to make: how long and how fast the fit runs, which pixels
it fits and to what, the recipe, and how the steps run on a GPU. What the method fixes (the learning
rate's schedule, when the copied layer starts from the colour map, how fast the segmentation head
steps on a large edit) is stated where it is computed (:mod:`virgi_ns.edit.targets`,
:mod:`virgi_ns.edit.fitting`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

COMPOSITE_KINDS = ("auto", "csr", "fused")
"""The values of :attr:`EditConfig.batch_composite` (:mod:`virgi_ns.edit.pixels`)."""


@dataclass
class EditConfig:
    """Settings of one edit. Values no edit can run with raise ``ValueError``, at construction and when a
    field is set (the field then keeps its value): an ``EditConfig`` is always one an edit can run with."""

    steps: int = 100
    """Adam steps of a fit. The learning rate stays at ``lr`` for the first half of them, then falls
    by half a cosine to 0 at ``steps`` (counted over every :meth:`~virgi_ns.edit.engine.EditEngine.fit`
    of one target; a retarget starts it again); steps past ``steps`` move nothing."""
    lr: float = 2e-2
    """Learning rate of both heads."""
    seed: int = 0
    """Seeds the segmentation head's initialisation and the pixel sets: equal seeds, equal edits."""
    pixel_batches: int = 4
    """The view's pixels split into this many random sets, one per step (1: the whole view every
    step)."""
    batch_composite: Literal["auto", "csr", "fused"] = "auto"
    """How a step applies its pixel set's sparse matrix ``A`` (pixels x Gaussians) and ``A^T``
    (:mod:`virgi_ns.edit.pixels`): ``csr``, sparse CSR products with a precomputed transpose (the
    reference); ``fused``, one CUDA kernel for the composite and the L1 loss and one that gathers the
    gradient per Gaussian, every set in one recorded CUDA graph (the same sums in torch on a CPU);
    ``auto``: ``fused`` on a GPU with the package's CUDA extension, ``csr`` elsewhere. Both give the
    same edit up to the order of float sums."""
    unchanged_tol: float = 3.0 / 255.0
    """Pixels whose colour moved by at most this (every channel) from the image the user started from
    (the original, or the current render) are not part of the edit: their target is the current
    render. Covers an 8-bit round trip; strong JPEG compression of the edited image can exceed it
    (noise then counts as a change: save edits as PNG)."""
    changed_share: float = 0.5
    """With the changed pixels known: the share of the loss they carry (the unchanged ones carry the
    rest), whatever their numbers, so a small edit is not outvoted by the many pixels asking for no
    change."""
    unchanged_weights: Literal["count", "colour"] = "colour"
    """How the unchanged pixels split their share of the loss. ``count``: each the same. ``colour``: half of
    it as ``count``, the other half split equally over the colours that the edited image shows only
    unchanged (:func:`~virgi_ns.edit.targets.unchanged_pixel_weights`: each pixel keyed by the binned
    diffuse colour of the Gaussian weighing most in it), so a part of another colour that the image
    shows unchanged is held to its colour however few pixels it covers beside the background's. No
    effect on a whole-image fit."""
    whole_image: bool = False
    """Fit every pixel to the edited image (no original, no edited-render detection)."""
    changed_target: Literal["affine", "edited"] = "affine"
    """What the changed pixels of an edited photo (``original`` given) are fitted to. ``affine``: the
    edited pixel moved by the model's reconstruction error there as the user's change moves colours,
    ``edited + J (render - original)``, ``J`` the slope of the best affine fit of the edited colours
    to the original ones over the changed pixels (:func:`~virgi_ns.edit.targets.change_slope`): exact
    for a change affine in colour (a hue shift of 120 degrees permutes the channels), first order for
    any other; the photo's detail the model never reproduced stays out of the edit. ``edited``: the
    edited pixels themselves (the paper's). The same for an edited render; no effect with
    ``whole_image``."""
    recipe: Literal["joint", "staged"] = "joint"
    """How the two heads are fitted. ``joint`` (the paper's): both heads together on the pixel loss.
    ``staged``: the segmentation first, as a classifier of which Gaussians the edit changed (each
    visible Gaussian labelled by the share of its pixel weight on changed pixels, trusted in
    proportion to its weight and to how clear that share is, the two classes weighing the same), so a
    part of another colour inside a recoloured object keeps its colour; then the copied layer, from
    the colour map of the changed pixels, with the segmentation fixed. Needs the changed pixels (a
    whole-image fit runs ``joint``)."""
    seg_steps: int = 300
    """``staged``: Adam steps of the segmentation classifier."""
    seg_samples: int = 65536
    """``staged``: Gaussians drawn (by their label weight, half from each class) to train the
    classifier on; every step uses all of them."""
    seg_width: int = 64
    """Hidden width of the segmentation head."""
    seg_init_bias: float = -4.0
    """Initial output bias of the segmentation head: alpha starts at its sigmoid, so a fresh edit is
    close to a no-op."""
    fused_heads: bool = True
    """On a GPU, the heads' steps written out on our kernels instead of through torch, the same steps up
    to float rounding: with the ``fused`` kind and the joint recipe, the heads' forward and backward of
    :mod:`virgi_ns.edit.heads` (two cuBLAS products and two kernels); with the ``staged`` recipe, its
    classifier's gradient (:func:`~virgi_ns.edit.fitting.written_out_gradients`, two kernels)."""
    cuda_graphs: bool = True
    """On a GPU, record each pixel set's step once as a CUDA graph and replay it (the same kernels,
    without a Python and launch round trip per kernel). A fit of a few steps runs eagerly; where a
    step cannot be recorded the engine turns this off and runs eagerly."""

    def __post_init__(self) -> None:
        self.check()
        object.__setattr__(self, "_checked", True)

    def __setattr__(self, name: str, value) -> None:
        if not self.__dict__.get("_checked"):  # during construction: __post_init__ checks
            object.__setattr__(self, name, value)
            return
        before = self.__dict__.get(name)
        object.__setattr__(self, name, value)
        try:
            self.check()
        except ValueError:
            object.__setattr__(self, name, before)
            raise

    def check(self) -> None:
        """Refuse values no edit can run with."""
        if self.batch_composite not in COMPOSITE_KINDS:
            raise ValueError(f"EditConfig.batch_composite must be one of {', '.join(COMPOSITE_KINDS)}, "
                             f"got {self.batch_composite!r}")
        if self.changed_target not in ("affine", "edited"):
            raise ValueError(f"EditConfig.changed_target must be 'affine' or 'edited', got {self.changed_target!r}")
        if self.unchanged_weights not in ("count", "colour"):
            raise ValueError(f"EditConfig.unchanged_weights must be 'count' or 'colour', got {self.unchanged_weights!r}")
        if self.recipe not in ("joint", "staged"):
            raise ValueError(f"EditConfig.recipe must be 'joint' or 'staged', got {self.recipe!r}")
        if self.seg_steps < 0 or self.seg_samples < 2:
            raise ValueError(f"EditConfig: seg_steps must be >= 0 and seg_samples >= 2 "
                             f"(got {self.seg_steps}, {self.seg_samples})")
        if self.steps < 0 or self.pixel_batches < 1:
            raise ValueError(f"EditConfig: steps must be >= 0 and pixel_batches >= 1 "
                             f"(got {self.steps}, {self.pixel_batches})")
        if not 0.0 < self.changed_share < 1.0:
            raise ValueError(f"EditConfig.changed_share must be in (0, 1), got {self.changed_share}")


__all__ = ["COMPOSITE_KINDS", "EditConfig"]
