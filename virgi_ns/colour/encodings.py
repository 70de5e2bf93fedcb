"""The colour field's encodings without importing nerfstudio: a multi-resolution hash grid, the SH
encoding of view directions and the L-inf scene contraction.

Each computes what nerfstudio 1.1.5's torch implementation computes, bit for bit (its
``HashEncoding``, ``SHEncoding``, ``SceneContraction(order=inf)``), with the same parameter names,
the same random initialisation (the same draws from torch's generator) and so the same state
dict: runs trained with either load into the other. Importing nerfstudio's field components pulls
in its viewer library and much of torch's compiler stack, about a second of a fresh process that
the command-line tools would otherwise pay on every call.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from virgi_ns.colour.sh import sh_components

__all__ = ["GridEncoding", "SHDirections", "contract_linf"]

_PRIMES = (1, 2654435761, 805459861)
# the eight corners (x, y, z; 1 = ceil) in the order the interpolation below reads them:
# ccc, cfc, ffc, fcc, ccf, cff, fff, fcf
_CORNERS = ((1, 1, 1), (1, 0, 1), (0, 0, 1), (0, 1, 1), (1, 1, 0), (1, 0, 0), (0, 0, 0), (0, 1, 0))


class GridEncoding(nn.Module):
    """Instant-NGP hash grid over [0, 1]^3: ``num_levels`` tables of ``2**log2_hashmap_size`` rows
    of ``features_per_level``, level ``l`` at resolution ``floor(min_res * growth**l)``, trilinear
    interpolation of the eight corners. The eight look-ups are one ``index_select``, whose gradient
    accumulates with ``index_add_`` (atomic adds on a GPU) instead of the sort that advanced
    indexing's backward costs. ``empty``: leave the table uninitialised (its state is loaded next)."""

    def __init__(self, num_levels: int = 16, min_res: int = 16, max_res: int = 1024, log2_hashmap_size: int = 19,
                 features_per_level: int = 2, hash_init_scale: float = 0.001, implementation: str = "torch",
                 empty: bool = False) -> None:
        super().__init__()
        if implementation != "torch":
            raise ValueError(f"GridEncoding: only the torch implementation exists here, not {implementation!r}")
        self.in_dim = 3
        self.num_levels = num_levels
        self.min_res = min_res
        self.features_per_level = features_per_level
        self.hash_init_scale = hash_init_scale
        self.log2_hashmap_size = log2_hashmap_size
        self.hash_table_size = 2**log2_hashmap_size
        levels = torch.arange(num_levels)
        self.growth_factor = np.exp((np.log(max_res) - np.log(min_res)) / (num_levels - 1)) if num_levels > 1 else 1
        self.scalings = torch.floor(min_res * self.growth_factor**levels)
        self.hash_offset = levels * self.hash_table_size
        self.tcnn_encoding = None
        size = (self.hash_table_size * num_levels, features_per_level)
        if empty:  # a table about to be loaded: no random draws (a large table's take a fresh process long)
            table = torch.empty(size)
        else:
            table = torch.rand(size=size) * 2 - 1
            table *= hash_init_scale
        self.hash_table = nn.Parameter(table)

    def get_out_dim(self) -> int:
        return self.num_levels * self.features_per_level

    def hash_fn(self, idx: Tensor) -> Tensor:
        """Rows of the integer grid corners ``idx`` [..., L, 3] in the stacked tables [..., L]."""
        idx = idx * torch.tensor(_PRIMES).to(idx.device)
        x = torch.bitwise_xor(idx[..., 0], idx[..., 1])
        x = torch.bitwise_xor(x, idx[..., 2])
        x %= self.hash_table_size
        x += self.hash_offset.to(x.device)
        return x

    def pytorch_fwd(self, in_tensor: Tensor) -> Tensor:
        """Features [..., L * F] of points ``in_tensor`` [..., 3] in [0, 1]^3."""
        assert in_tensor.shape[-1] == 3
        in_tensor = in_tensor[..., None, :]  # [..., 1, 3]
        scaled = in_tensor * self.scalings.view(-1, 1).to(in_tensor.device)  # [..., L, 3]
        c = torch.ceil(scaled).type(torch.int32)
        f = torch.floor(scaled).type(torch.int32)
        offset = scaled - f
        # the corners [..., 8, L, 3]: with corners before levels, hash_fn adds each level's table
        # offset as it does for one corner
        ceil = torch.tensor(_CORNERS, dtype=torch.bool, device=c.device).view(8, 1, 3)
        hashed = self.hash_fn(torch.where(ceil, c[..., None, :, :], f[..., None, :, :]))  # [..., 8, L]
        feats = self.hash_table.index_select(0, hashed.reshape(-1)).view(*hashed.shape, -1)  # [..., 8, L, F]
        f_0, f_1, f_2, f_3, f_4, f_5, f_6, f_7 = feats.unbind(-3)
        o0, o1, o2 = offset[..., 0:1], offset[..., 1:2], offset[..., 2:3]
        f_03 = f_0 * o0 + f_3 * (1 - o0)
        f_12 = f_1 * o0 + f_2 * (1 - o0)
        f_56 = f_5 * o0 + f_6 * (1 - o0)
        f_47 = f_4 * o0 + f_7 * (1 - o0)
        f0312 = f_03 * o1 + f_12 * (1 - o1)
        f4756 = f_47 * o1 + f_56 * (1 - o1)
        encoded = f0312 * o2 + f4756 * (1 - o2)  # [..., L, F]
        return torch.flatten(encoded, start_dim=-2, end_dim=-1)

    def forward(self, in_tensor: Tensor) -> Tensor:
        return self.pytorch_fwd(in_tensor)


class SHDirections(nn.Module):
    """Real spherical harmonics of unit directions, bands ``0 .. levels - 1`` (``levels**2``
    components; no gradient flows to the directions, as in nerfstudio's encoding)."""

    def __init__(self, levels: int = 4, implementation: str = "torch") -> None:
        super().__init__()
        if levels <= 0 or levels > 4:
            raise ValueError(f"Spherical harmonic encoding only supports 1 to 4 levels, requested {levels}")
        self.in_dim = 3
        self.levels = levels
        self.tcnn_encoding = None

    def get_out_dim(self) -> int:
        return self.levels**2

    @torch.no_grad()
    def forward(self, in_tensor: Tensor) -> Tensor:
        return sh_components(self.levels, in_tensor)


def contract_linf(x: Tensor) -> Tensor:
    """MipNeRF-360's contraction with the L-inf norm: the unit cube stays, the rest of space lands
    in the cube of side 4 (``(2 - 1/|x|) x/|x|`` outside)."""
    mag = torch.linalg.norm(x, ord=float("inf"), dim=-1)[..., None]
    return torch.where(mag < 1, x, (2 - (1 / mag)) * (x / mag))
