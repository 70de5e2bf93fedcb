"""Spherical-harmonic colours of Gaussians for a view direction (the 3DGS / INRIA convention).

The basis functions are nerfstudio's (:func:`sh_components` computes what its
``components_from_spherical_harmonics`` does, without importing nerfstudio); 3DGS files use
the opposite sign on every odd-numbered basis function (its real-SH convention has
``-C1 y, +C1 z, -C1 x, ...``), so those are negated here. The colour is
``max(sum_k sh_k Y_k(dir) + 0.5, 0)`` with ``dir`` the unit vector from the camera centre to the
Gaussian; at degree 0 this is ``0.2820948 f_dc + 0.5`` clamped below at 0.
"""

from __future__ import annotations

import torch
from torch import Tensor

from virgi_ns.gaussians import SH_C0, sh_degree_from_coeffs

__all__ = ["sh_basis", "sh_colors", "sh_components", "view_colors"]


def sh_components(levels: int, directions: Tensor) -> Tensor:
    """[..., levels**2] real SH basis (nerfstudio's signs and order) at unit ``directions`` [..., 3],
    bands ``0 .. levels - 1`` (1 to 5 levels). The same expressions in the same order as nerfstudio
    1.1.5, so the values are equal bit for bit; like it, the result has torch's default dtype."""
    assert 1 <= levels <= 5, f"SH levels must be in [1,5], got {levels}"
    assert directions.shape[-1] == 3, f"directions must have three components, got {directions.shape[-1]}"
    out = torch.zeros((*directions.shape[:-1], levels**2), device=directions.device)
    x, y, z = directions[..., 0], directions[..., 1], directions[..., 2]
    xx, yy, zz = x**2, y**2, z**2
    out[..., 0] = 0.28209479177387814
    if levels > 1:
        out[..., 1] = 0.4886025119029199 * y
        out[..., 2] = 0.4886025119029199 * z
        out[..., 3] = 0.4886025119029199 * x
    if levels > 2:
        out[..., 4] = 1.0925484305920792 * x * y
        out[..., 5] = 1.0925484305920792 * y * z
        out[..., 6] = 0.9461746957575601 * zz - 0.31539156525251999
        out[..., 7] = 1.0925484305920792 * x * z
        out[..., 8] = 0.5462742152960396 * (xx - yy)
    if levels > 3:
        out[..., 9] = 0.5900435899266435 * y * (3 * xx - yy)
        out[..., 10] = 2.890611442640554 * x * y * z
        out[..., 11] = 0.4570457994644658 * y * (5 * zz - 1)
        out[..., 12] = 0.3731763325901154 * z * (5 * zz - 3)
        out[..., 13] = 0.4570457994644658 * x * (5 * zz - 1)
        out[..., 14] = 1.445305721320277 * z * (xx - yy)
        out[..., 15] = 0.5900435899266435 * x * (xx - 3 * yy)
    if levels > 4:
        out[..., 16] = 2.5033429417967046 * x * y * (xx - yy)
        out[..., 17] = 1.7701307697799304 * y * z * (3 * xx - yy)
        out[..., 18] = 0.9461746957575601 * x * y * (7 * zz - 1)
        out[..., 19] = 0.6690465435572892 * y * z * (7 * zz - 3)
        out[..., 20] = 0.10578554691520431 * (35 * zz * zz - 30 * zz + 3)
        out[..., 21] = 0.6690465435572892 * x * z * (7 * zz - 3)
        out[..., 22] = 0.47308734787878004 * (xx - yy) * (7 * zz - 1)
        out[..., 23] = 1.7701307697799304 * x * z * (xx - 3 * yy)
        out[..., 24] = 0.6258357354491761 * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))
    return out


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """[..., (degree+1)^2] real SH basis at unit directions ``dirs`` [..., 3], 3DGS signs."""
    k = (degree + 1) ** 2
    comps = sh_components(degree + 1, dirs).to(dirs.dtype)
    sign = torch.ones(k, dtype=dirs.dtype, device=dirs.device)
    sign[1::2] = -1.0
    return comps * sign


def sh_colors(sh: Tensor, dirs: Tensor | None = None) -> Tensor:
    """Colours [N, 3] from SH coefficients [N, K, 3] seen along ``dirs`` [N, 3] (any length;
    normalised here). ``dirs`` may be None when K == 1."""
    degree = sh_degree_from_coeffs(sh.shape[1])
    if degree == 0:
        rgb = SH_C0 * sh[:, 0]
    else:
        if dirs is None:
            raise ValueError("sh_colors: view directions are needed for SH degree > 0")
        d = torch.nn.functional.normalize(dirs.to(sh.dtype), dim=-1)
        rgb = (sh_basis(degree, d)[:, :, None] * sh).sum(dim=1)
    return torch.clamp_min(rgb + 0.5, 0.0)


def view_colors(sh: Tensor, means: Tensor, camera_center: Tensor) -> Tensor:
    """Colours [N, 3] of Gaussians at ``means`` [N, 3] seen from ``camera_center`` [3]."""
    if sh.shape[1] == 1:
        return sh_colors(sh)
    return sh_colors(sh, means - camera_center.to(means).reshape(1, 3))
