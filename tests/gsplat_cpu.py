"""gsplat's GPU entry points, on a CPU, for the tests of what calls them.

gsplat 1.4.0 ships pure-torch versions of its projection and tile sort (``gsplat/cuda/_torch_impl.py``,
private, with other signatures); its rasterization has none that runs without CUDA. :func:`use_on_cpu`
puts in the place of ``gsplat.fully_fused_projection``, ``isect_tiles`` and ``isect_offset_encode``
gsplat's own torch code behind the public signatures (the sort made stable, as the GPU's radix sort), and in the place of ``rasterize_to_pixels``
:func:`composite_tiles`, a plain per-tile compositor of gsplat's sorted lists by gsplat's classic rules
(pixel centres at +0.5, ``alpha = min(0.999, o exp(-sigma))``, skip ``sigma < 0`` or ``alpha < 1/255``,
stop before ``T <= 1e-4``). So code that calls gsplat's pieces (``virgi_ns/nerfstudio/gsplat_pass.py``)
runs on a CPU through gsplat's own projection and sort; only the last kernel is stood in for."""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from edit_scene import one_thread  # the tests' folder is on sys.path wherever this helper is imported


def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3, near_plane=0.01,
                           far_plane=1e10, radius_clip=0.0, packed=False, sparse_grad=False,
                           calc_compensations=False, camera_model="pinhole"):
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    assert covars is None and not packed and radius_clip == 0.0 and camera_model == "pinhole", "not stood in for"
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    return _fully_fused_projection(means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane,
                                   calc_compensations, camera_model)


def isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, packed=False, n_cameras=None,
                camera_ids=None, gaussian_ids=None):
    from gsplat.cuda._torch_impl import _isect_tiles

    assert not packed, "not stood in for"
    with one_thread():
        tiles, isect_ids, flatten_ids = _isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height,
                                                     sort=False)
    if sort:  # stable, as gsplat's radix sort on the GPU: equal depths keep the Gaussians' order
        isect_ids, order = torch.sort(isect_ids, stable=True)
        flatten_ids = flatten_ids[order]
    return tiles, isect_ids, flatten_ids


def isect_offset_encode(isect_ids, n_cameras, tile_width, tile_height):
    from gsplat.cuda._torch_impl import _isect_offset_encode

    return _isect_offset_encode(isect_ids, n_cameras, tile_width, tile_height)




def composite_tiles(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, image_width: int,
                    image_height: int, tile_size: int, isect_offsets: Tensor, flatten_ids: Tensor,
                    backgrounds: Optional[Tensor] = None, masks=None, packed: bool = False, absgrad: bool = False):
    """``rasterize_to_pixels``'s forward for unpacked inputs: ([C,H,W,D] colours, [C,H,W,1] alphas)."""
    assert masks is None and not packed, "not stood in for"
    with one_thread():
        return _composite_tiles(means2d, conics, colors, opacities, image_width, image_height, tile_size,
                                isect_offsets, flatten_ids, backgrounds)


def _composite_tiles(means2d, conics, colors, opacities, image_width, image_height, tile_size, isect_offsets,
                     flatten_ids, backgrounds):
    C, N = means2d.shape[:2]
    D = colors.shape[-1]
    out = colors.new_zeros(C, image_height, image_width, D)
    alphas = colors.new_zeros(C, image_height, image_width, 1)
    th, tw = isect_offsets.shape[1:]
    ends = torch.cat([isect_offsets.flatten()[1:], isect_offsets.new_tensor([len(flatten_ids)])])
    for c in range(C):
        for ty in range(th):
            for tx in range(tw):
                t = (c * th + ty) * tw + tx
                ids = flatten_ids[int(isect_offsets.flatten()[t]):int(ends[t])].long() - c * N
                y0, x0 = ty * tile_size, tx * tile_size
                y1, x1 = min(y0 + tile_size, image_height), min(x0 + tile_size, image_width)
                ys, xs = torch.meshgrid(torch.arange(y0, y1), torch.arange(x0, x1), indexing="ij")
                px = xs.reshape(-1).to(means2d) + 0.5
                py = ys.reshape(-1).to(means2d) + 0.5
                T_end = torch.ones_like(px)
                if len(ids):
                    m, q = means2d[c, ids], conics[c, ids]  # [M,2], [M,3]
                    dx, dy = m[:, :1] - px, m[:, 1:] - py  # [M,P]
                    sigma = 0.5 * (q[:, :1] * dx * dx + q[:, 2:] * dy * dy) + q[:, 1:2] * dx * dy
                    alpha = torch.clamp_max(opacities[c, ids, None] * torch.exp(-sigma), 0.999)
                    alpha = torch.where((sigma >= 0) & (alpha >= 1.0 / 255.0), alpha, torch.zeros_like(alpha))
                    after = torch.cumprod(1 - alpha, 0)  # T after each Gaussian, in depth order
                    before = torch.cat([torch.ones_like(after[:1]), after[:-1]])
                    kept = (alpha > 0) & (after > 1e-4)  # T is non-increasing: the rest stop too
                    w = torch.where(kept, alpha * before, torch.zeros_like(alpha))
                    T_end = torch.where(kept, after, torch.ones_like(after)).min(0).values
                    pix = w.T @ colors[c, ids]  # [P,D]
                else:
                    pix = colors.new_zeros(len(px), D)
                if backgrounds is not None:
                    pix = pix + T_end[:, None] * backgrounds[c]
                out[c, y0:y1, x0:x1] = pix.reshape(y1 - y0, x1 - x0, D)
                alphas[c, y0:y1, x0:x1, 0] = (1 - T_end).reshape(y1 - y0, x1 - x0)
    return out, alphas


def use_on_cpu(monkeypatch) -> None:
    """gsplat's four entry points that ``gsplat_pass`` calls, on a CPU (see the module docstring)."""
    import gsplat

    monkeypatch.setattr(gsplat, "fully_fused_projection", fully_fused_projection)
    monkeypatch.setattr(gsplat, "isect_tiles", isect_tiles)
    monkeypatch.setattr(gsplat, "isect_offset_encode", isect_offset_encode)
    monkeypatch.setattr(gsplat, "rasterize_to_pixels", composite_tiles)
