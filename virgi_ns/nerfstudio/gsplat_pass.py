"""One view of the frozen Gaussians through gsplat's public pieces (``fully_fused_projection``,
``isect_tiles``, ``isect_offset_encode``, ``rasterize_to_pixels``), doing for one camera the work that
``gsplat.rasterization(..., sh_degree=None, packed=False, rasterize_mode="classic")`` does, with the same
settings (tile 16, ``eps2d`` 0.3, near 0.01, far 1e10, no radius clip, pinhole) and so the same kernels
on the same inputs, less what that call adds for generality:

- the opacities are passed as a [1,N] view (``rasterization`` copies them with ``repeat(C, 1)``);
- the background of the depth channel is a zero the caller keeps (``rasterization`` builds it with
  ``zeros`` and ``cat`` per call);
- expected depth is the composited depth divided in place by the clamped accumulation
  (``rasterization`` divides and then copies the whole image with ``cat``);
- the projection is returned, so that a second pass of other channels in the same view (diffuse,
  segmentation) composites without projecting and sorting again;
- none of its argument checks and bookkeeping (``meta``) in Python.

gsplat is imported on first use (it compiles its CUDA code then).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import Tensor

TILE = 16
EPS2D = 0.3
NEAR = 0.01
FAR = 1e10


@dataclass(eq=False)
class Projection:
    """gsplat's projection and tile intersections of the Gaussians in one view."""

    means2d: Tensor
    """[1,N,2]"""
    conics: Tensor
    """[1,N,3]"""
    depths: Tensor
    """[1,N] camera z of each mean."""
    opacities: Tensor
    """[1,N]"""
    isect_offsets: Tensor
    flatten_ids: Tensor
    width: int
    height: int


def project(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
            width: int, height: int) -> Projection:
    """Project ``N`` Gaussians (activated ``scales`` [N,3] and ``opacities`` [N]) into one view
    (``viewmat`` [1,4,4], ``K`` [1,3,3]) and sort their tile intersections."""
    from gsplat import fully_fused_projection, isect_offset_encode, isect_tiles

    radii, means2d, depths, conics, _ = fully_fused_projection(
        means, None, quats, scales, viewmat, K, width, height, eps2d=EPS2D, near_plane=NEAR, far_plane=FAR,
        radius_clip=0.0, packed=False, calc_compensations=False)
    tw, th = math.ceil(width / TILE), math.ceil(height / TILE)
    _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, TILE, tw, th, packed=False, n_cameras=1)
    offsets = isect_offset_encode(isect_ids, 1, tw, th)
    return Projection(means2d, conics, depths, opacities[None], offsets, flatten_ids, width, height)


def rasterize(p: Projection, colours: Tensor, backgrounds: Optional[Tensor], expected_depth: bool
              ) -> Tuple[Tensor, Tensor]:
    """Composite ``colours`` [N,D] (float32) over ``backgrounds`` ([1,D], or [1,D+1] ending in 0 with
    ``expected_depth``, or None) in the projected view: ([H,W,D] or [H,W,D+1] with the expected depth
    last, [H,W,1] accumulation), as ``rasterization``'s "RGB" / "RGB+ED"."""
    from gsplat import rasterize_to_pixels

    c = torch.cat([colours, p.depths[0, :, None]], dim=-1) if expected_depth else colours
    img, alpha = rasterize_to_pixels(p.means2d, p.conics, c[None], p.opacities, p.width, p.height, TILE,
                                     p.isect_offsets, p.flatten_ids, backgrounds=backgrounds)
    img, alpha = img[0], alpha[0]
    if expected_depth:
        img[..., -1:].div_(alpha.clamp(min=1e-10))
    return img, alpha


__all__ = ["Projection", "project", "rasterize"]
