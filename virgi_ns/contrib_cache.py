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
        pv, px, py = request.pixel_coords()
        P = len(pv)
        out_pixel, entry_gauss, entry_w, entry_view = [], [], [], []
        T = torch.ones(P)
        for v in torch.unique(request.views).tolist():
            view = self.views[v]
            sel = ((pv == v) & valid).nonzero().flatten()  # output pixels on view v, ascending
            if sel.numel() == 0:
                continue
            src = py[sel] * view.width + px[sel]
            T[sel] = view.transmittance[src]
            start, stop = view.ptr[src], view.ptr[src + 1]
            n = stop - start
            total = int(n.sum())
            if total == 0:
                continue
            rep = torch.repeat_interleave(torch.arange(len(sel)), n)
            first = torch.cumsum(n, 0) - n
            idx = start[rep] + (torch.arange(total) - first[rep])
            out_pixel.append(sel[rep])
            entry_gauss.append(view.gaussian[idx].long())
            entry_w.append(view.weight[idx])
            entry_view.append(torch.full((total,), v, dtype=torch.long))
        if out_pixel:
            pix = torch.cat(out_pixel)
            order = torch.argsort(pix, stable=True)  # views were visited in turn: regroup by pixel
            pix, g = pix[order], torch.cat(entry_gauss)[order]
            w, ev = torch.cat(entry_w)[order], torch.cat(entry_view)[order]
        else:
            pix = g = ev = torch.zeros(0, dtype=torch.long)
            w = torch.zeros(0)
        keys, pair = torch.unique(ev * N + g, return_inverse=True)
        pair_view, pair_gaussian = keys // N, keys % N
        vm = self.cameras.viewmats.to(dev, means.dtype)
        m = means.detach()[pair_gaussian.to(dev)]
        depth = (vm[pair_view.to(dev), 2, :3] * m).sum(-1) + vm[pair_view.to(dev), 2, 3]
        return Contributions(request, N, pair_view.to(dev), pair_gaussian.to(dev), depth, pix.to(dev), pair.to(dev),
                             w.to(dev, means.dtype), T.to(dev, means.dtype), valid.to(dev))


__all__ = ["ContributionCache"]
