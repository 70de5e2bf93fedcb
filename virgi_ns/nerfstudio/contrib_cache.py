"""Contribution lists of whole views computed once, then served for any request on those views.

Geometry is frozen during the colour stage, so the contributions of a pixel never change. On a
CPU, where the reference rasterizer costs seconds per batch, rasterizing every training view
once and slicing the tiles each step asks for out of those lists is far cheaper than
rasterizing the tiles again. The slice is exactly what the rasterizer would return for the same
request (same entries, weights, order and transmittance): a pixel's contributions do not depend
on which other pixels were requested.

Only the :class:`~virgi_ns.raster.Contributions` contract is used; the weights are stored
detached (no gradient reaches the geometry, which is frozen anyway).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from virgi_ns.raster import Cameras, Contributions, Request


@dataclass
class _View:
    ptr: Tensor  # [P+1] long: entries of pixel p are ptr[p]:ptr[p+1]
    gaussian: Tensor  # [M] int32
    weight: Tensor  # [M]
    transmittance: Tensor  # [P]
    width: int
    height: int


class ContributionCache:
    """Whole-view contribution lists of ``cameras`` (rasterized by ``raster(cams, request)``)."""

    def __init__(self, cameras: Cameras, num_gaussians: int,
                 raster: Callable[[Cameras, Request], Contributions],
                 progress: Optional[Callable[[int, int], None]] = None) -> None:
        self.cameras = cameras
        self.num_gaussians = num_gaussians
        self.views: list[_View] = []
        for v in range(len(cameras)):
            cam = cameras.index(v)
            with torch.no_grad():
                c = raster(cam, Request.whole_images(cam))
            self.views.append(self._pack(c))
            if progress is not None:
                progress(v + 1, len(cameras))

    @staticmethod
    def _pack(c: Contributions) -> _View:
        P = c.num_pixels
        counts = torch.bincount(c.pixel.cpu(), minlength=P)
        ptr = torch.zeros(P + 1, dtype=torch.long)
        ptr[1:] = torch.cumsum(counts, 0)
        return _View(ptr, c.pair_gaussian.cpu()[c.pair.cpu()].to(torch.int32), c.weight.detach().cpu().float(),
                     c.transmittance.detach().cpu().float(), c.request.width, c.request.height)

    @property
    def num_entries(self) -> int:
        return sum(int(v.gaussian.numel()) for v in self.views)

    def matches(self, cameras: Cameras) -> bool:
        """True when ``cameras`` are the cached ones (same count, intrinsics and poses)."""
        if cameras is self.cameras:
            return True
        return (len(cameras) == len(self.cameras)
                and torch.equal(cameras.viewmats.cpu(), self.cameras.viewmats.cpu())
                and torch.equal(cameras.Ks.cpu(), self.cameras.Ks.cpu()))

    def contributions(self, request: Request, means: Tensor) -> Contributions:
        """The contributions of ``request`` (items on the cached views), as the rasterizer gives
        them; ``means`` [N,3] (the frozen means) give each pair's depth."""
        dev = means.device
        N = self.num_gaussians
        valid = request.valid_mask(self.cameras)
        hh, ww = request.height, request.width
        rr = torch.arange(hh).view(-1, 1)
        cc = torch.arange(ww).view(1, -1)
        P = request.num_pixels
        T = torch.ones(P)
        pix_parts, idx_parts, view_parts = [], [], []
        for i in range(len(request)):  # item by item: output pixels stay in ascending order
            v = int(request.views[i])
            view = self.views[v]
            x, y = int(request.x0[i]) + cc, int(request.y0[i]) + rr
            inside = ((x >= 0) & (x < view.width) & (y >= 0) & (y < view.height)).reshape(-1)
            out = (i * hh * ww + torch.arange(hh * ww))[inside]
            src = (y * view.width + x).reshape(-1)[inside]
            T[out] = view.transmittance[src]
            start = view.ptr[src]
            n = view.ptr[src + 1] - start
            total = int(n.sum())
            if total == 0:
                continue
            rep = torch.repeat_interleave(n)
            first = torch.cumsum(n, 0) - n
            pix_parts.append(out[rep])
            idx_parts.append(start[rep] + (torch.arange(total) - first[rep]))
            view_parts.append((v, total))
        used = sorted({v for v, _ in view_parts})
        slot = {v: k for k, v in enumerate(used)}
        g_parts, w_parts, key_parts = [], [], []
        for (v, total), idx in zip(view_parts, idx_parts):
            g = self.views[v].gaussian[idx].long()
            g_parts.append(g)
            w_parts.append(self.views[v].weight[idx])
            key_parts.append(g + slot[v] * N)
        if pix_parts:
            pix, key, w = torch.cat(pix_parts), torch.cat(key_parts), torch.cat(w_parts)
        else:
            pix = key = torch.zeros(0, dtype=torch.long)
            w = torch.zeros(0)
        # distinct (view, Gaussian) pairs, ascending by view * N + gaussian, without a sort
        present = torch.zeros(max(len(used), 1) * N, dtype=torch.bool)
        present[key] = True
        keys = present.nonzero().flatten()
        rank = torch.cumsum(present, 0) - 1
        pair = rank[key]
        used_t = torch.tensor(used, dtype=torch.long) if used else torch.zeros(0, dtype=torch.long)
        pair_view, pair_gaussian = used_t[keys // N] if len(keys) else keys, keys % N
        vm = self.cameras.viewmats.to(dev, means.dtype)
        m = means.detach()[pair_gaussian.to(dev)]
        pvd = pair_view.to(dev)
        depth = (vm[pvd, 2, :3] * m).sum(-1) + vm[pvd, 2, 3]
        return Contributions(request, N, pvd, pair_gaussian.to(dev), depth, pix.to(dev), pair.to(dev),
                             w.to(dev, means.dtype), T.to(dev, means.dtype), valid.to(dev))


__all__ = ["ContributionCache"]
