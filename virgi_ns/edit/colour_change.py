"""The user's change as a function of colour, learnt from the photo they edited.

A recolour of a photo is, almost everywhere, a function of the pixel's colour: a hue rule, a pick's
hue change, a paint bucket. :func:`fit_colour_change` estimates that function from the photo and
its edited copy (every pixel: the unchanged ones say "this colour stays"), as a kernel regression
on a regular RGB grid: each pixel's change ``edited - original`` is spread over the 8 grid points
around its colour with trilinear weights, and :meth:`ColourChange.delta` reads the weighted mean
change back at any colour with the same weights (a tent kernel about two cells wide).

The edit engine applies it to its *render* (``EditConfig.changed_target="map"``): the changed
pixels are fitted to ``render + delta(render)`` wherever the map explains the user's change of
that pixel, so the photo's detail that the model never reproduced is not fitted as part of the edit,
and a render pixel gets the change the user gave to its own colour (a blended edge of the render
gets the change of a blended colour, not that of the sharp photo pixel behind it). Where an edit is
not one function of colour (two objects of one colour changed differently, or one changed and one
not) :meth:`ColourChange.explains` says so per pixel and the engine falls back to the render plus that
pixel's own change (``EditConfig.map_fallback``).

A map may have finer levels (``fit_colour_change(..., levels=3)``: grids of 17, 33 and 65 points):
at each colour the coarsest level that has support and whose change is one change gives the change.
A rule's threshold (of hue, saturation or value) makes the change a step in colour; a coarse cell
that the step runs through mixes changed and unchanged colours (dark colours of several hues share
a cell), and a finer level's narrower kernel can hold the two apart, so more of the changed pixels
use the map. The cost: a colour just past a threshold, with few photo pixels of its own side near
it, takes its changed neighbours' change at a fine level where the coarse one refused it. Off by
default (``EditConfig.map_levels``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

GRID = 17
"""Grid points per RGB axis (cells of 1/16): fine enough that a hue rule's change varies little
across a cell, coarse enough that the colours of one photo fill the cells they touch."""
MIN_SUPPORT = 0.5
"""A colour is covered when the photo's pixels near it carry at least this much kernel weight (a
pixel of that very colour carries 1): one nearby pixel is enough, as a small object in a small
image may offer no more; elsewhere the map knows nothing and :meth:`ColourChange.delta` gives no
change."""
EXPLAIN_TOL = 0.1
"""A changed pixel is explained by the map when ``original + delta(original)`` is within this (every
channel, 0..1) of its edited colour: the grid's interpolation error on a smooth change stays a few
hundredths, while an edit that is not one function of colour leaves about half of its change or
more (the map averages the two answers)."""


_OFFSETS = torch.tensor([[dx, dy, dz] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)])  # [8,3]


SPREAD_SHARE = 0.25
"""The change near a colour is one change when its spread is at most this share of its size: pixels
of one colour changed one way and kept another (a split p / 1-p) give a spread of sqrt((1-p)/p) of
the mean change, 1 for an even split and 0.25 for 94 / 6, while a smooth recolour's own variation
over the kernel's width stays near a tenth of it (a hue rotation)."""


def _one(delta: Tensor, support: Tensor, spread: Tensor) -> Tensor:
    """Covered, and one change: the spread within :data:`SPREAD_SHARE` of the mean change's largest channel."""
    return (support >= MIN_SUPPORT) & (spread <= SPREAD_SHARE * delta.abs().amax(-1))


def _corners(colours: Float[Tensor, "N 3"], grid: int) -> tuple[Tensor, Tensor]:
    """The 8 grid points around each colour: flat indices [N,8] and trilinear weights [N,8]."""
    x = colours.clamp(0.0, 1.0) * (grid - 1)
    i0 = x.floor().clamp(0, grid - 2)
    f = (x - i0)[:, None, :]  # [N,1,3]
    d = _OFFSETS.to(colours.device)
    w = torch.where(d.bool(), f, 1.0 - f).prod(-1)  # [N,8]
    c = i0.long()[:, None, :] + d  # [N,8,3]
    return (c[..., 0] * grid + c[..., 1]) * grid + c[..., 2], w


@dataclass
class ColourChange:
    """Kernel sums on the grid: ``change`` [G^3,3] (weighted changes), ``square`` [G^3,3] (weighted
    squared changes) and ``weight`` [G^3]."""

    change: Tensor
    square: Tensor
    weight: Tensor
    grid: int = GRID
    finer: Optional["ColourChange"] = None
    """The next finer level (grid ``2 * grid - 1``), consulted where this one is not one change."""

    def support(self, colours: Float[Tensor, "N 3"]) -> Float[Tensor, "N"]:
        """Kernel weight of the photo's pixels near each colour."""
        return self.lookup(colours)[1]

    def delta(self, colours: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3"]:
        """The mean change the user made to pixels of (about) this colour; zero where uncovered."""
        return self.lookup(colours)[0]

    def lookup(self, colours: Float[Tensor, "N 3"]) -> tuple[Tensor, Tensor, Tensor]:
        """(:meth:`delta`, :meth:`support`, spread) from one lookup. The spread is the largest
        per-channel standard deviation of the changes near the colour: small where the user changed
        pixels of this colour one way, about half the change where they changed some and not others
        (a rule's threshold running through a cell of the grid, dark colours of several hues that
        share a cell)."""
        idx, w = _corners(colours.float(), self.grid)
        den = (self.weight[idx] * w).sum(1)
        covered = (den >= MIN_SUPPORT)[:, None]
        safe = den.clamp_min(1e-12)[:, None]
        mean = (self.change[idx] * w[..., None]).sum(1) / safe
        var = ((self.square[idx] * w[..., None]).sum(1) / safe - mean ** 2).clamp_min(0.0)
        zero = torch.zeros_like(mean)
        out = torch.where(covered, mean, zero), den, torch.where(covered, var, zero).amax(-1).sqrt()
        if self.finer is None:
            return out
        # where this level is not one change, a finer level that is (the finer's own choice) answers
        fine = self.finer.lookup(colours)
        take = ~_one(*out) & _one(*fine)
        return tuple(torch.where(take[:, None] if a.dim() == 2 else take, b, a) for a, b in zip(out, fine))

    def one_change(self, colours: Float[Tensor, "N 3"]) -> Float[Tensor, "N"]:
        """Per colour: covered, and the changes near it are one change (spread within
        :data:`SPREAD_SHARE` of the mean change's largest channel)."""
        return self.apply_where_one_change(colours)[1]

    def apply_where_one_change(self, colours: Float[Tensor, "N 3"],
                               tolerance: Optional[Float[Tensor, "N"]] = None) -> tuple[Tensor, Tensor]:
        """(:meth:`apply`, :meth:`one_change`) of ``colours`` from one lookup. ``tolerance`` (per
        colour): also one change where the spread is at most this, however small the change (the
        caller's error of the alternative to the map's change)."""
        delta, support, spread = self.lookup(colours)
        one = _one(delta, support, spread)
        if tolerance is not None:
            one = one | ((support >= MIN_SUPPORT) & (spread <= tolerance))
        return (colours + delta).clamp(0.0, 1.0), one

    def apply(self, colours: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3"]:
        """``colours`` changed as the user changed such colours (clamped to [0, 1])."""
        return (colours + self.delta(colours)).clamp(0.0, 1.0)

    def explains(self, original: Float[Tensor, "N 3"], edited: Float[Tensor, "N 3"],
                 tol: float = EXPLAIN_TOL) -> Float[Tensor, "N"]:
        """Per pixel: whether the map takes its original colour to its edited one within ``tol``."""
        return (self.apply(original) - edited).abs().amax(-1) <= tol


def fit_colour_change(original: Float[Tensor, "N 3"], edited: Float[Tensor, "N 3"], grid: int = GRID,
                      levels: int = 1) -> ColourChange:
    """The change ``edited - original`` as a function of the original colour (module docstring), on
    ``grid`` points per axis and ``levels - 1`` finer levels, each of twice the cells."""
    if levels < 1:
        raise ValueError(f"fit_colour_change: levels must be >= 1, got {levels}")
    original, edited = original.reshape(-1, 3).float(), edited.reshape(-1, 3).float()
    idx, w = _corners(original, grid)
    d = (edited - original)[:, None, :]
    flat = idx.reshape(-1)

    def splat(values: Tensor) -> Tensor:
        return torch.zeros(grid ** 3, values.shape[-1], device=original.device).index_add_(0, flat, values.reshape(-1, values.shape[-1]))

    finer = fit_colour_change(original, edited, 2 * grid - 1, levels - 1) if levels > 1 else None
    return ColourChange(splat(d * w[..., None]), splat(d * d * w[..., None]), splat(w[..., None])[:, 0], grid, finer)


__all__ = ["ColourChange", "EXPLAIN_TOL", "GRID", "MIN_SUPPORT", "SPREAD_SHARE", "fit_colour_change"]
