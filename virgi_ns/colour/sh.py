"""Spherical-harmonic colours of Gaussians for a view direction (the 3DGS / INRIA convention).

The basis functions are nerfstudio's (``components_from_spherical_harmonics``); 3DGS files use
the opposite sign on every odd-numbered basis function (its real-SH convention has
``-C1 y, +C1 z, -C1 x, ...``), so those are negated here. The colour is
``max(sum_k sh_k Y_k(dir) + 0.5, 0)`` with ``dir`` the unit vector from the camera centre to the
Gaussian; at degree 0 this is ``0.2820948 f_dc + 0.5`` clamped below at 0.
"""

from __future__ import annotations

import torch
from nerfstudio.utils.math import components_from_spherical_harmonics
from torch import Tensor

from virgi_ns.gaussians import SH_C0, sh_degree_from_coeffs

__all__ = ["sh_basis", "sh_colours", "view_colours"]


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """[..., (degree+1)^2] real SH basis at unit directions ``dirs`` [..., 3], 3DGS signs."""
    k = (degree + 1) ** 2
    comps = components_from_spherical_harmonics(degree + 1, dirs).to(dirs.dtype)
    sign = torch.ones(k, dtype=dirs.dtype, device=dirs.device)
    sign[1::2] = -1.0
    return comps * sign


def sh_colours(sh: Tensor, dirs: Tensor | None = None) -> Tensor:
    """Colours [N, 3] from SH coefficients [N, K, 3] seen along ``dirs`` [N, 3] (any length;
    normalised here). ``dirs`` may be None when K == 1."""
    degree = sh_degree_from_coeffs(sh.shape[1])
    if degree == 0:
        rgb = SH_C0 * sh[:, 0]
    else:
        if dirs is None:
            raise ValueError("sh_colours: view directions are needed for SH degree > 0")
        d = torch.nn.functional.normalize(dirs.to(sh.dtype), dim=-1)
        rgb = (sh_basis(degree, d)[:, :, None] * sh).sum(dim=1)
    return torch.clamp_min(rgb + 0.5, 0.0)


def view_colours(sh: Tensor, means: Tensor, camera_center: Tensor) -> Tensor:
    """Colours [N, 3] of Gaussians at ``means`` [N, 3] seen from ``camera_center`` [3]."""
    if sh.shape[1] == 1:
        return sh_colours(sh)
    return sh_colours(sh, means - camera_center.to(means).reshape(1, 3))
