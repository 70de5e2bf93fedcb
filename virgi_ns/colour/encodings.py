"""The colour field's hash grid: nerfstudio's, with two changes that are ours to make from outside
nerfstudio (the field takes nerfstudio's SH encoding and scene contraction as they are):

- :class:`GridEncoding` reads the eight corners of a point in one ``index_select`` (same hash,
  same trilinear arithmetic, same parameter and state dict as nerfstudio's torch
  ``HashEncoding``): its gradient accumulates with ``index_add_`` instead of the sort that
  advanced indexing's backward costs, which dominated a colour step; and it hashes each axis's
  two coordinates once for the corners that share them;
- ``empty=True`` builds the table without its random draws (a run's field whose state is loaded
  next: a large table's draws take a fresh process a noticeable part of a second).
"""

from __future__ import annotations

import torch
from nerfstudio.field_components.encodings import HashEncoding
from torch import Tensor, nn

__all__ = ["GridEncoding"]

# the eight corners (x, y, z; 1 = ceil) in the order nerfstudio's interpolation reads them:
# ccc, cfc, ffc, fcc, ccf, cff, fff, fcf
_CORNERS = ((1, 1, 1), (1, 0, 1), (0, 0, 1), (0, 1, 1), (1, 1, 0), (1, 0, 0), (0, 0, 0), (0, 1, 0))


class GridEncoding(HashEncoding):
    """nerfstudio's torch :class:`HashEncoding` with the corner look-ups in one ``index_select``
    (module docstring); ``empty``: leave the table uninitialised (its state is loaded next)."""

    def __init__(self, empty: bool = False, **kwargs) -> None:
        if not empty:
            super().__init__(**kwargs)
            return
        # the parent built with a one-row table per level (its random draw costs nothing), then
        # given the table size asked for, uninitialised
        size = int(kwargs.pop("log2_hashmap_size", 19))
        super().__init__(log2_hashmap_size=0, **kwargs)
        self.log2_hashmap_size = size
        self.hash_table_size = 2**size
        self.hash_offset = torch.arange(self.num_levels) * self.hash_table_size
        self.hash_table = nn.Parameter(torch.empty(self.hash_table_size * self.num_levels, self.features_per_level))

    def _corner_hashes(self, c: Tensor, f: Tensor) -> Tensor:
        """[..., 8, L] table rows of the eight corners (``_CORNERS``' order) from the ceil and floor grid
        coordinates ``c``, ``f`` [..., L, 3]: nerfstudio's ``hash_fn`` (each axis times its prime, XORed,
        modulo the table size, plus the level's offset), with each axis's two products computed once and
        shared by the four corners that use them: the same integers, a quarter of the multiplications."""
        primes = torch.tensor([1, 2654435761, 805459861], device=c.device)
        terms = (f * primes, c * primes)  # [..., L, 3] int64: each axis's floor and ceil term
        offsets = self.hash_offset.to(c.device)
        rows = []
        for ix, iy, iz in _CORNERS:
            h = torch.bitwise_xor(terms[ix][..., 0], terms[iy][..., 1])
            h = torch.bitwise_xor(h, terms[iz][..., 2])
            h %= self.hash_table_size
            rows.append(h + offsets)
        return torch.stack(rows, dim=-2)

    def pytorch_fwd(self, in_tensor: Tensor) -> Tensor:
        """Features [..., L * F] of points ``in_tensor`` [..., 3] in [0, 1]^3."""
        assert in_tensor.shape[-1] == 3
        in_tensor = in_tensor[..., None, :]  # [..., 1, 3]
        scaled = in_tensor * self.scalings.view(-1, 1).to(in_tensor.device)  # [..., L, 3]
        c = torch.ceil(scaled).type(torch.int32)
        f = torch.floor(scaled).type(torch.int32)
        offset = scaled - f
        hashed = self._corner_hashes(c, f)  # [..., 8, L]
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
