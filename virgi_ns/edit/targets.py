"""What an edit's loss fits: the changed pixels, their target, and where the copied layer starts.

- :func:`find_target`: from the edited image (and the original the user started from, or a
  selection) the :class:`Target`: the image the loss fits (the edited pixels where the user changed
  something, the current render elsewhere), which pixels changed, and what the fit is (``mode``).
- :func:`changed_pixels_target`: the changed pixels' target for an edited photo
  (:attr:`EditConfig.changed_target`), with :func:`change_slope`, the slope of the user's change.
- :func:`unchanged_pixel_weights`: how the unchanged pixels split their share of the loss
  (:attr:`EditConfig.unchanged_weights`).
- :func:`logit_colour_map`: the affine map in logit space that takes one set of colours to another,
  the copied layer's start for a large edit (:data:`MAP_START_SHARE`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.edit.config import EditConfig
from virgi_ns.errors import InputError

RENDER_MATCH_MIN = 0.5
"""Without an original: when at least this share of the edited image's pixels equal the current render
(within :attr:`EditConfig.unchanged_tol`), the image is an edited render and only the other pixels are
fitted to it (as with an original); otherwise every pixel is."""

MAP_START_SHARE = 0.2
"""An edit that changes at least this share of the view starts the copied layer from the colour map of
the changed pixels (:func:`logit_colour_map`: ``W' = M W``, ``b' = M b + t``), which a large recolour of
many colours does not reach from ``W`` in its steps; a smaller edit starts from ``W``, so its
segmentation stays on the painted pixels. The ``staged`` recipe always starts from the map."""

SLOPE_RIDGE = (1.0 / 255.0) ** 2
"""Ridge of :func:`change_slope`: along a direction of colour in which the changed pixels vary by less
than one 8-bit level the photo says little of how the change varies, so the slope there shrinks
towards 0 (no correction: the render plus the pixel's own change)."""

SLOPE_MIN_PIXELS = 64
"""Fewest changed pixels :func:`change_slope` fits a slope to: the fit has 12 parameters, and with
fewer than about five pixels each a chance correlation of a few dabs of paint fits as well as a
colour rule; a smaller edit gets no slope (the render plus each pixel's own change)."""


@dataclass
class Target:
    """What the loss fits. ``image`` [H,W,3]: the target (the edited pixels' targets where ``changed``,
    the current render elsewhere; the edited image for a whole-image fit); ``changed`` [H,W,1] bool or
    None (a whole-image fit); ``count``: how many pixels changed (None for a whole-image fit);
    ``mode``: what the fit is, in words (an edit's ``info["fit"]``)."""

    image: Tensor
    changed: Optional[Tensor]
    count: Optional[int]
    mode: str

    @property
    def fraction(self) -> float:
        """The share of the view's pixels the edit changed (1 for a whole-image fit)."""
        return 1.0 if self.changed is None else self.count / self.changed.numel()

    @property
    def flat(self) -> Optional[Tensor]:
        """``changed`` as [H*W] (None for a whole-image fit)."""
        return None if self.changed is None else self.changed.reshape(-1)


def find_target(cfg: EditConfig, render: Float[Tensor, "H W 3"], edited: Float[Tensor, "H W 3"],
                original: Optional[Float[Tensor, "H W 3"]] = None, selection: Optional[Tensor] = None) -> Target:
    """The :class:`Target` of ``edited`` for a view whose current render is ``render``. The changed
    pixels are ``selection`` [H,W] (bool) when given; else (unless ``cfg.whole_image``) those that
    differ by more than ``cfg.unchanged_tol`` from the image the user started from: ``original`` or
    the render, whichever the edited image matches more (with no original, the render when at least
    :data:`RENDER_MATCH_MIN` of the image matches it). Found against an original, the changed pixels
    are fitted to :func:`changed_pixels_target`. Raises :class:`InputError` when nothing changed."""
    if selection is not None:
        changed, ref, count = selection[..., None], "selection", int(selection.sum())
    elif cfg.whole_image:
        changed, ref, count = None, "", None
    else:
        changed, ref, count = _changed_pixels(cfg.unchanged_tol, render, edited, original)
    if changed is None:
        return Target(edited, None, None, "whole image")
    if count == 0:
        raise InputError("the selection is empty: nothing to edit" if ref == "selection" else
                         f"the edited image does not differ from the {ref}: nothing to edit")
    if ref == "original":
        edited = changed_pixels_target(cfg, render, edited, original, changed[..., 0])
        mode = "changed pixels (original given, " + (
            "edited + its slope x (render - photo))" if cfg.changed_target == "affine" else "edited image)")
    else:
        mode = "changed pixels (a selection)" if ref == "selection" else "changed pixels (an edited render)"
    return Target(torch.where(changed, edited, render), changed, count, mode)


def _changed_pixels(tol: float, render: Tensor, edited: Tensor, original: Optional[Tensor]
                    ) -> tuple[Optional[Tensor], str, Optional[int]]:
    """(changed [H,W,1] or None for a whole-image fit, what they were found against, how many pixels
    are changed, or None). The counts are read from the GPU once."""

    def off(ref: Tensor) -> Tensor:
        return (edited - ref).abs().amax(-1, keepdim=True) > tol

    off_render = off(render)
    if original is not None:
        off_orig = off(original)
        n_orig, n_render = torch.stack([off_orig.sum(), off_render.sum()]).tolist()
        if n_orig <= n_render:
            return off_orig, "original", n_orig
        return off_render, "current render", n_render  # e.g. a render edited for a training view
    n_render = int(off_render.sum())
    if 1.0 - n_render / off_render.numel() >= RENDER_MATCH_MIN:
        return off_render, "current render", n_render
    return None, "current render", None


def change_slope(original: Float[Tensor, "N 3"], edited: Float[Tensor, "N 3"]) -> Float[Tensor, "3 3"]:
    """``J``, the slope of the best affine fit ``edited ~ J original + b`` over these pixels (least
    squares, the slope's excess over identity ridged by :data:`SLOPE_RIDGE`): how the user's change
    moves with the colour it starts from. The excess is scaled by the share of the change's variance
    the fit explains, adjusted for the fit's 4 parameters per channel, so a change that is no
    function of colour (strokes of paint) gets no slope from colours that only happen to correlate
    with it; under :data:`SLOPE_MIN_PIXELS` pixels, identity."""
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
                          original: Float[Tensor, "H W 3"], changed: Tensor) -> Float[Tensor, "H W 3"]:
    """What the pixels a user changed in a photo (``original`` -> ``edited``; ``changed`` [H,W] bool)
    are fitted to, by ``cfg.changed_target``, as an image [H,W,3] read on the changed pixels only:
    ``affine``, ``edited + J (render - original)`` with ``J`` = :func:`change_slope` over the changed
    pixels; ``edited``, the edited image."""
    if cfg.changed_target == "affine":
        changed = changed.reshape(render.shape[:-1])
        slope = change_slope(original[changed], edited[changed])
        return (edited + (render - original) @ slope.T).clamp(0.0, 1.0)
    return edited


KEEP_COLOUR_BINS = 8
"""Levels per channel of the colour bins :func:`unchanged_pixel_weights` keys pixels by."""

KEEP_COLOUR_CHANGED_MAX = 0.1
"""A colour bin counts as shown only unchanged when at most this share of its pixels changed (a pixel that
a part's Gaussian dominates but the rule caught through a blend with its neighbour does not make the
part's colour a changed one)."""


def heaviest_gaussian(pixel: Tensor, gaussian: Tensor, weight: Tensor, P: int,
                      offsets: Optional[Tensor] = None) -> Tensor:
    """[P] each pixel's Gaussian of largest weight (among equals the largest index; -1 where none), from
    the entries ``pixel``, ``gaussian``, ``weight`` [E] in any order. With ``offsets`` [P+1] (the entries
    grouped by pixel) on a GPU with the extension: one pass per pixel (:func:`virgi_ns.raster.cuda.heaviest_pair`),
    no wait; else scatters and a mask, which wait for the device."""
    dev = weight.device
    if offsets is not None and weight.is_cuda:
        from virgi_ns.raster import cuda

        if cuda.available()[0]:
            return cuda.heaviest_pair(gaussian.int().contiguous(), weight.detach().float().contiguous(),
                                      offsets.long().contiguous())
    pixel, gaussian, weight = pixel.to(dev).long(), gaussian.to(dev).long(), weight.detach().float()
    best = torch.zeros(P, device=dev).scatter_reduce_(0, pixel, weight, "amax")
    top = weight >= best[pixel]
    return torch.full((P,), -1, dtype=torch.long, device=dev).scatter_reduce_(0, pixel[top], gaussian[top], "amax")


def unchanged_pixel_weights(pixel: Tensor, gaussian: Tensor, weight: Tensor, colours: Float[Tensor, "U 3"],
                            changed: Tensor, offsets: Optional[Tensor] = None) -> Tensor:
    """Relative loss weights [P] of the unchanged pixels (``changed`` [P] bool; changed pixels get 0) for
    :attr:`EditConfig.unchanged_weights` ``colour``: half as if every unchanged pixel weighed the same,
    half split equally over the colour bins that the image shows only unchanged (at most
    :data:`KEEP_COLOUR_CHANGED_MAX` of their pixels changed) and within a bin equally over its pixels. A
    pixel's bin is that of the colour ``colours`` [U, 3] (in [0, 1]) of the Gaussian with the largest
    weight in it (:func:`heaviest_gaussian`), :data:`KEEP_COLOUR_BINS` levels per channel; a pixel no
    Gaussian reaches has no bin. Where no bin qualifies, every unchanged pixel weighs the same. Waits for
    the device (its masks and counts): a set-up step, never recorded.

    Args:
        pixel: [E] each contribution entry's pixel (of P = ``changed.numel()``).
        gaussian: [E] its Gaussian (a row of ``colours``).
        weight: [E] its weight.
        offsets: [P+1] each pixel's range of entries, where they are grouped by pixel."""
    P, dev = changed.numel(), changed.device
    dominant = heaviest_gaussian(pixel, gaussian, weight.to(dev), P, offsets)  # it moves the entries to weight's device
    n = KEEP_COLOUR_BINS
    q = (colours.detach().float().clamp(0.0, 1.0) * n).long().clamp_max(n - 1)
    key_of = (q[:, 0] * n + q[:, 1]) * n + q[:, 2]
    none = n**3  # the bin of pixels no Gaussian reaches
    key = torch.where(dominant >= 0, key_of[dominant.clamp_min(0)], torch.full_like(dominant, none))
    unchanged = ~changed.reshape(-1)
    n_u = torch.bincount(key[unchanged], minlength=none + 1).float()
    n_c = torch.bincount(key[~unchanged], minlength=none + 1).float()
    kept = (n_u > 0) & (n_c <= KEEP_COLOUR_CHANGED_MAX * (n_u + n_c))
    kept[none] = False
    n_kept = kept.sum()
    uniform = 1.0 / n_u.sum().clamp_min(1.0)
    extra = torch.where(kept[key], 1.0 / (n_kept.clamp_min(1) * n_u[key].clamp_min(1.0)), torch.zeros((), device=dev))
    w = torch.where(n_kept > 0, 0.5 * uniform + 0.5 * extra, uniform)
    return torch.where(unchanged, w, torch.zeros((), device=dev))


@functools.lru_cache(maxsize=4)
def _pixel_subset(n: int, k: int, seed: int) -> Tensor:
    """The first ``k`` of a permutation of ``n`` drawn on the CPU with ``seed`` (the same on every
    device). Kept for the next call: a live drag asks for the same subset at every change, and the
    permutation of a megapixel view takes tens of milliseconds."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    return torch.randperm(n, generator=g)[:k]


def logit_colour_map(source: Float[Tensor, "N 3"], target: Float[Tensor, "N 3"], seed: int = 0,
                     max_pixels: int = 1 << 16, eps: float = 0.02, ridge: float = 0.05,
                     ridge_floor: float = 0.01) -> Float[Tensor, "3 4"]:
    """The affine map ``[M | t]`` with ``logit(target) ~ M logit(source) + t``: least squares over at
    most ``max_pixels`` pixels drawn with ``seed``, colours clamped to [eps, 1 - eps] before the
    logit. M is pulled towards the identity by a ridge of ``ridge`` x the source's mean logit
    variance + ``ridge_floor``: the directions in which the pixels hardly vary (a patch of one
    colour) leave M near the identity and the shift to t, instead of fitting their noise.

    Args:
        source: [N, 3] colours in [0, 1].
        target: [N, 3] colours in [0, 1], row for row.

    Returns:
        [3, 4]: ``M`` (first three columns) and ``t``."""
    n = source.shape[0]
    if n > max_pixels:
        pick = _pixel_subset(n, max_pixels, seed).to(source.device)
        source, target = source[pick], target[pick]
    x = torch.logit(source.double().clamp(eps, 1.0 - eps))
    y = torch.logit(target.double().clamp(eps, 1.0 - eps))
    xm, ym = x.mean(0), y.mean(0)
    xc, yc = x - xm, y - ym
    cxx, cxy = xc.T @ xc / x.shape[0], xc.T @ yc / x.shape[0]
    lam = torch.diagonal(cxx).mean() * ridge + ridge_floor  # on the device: no read back
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    # positive definite (the ridge), so no error to check: the checked solve would wait for the GPU
    Mt = torch.linalg.solve_ex(cxx + lam * eye, cxy + lam * eye, check_errors=False).result  # M^T: y ~ x M^T
    t = ym - xm @ Mt
    return torch.cat([Mt.T, t[:, None]], 1).float()  # [3, 4]


__all__ = ["KEEP_COLOUR_BINS", "KEEP_COLOUR_CHANGED_MAX", "MAP_START_SHARE", "RENDER_MATCH_MIN", "SLOPE_MIN_PIXELS", "SLOPE_RIDGE", "Target", "change_slope",
           "changed_pixels_target", "find_target", "logit_colour_map", "unchanged_pixel_weights"]
