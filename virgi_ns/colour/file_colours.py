"""A splat's own SH colours as the base under edits (``base_colours="file"``).

The colour field blurs neighbouring Gaussians' colours a little: a hash grid gives nearby
Gaussians nearby features. A splat imported from a file already holds each Gaussian's exact
colour, its spherical harmonics, so what no edit touches should keep it, and the colour field
should serve only the edit (its segmentation and its change of colour).

For Gaussian ``g`` seen along the unit direction ``d`` (camera centre to mean, in the frame the
coefficients were fitted in) the file's colour is, as 3DGS renderers evaluate it::

    C_g(d) = max(SH(d) . sh_g + 0.5, 0)

Edits work on the colour model's logits (:mod:`virgi_ns.edit.engine`): a diffuse logit ``c_d``,
mixed by each edit's segmentation with its copied layer, and a view-dependent logit ``c_s``
scaled by the specular strength ``k``. The file's colours give them

    b_g    = logit(clamp(C_g^0, eps, 1 - eps))               the degree-0 colour, view independent
    s_g(d) = logit(clamp(C_g(d), eps, 1 - eps)) - b_g        the file's own view-dependent part

so that ``sigmoid(b + s)`` is the file's colour within ``(eps, 1 - eps)``. The edits change the
field's diffuse logit ``c_d`` into ``c_d''`` (each mixes its copied layer in by its segmentation);
that change is applied to the file's logit, ``e_g = b_g + (c_d''_g - c_d_g)``, and the shown colour
is the file's colour plus the change it makes::

    C'_g(d) = C_g(d) + sigmoid(e_g + k s_g(d)) - sigmoid(b_g + s_g(d))

(Mixing the copied layer with ``b`` directly would leak ``alpha (c_d - b)``, the field's own error,
onto every Gaussian, since an edit's segmentation is never exactly 0.) The edit engine fits
``sigmoid(c_d'' + k c_s)``; it takes ``c_d`` from the field and
``c_s = s + (b - c_d) / k`` (:meth:`FileColours.for_edit`), which is the same colour.

A Gaussian is *touched* when ``k != 1`` (for a view-dependent file) or when the edits move its
diffuse colour ``sigmoid(e_g)`` away from ``sigmoid(b_g)`` by more than ``tolerance`` in some
channel (half an 8-bit step by default: an edit's segmentation is a sigmoid, never exactly 0);
every other Gaussian shows ``C_g(d)`` exactly, and its exported coefficients are the file's.
Nothing here knows of rendering or of nerfstudio.
"""

from __future__ import annotations

from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.gaussians import SH_C0

EPS = 1e-3
"""Colours are clamped to ``(EPS, 1 - EPS)`` before their logit (``|logit| <= 6.9``)."""
TOLERANCE = 0.5 / 255.0
"""Largest change of a Gaussian's diffuse colour that leaves it untouched (half an 8-bit step)."""

__all__ = ["EPS", "TOLERANCE", "FileColours"]


def _basis(degree: int, dirs: Tensor) -> Tensor:
    from virgi_ns.colour.sh import sh_basis  # (imports nerfstudio's SH components on first use)

    return sh_basis(degree, dirs)


class FileColours:
    """The Gaussians' own SH colours (``features_dc`` [N,3] and ``features_rest`` [N,K-1,3], the
    3DGS convention) and the rotation ``rotation`` [3,3] taking directions of the rendering frame
    to the coefficients' frame as row vectors (``d_file = d @ rotation``; None: the same frame)."""

    def __init__(self, features_dc: Float[Tensor, "N 3"], features_rest: Float[Tensor, "N R 3"],
                 rotation: Optional[Tensor] = None, tolerance: float = TOLERANCE) -> None:
        self.dc = features_dc.detach()
        rest = features_rest.detach()
        k = 1 + rest.shape[1]
        self.degree = int(round(k**0.5)) - 1
        if (self.degree + 1) ** 2 != k:
            raise ValueError(f"FileColours: {k} SH coefficients per channel is not (degree + 1)^2")
        self.rest = rest
        # a file whose higher bands are all zero is view independent: its colour is computed once
        self.view_dependent = bool(rest.numel() > 0 and bool((rest != 0).any()))
        self.rotation = None if rotation is None else torch.as_tensor(rotation).detach().to(self.dc)
        self.tolerance = float(tolerance)
        self._dc_colour: Optional[Tensor] = None
        self._base: Optional[Tensor] = None

    @property
    def device(self) -> torch.device:
        return self.dc.device

    def to(self, device) -> "FileColours":
        if torch.device(device) == self.device:
            return self
        return FileColours(self.dc.to(device), self.rest.to(device),
                           None if self.rotation is None else self.rotation.to(device), self.tolerance)

    # ------------------------------------------------------------------ colours
    def dc_colours(self, idx: Optional[Tensor] = None) -> Float[Tensor, "M 3"]:
        """``max(C0 f_dc + 0.5, 0)``: the degree-0 colour (all Gaussians when ``idx`` is None)."""
        if self._dc_colour is None:
            self._dc_colour = (SH_C0 * self.dc + 0.5).clamp_min(0.0)
        return self._dc_colour if idx is None else self._dc_colour[idx]

    def colours(self, idx: Optional[Tensor], dirs: Optional[Float[Tensor, "M 3"]]) -> Float[Tensor, "M 3"]:
        """``C_g(d)`` of Gaussians ``idx`` (None: all) along ``dirs`` (camera to Gaussian, any
        length, in the rendering frame; unused for a view-independent file)."""
        if not self.view_dependent or dirs is None:
            return self.dc_colours(idx)
        d = torch.nn.functional.normalize(dirs.to(self.dc.dtype), dim=-1)
        if self.rotation is not None:
            d = d @ self.rotation
        dc = self.dc if idx is None else self.dc[idx]
        rest = self.rest if idx is None else self.rest[idx]
        B = _basis(self.degree, d)  # [M,K]
        rgb = B[:, :1] * dc + (B[:, 1:, None] * rest).sum(dim=1)
        return (rgb + 0.5).clamp_min(0.0)

    def base_logits(self, idx: Optional[Tensor] = None) -> Float[Tensor, "M 3"]:
        """``b``: the logit of the degree-0 colour, clamped to ``(EPS, 1 - EPS)``."""
        if self._base is None:
            self._base = torch.logit(self.dc_colours().clamp(EPS, 1.0 - EPS))
        return self._base if idx is None else self._base[idx]

    def logits(self, idx: Optional[Tensor], dirs: Optional[Tensor]) -> tuple[Tensor, Tensor]:
        """``(b, s)``: the file's diffuse and view-dependent logits of Gaussians ``idx`` along
        ``dirs`` (what the edit engine takes for ``c_d`` and ``c_s``)."""
        b = self.base_logits(idx)
        if not self.view_dependent or dirs is None:
            return b, torch.zeros_like(b)
        return b, torch.logit(self.colours(idx, dirs).clamp(EPS, 1.0 - EPS)) - b

    # ------------------------------------------------------------------- edits
    @staticmethod
    def edited_logits(base: Tensor, field_diffuse: Tensor, field_edited: Tensor) -> Tensor:
        """``e = b + (c_d'' - c_d)``: the edits' change of the field's diffuse logits applied to the file's."""
        return base + (field_edited - field_diffuse)

    def for_edit(self, idx: Optional[Tensor], dirs: Optional[Tensor], field_diffuse: Tensor, k: float
                 ) -> tuple[Tensor, Tensor]:
        """``(offset, c_s)`` for an edit engine that fits ``sigmoid(c_d'' + offset + k c_s)`` with the field's
        ``c_d`` (``field_diffuse`` [M,3] of Gaussians ``idx``) mixed by its edits: ``(0, s + (b - c_d) / k)``,
        the colour :meth:`edited_colours` shows; with ``k = 0`` the offset ``b - c_d`` is added to ``c_d''``
        itself (exact for every Gaussian outside the new edit's segmentation)."""
        b, s = self.logits(idx, dirs)
        o = b - field_diffuse.to(b)
        if k != 0.0:
            return torch.zeros_like(o), s + o / k
        return o, s

    def touched(self, base: Tensor, edited: Tensor, k: float) -> Tensor:
        """Bool [M]: the Gaussians whose colour the edits (diffuse logits ``edited`` from ``base``)
        or the specular strength ``k`` change (see the module doc)."""
        if k != 1.0 and self.view_dependent:
            return torch.ones(base.shape[0], dtype=torch.bool, device=base.device)
        moved = (torch.sigmoid(edited) - torch.sigmoid(base)).abs().amax(dim=-1)
        return moved > self.tolerance

    @staticmethod
    def change(base: Tensor, spec: Tensor, edited: Tensor, k: float) -> Tensor:
        """``sigmoid(e + k s) - sigmoid(b + s)``: what the edits add to the file's colour."""
        return torch.sigmoid(edited + k * spec) - torch.sigmoid(base + spec)

    def edited_colours(self, idx: Optional[Tensor], dirs: Optional[Tensor], edited: Tensor, k: float
                       ) -> Float[Tensor, "M 3"]:
        """``C'_g(d)`` of Gaussians ``idx`` whose edited diffuse logits are ``edited`` [M,3] (``e``, see
        :meth:`edited_logits`): exactly the file's colour where untouched."""
        colour = self.colours(idx, dirs)
        b, s = self.logits(idx, dirs)
        touched = self.touched(b, edited, k)
        if not bool(touched.any()):
            return colour
        delta = self.change(b, s, edited, k)
        return torch.where(touched[:, None], colour + delta, colour)
