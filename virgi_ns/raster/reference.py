"""The reference rasterizer: pure torch, CPU or GPU, float32 or float64, differentiable.

This module is the specification that every other backend must reproduce. Its rules are those
of gsplat 1.4.0 in classic mode (``fully_fused_projection_fwd.cu``, ``utils.cuh``,
``isect_tiles.cu``, ``rasterize_to_pixels_fwd.cu``), checked against the installed sources:

Projection (per view, per Gaussian)
  * ``q`` is normalised; ``R(q)`` is the usual rotation matrix of a unit wxyz quaternion;
    ``Sigma = (R S)(R S)^T`` with ``S = diag(scales)`` (standard deviations).
  * camera space: ``mu_c = W mu + t``, ``Sigma_c = W Sigma W^T`` (``[W | t]`` = viewmat).
  * culled (radius 0) when ``z < near`` (0.01) or ``z > far`` (1e10). ``z == near`` is kept.
  * pinhole Jacobian with the image-bound clamp: ``tan_fovx = 0.5 W / fx``,
    ``lim_x+ = (W - cx) / fx + 0.3 tan_fovx``, ``lim_x- = cx / fx + 0.3 tan_fovx`` (same for y
    with H, fy, cy); ``tx = z clamp(x / z, -lim_x-, lim_x+)``, likewise ``ty``;
    ``J = [[fx/z, 0, -fx tx / z^2], [0, fy/z, -fy ty / z^2]]``, ``Sigma2d = J Sigma_c J^T``.
    W, H are the FULL image's size, whatever part of the image is requested.
  * ``mean2d = (fx x / z + cx, fy y / z + cy)`` (unclamped).
  * ``Sigma2d += eps2d I`` with eps2d = 0.3; ``det = a c - b^2`` of the blurred matrix; culled when
    ``det <= 0``. ``conic = (c / det, -b / det, a / det)``.
    Float32 note (deliberate, same values in exact arithmetic): ``Sigma2d = A A^T`` with
    ``A = J W R S`` (2x3), and ``det`` is computed as ``sum of squared 2x2 minors of A
    + eps2d (a0 + c0) + eps2d^2`` (Cauchy-Binet), which does not cancel for anisotropic Gaussians
    the way ``a c - b^2`` does in float32.
  * radius (one integer per Gaussian and view, as gsplat 1.4.0's ``radii`` [C, N]):
    ``mid = (a + c) / 2``, ``v1 = mid + sqrt(max(0.01, mid^2 - det))``, ``r = ceil(3 sqrt(v1))``;
    culled when ``r <= 0`` (radius_clip 0) or off-image:
    ``x + r <= 0 or x - r >= W or y + r <= 0 or y - r >= H``.

Tile membership (16 px, on the full image's grid, as ``isect_tiles``)
  * ``tiles_w = ceil(W / 16)``, ``tiles_h = ceil(H / 16)``; with ``tx = x / 16``, ``tr = r / 16``:
    ``[clamp(floor(tx - tr), 0, tiles_w), clamp(ceil(tx + tr), 0, tiles_w))`` (half open), same in y
    (gsplat casts the floor to uint32, which saturates negatives to 0).
  * A pixel (px, py) is reached only by Gaussians whose range holds its grid tile
    (px // 16, py // 16), whatever the request's own tile placement.
  * Per grid tile, Gaussians are composited by increasing depth z; ties by Gaussian index (gsplat's
    radix sort is stable over ids written in Gaussian order).

Compositing (per pixel, front to back)
  * pixel centre ``p = (px + 0.5, py + 0.5)``, ``d = mean2d - p``,
    ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy`` with conic (a, b, c). Evaluated as the equal sum
    of two squares ``sigma = 0.5 (p (dx - r dy)^2 + s dy^2)`` with ``p = c2/det``, ``r = b2/c2``,
    ``s = 1/c2`` (``a2, b2, c2``: the blurred 2D covariance; ``Projection.quad``), because the
    conic form cancels catastrophically in float32 for elongated Gaussians (errors ~1e-3 in alpha
    at anisotropy 1e4). Backends must use this form to agree with the reference in float32;
    ``sigma`` is never negative in it, so gsplat's ``sigma < 0`` skip never fires;
  * ``alpha = min(0.999, o exp(-sigma))``; skipped when ``sigma < 0`` or ``alpha < 1/255``;
  * ``T_next = T (1 - alpha)``; when ``T_next <= 1e-4`` the pixel stops and that Gaussian is
    excluded; otherwise it contributes ``w = alpha T`` and ``T = T_next``. ``T`` starts at 1 and its
    final value is the pixel's transmittance.

Implementation: each Gaussian's tile-range intersections with the requested grid tiles are
sorted by (tile, depth, index); each intersection is expanded into the pixel rows of its tile where
alpha can reach 1/255 (a conservative box around the ellipse ``sigma <= log(255 o)``, 1 px
margin: every excluded pixel has alpha < 1/255 for certain, so nothing depends on the box), each
row evaluated as a 16-pixel strip of the tile with the columns outside the box masked (the
per-row values broadcast; no per-pixel gathers); the
surviving (pixel, Gaussian) pairs are grouped per pixel in depth order and T is a sequential
``cumprod`` in the working dtype over each pixel's row of a padded matrix (rows padded to a
power of two, one matrix per width, so that padding at most doubles the memory). Every step is a torch
op of the geometry, so weights carry gradients to means, quats, scales and opacities.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from virgi_ns.raster.contract import Cameras, Contributions, Request

NEAR_PLANE = 0.01
FAR_PLANE = 1e10
EPS2D = 0.3
TILE_SIZE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4

_TILE_PIX = TILE_SIZE * TILE_SIZE


@dataclass
class Projection:
    """Per-view screen-space Gaussians, each [V, N, ...]; entries with ``radii == 0`` are culled
    (their other values are finite but meaningless)."""

    means2d: Tensor  # [V, N, 2]
    conics: Tensor  # [V, N, 3] (a, b, c) of the inverse 2D covariance, gsplat's ``conics``
    quad: Tensor  # [V, N, 3] (p, r, s): sigma = 0.5 (p (dx - r dy)^2 + s dy^2), the same form
    cov2d: Tensor  # [V, N, 3] (a, b, c) of the blurred 2D covariance
    depths: Tensor  # [V, N] camera-space z
    radii: Tensor  # [V, N] int32 pixel radius, 0 = culled
    widths: Tensor  # [V] long (cpu)
    heights: Tensor  # [V] long (cpu)

    @property
    def visible(self) -> Tensor:
        """[V, N] bool: the Gaussian reaches the view's image."""
        return self.radii > 0

    def tile_ranges(self, tile_size: int = TILE_SIZE) -> Tensor:
        """[V, N, 4] long ``(x_min, y_min, x_max, y_max)`` half-open tile ranges on the view's grid
        (empty for culled Gaussians), as gsplat's ``isect_tiles``."""
        dev = self.means2d.device
        m = self.means2d.detach()
        r = self.radii.to(m.dtype)
        tw = torch.div(self.widths + tile_size - 1, tile_size, rounding_mode="floor").to(dev).view(-1, 1)
        th = torch.div(self.heights + tile_size - 1, tile_size, rounding_mode="floor").to(dev).view(-1, 1)
        tx = m[..., 0] / tile_size
        ty = m[..., 1] / tile_size
        tr = r / tile_size
        zero = torch.zeros((), dtype=torch.long, device=dev)
        x0 = torch.floor(tx - tr).clamp(-1, 2**31).long().clamp(min=zero).minimum(tw)
        y0 = torch.floor(ty - tr).clamp(-1, 2**31).long().clamp(min=zero).minimum(th)
        x1 = torch.ceil(tx + tr).clamp(-1, 2**31).long().clamp(min=zero).minimum(tw)
        y1 = torch.ceil(ty + tr).clamp(-1, 2**31).long().clamp(min=zero).minimum(th)
        out = torch.stack([x0, y0, x1, y1], dim=-1)
        return torch.where(self.visible[..., None], out, torch.zeros_like(out))


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] wxyz (any norm) -> [N, 3, 3] rotation matrices."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    cameras: Cameras,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    eps2d: float = EPS2D,
) -> Projection:
    """Project N Gaussians into every view of ``cameras`` (gsplat 1.4.0 classic rules)."""
    dtype, dev = means.dtype, means.device
    cams = cameras.to(dev, dtype)
    W = cams.viewmats[:, :3, :3]  # [V,3,3]
    t = cams.viewmats[:, :3, 3]  # [V,3]
    wid = cams.widths.to(dev, dtype).view(-1, 1)
    hei = cams.heights.to(dev, dtype).view(-1, 1)
    fx = cams.Ks[:, 0, 0].view(-1, 1)
    fy = cams.Ks[:, 1, 1].view(-1, 1)
    cx = cams.Ks[:, 0, 2].view(-1, 1)
    cy = cams.Ks[:, 1, 2].view(-1, 1)

    Rq = quat_to_rotmat(quats)
    mean_c = torch.einsum("vij,nj->vni", W, means) + t[:, None, :]  # [V,N,3]

    x, y, z = mean_c.unbind(-1)
    in_depth = (z >= near_plane) & (z <= far_plane)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # keep culled rows finite (and their grads)
    rz = 1.0 / zs
    rz2 = rz * rz
    tan_fovx = 0.5 * wid / fx
    tan_fovy = 0.5 * hei / fy
    lim_x_pos = (wid - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (hei - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = zs * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * rz))
    ty = zs * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * rz))
    zero = torch.zeros_like(zs)
    J = torch.stack([fx * rz, zero, -fx * tx * rz2, zero, fy * rz, -fy * ty * rz2], dim=-1).reshape(*zs.shape, 2, 3)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)

    # Sigma2d = J W R S S R^T W^T J^T = A A^T with A = J W R S (2x3): its entries and its determinant
    # (Cauchy-Binet: the sum of the squared 2x2 minors of A) stay accurate in float32 even for
    # very anisotropic Gaussians, where a c - b^2 would cancel.
    JW = torch.einsum("vnij,vjk->vnik", J, W)  # [V,N,2,3]
    A = torch.einsum("vnij,njk->vnik", JW, Rq) * scales[None, :, None, :]
    a0 = (A[..., 0, :] * A[..., 0, :]).sum(-1)
    c0 = (A[..., 1, :] * A[..., 1, :]).sum(-1)
    b = (A[..., 0, :] * A[..., 1, :]).sum(-1)
    m01 = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    m02 = A[..., 0, 0] * A[..., 1, 2] - A[..., 0, 2] * A[..., 1, 0]
    m12 = A[..., 0, 1] * A[..., 1, 2] - A[..., 0, 2] * A[..., 1, 1]
    det0 = m01 * m01 + m02 * m02 + m12 * m12
    a = a0 + eps2d
    c = c0 + eps2d
    det = det0 + eps2d * (a0 + c0) + eps2d * eps2d
    ok = in_depth & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    # the same quadratic form as a sum of two squares (see the module docstring)
    quad = torch.stack([c / det_s, b / c, 1.0 / c], dim=-1)
    cov2d = torch.stack([a, b, c], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        v1 = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(v1))
        radius = torch.where(ok & torch.isfinite(radius), radius, torch.zeros_like(radius))
        mx, my = means2d[..., 0], means2d[..., 1]
        inside = (mx + radius > 0) & (mx - radius < wid) & (my + radius > 0) & (my - radius < hei)
        radius = torch.where(inside & (radius > 0), radius, torch.zeros_like(radius))
        radii = radius.clamp(max=2**31 - 1).to(torch.int32)
    return Projection(means2d, conics, quad, cov2d, z, radii, cams.widths.clone(), cams.heights.clone())


def _empty(request: Request, n: int, dtype: torch.dtype, dev: torch.device, valid: Tensor) -> Contributions:
    li = torch.zeros(0, dtype=torch.long, device=dev)
    return Contributions(
        request=request, num_gaussians=n, pair_view=li, pair_gaussian=li.clone(),
        pair_depth=torch.zeros(0, dtype=dtype, device=dev), pixel=li.clone(), pair=li.clone(),
        weight=torch.zeros(0, dtype=dtype, device=dev),
        transmittance=torch.ones(request.num_pixels, dtype=dtype, device=dev), valid=valid,
    )


def _segment_arange(counts: Tensor) -> Tensor:
    """[0..c0), [0..c1), ... concatenated."""
    total = int(counts.sum())
    starts = torch.cumsum(counts, 0) - counts
    return torch.arange(total, device=counts.device) - torch.repeat_interleave(starts, counts, output_size=total)


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, cameras: Cameras, request: Request,
              max_pairs: int = 1 << 21) -> Contributions:
    """Contribution lists for ``request`` (see the module docstring for the rules).

    Work is split into chunks of whole grid tiles of about ``max_pairs`` evaluated (pixel, Gaussian)
    lanes each (16 per row of a Gaussian's box in a tile), which bounds memory; results do not depend on it.
    """
    dtype, dev = means.dtype, means.device
    n = int(means.shape[0])
    opacities = opacities.reshape(-1)
    valid_cpu = request.valid_mask(cameras)
    valid = valid_cpu.to(dev)
    if n == 0 or len(request) == 0 or not bool(valid_cpu.any()):
        return _empty(request, n, dtype, dev, valid)

    # ---- project only the views the request touches
    views_used = torch.unique(request.views)
    proj = project(means, quats, scales, cameras.index(views_used))
    tw = torch.div(proj.widths + TILE_SIZE - 1, TILE_SIZE, rounding_mode="floor")  # [Vu] cpu
    th = torch.div(proj.heights + TILE_SIZE - 1, TILE_SIZE, rounding_mode="floor")
    tile_base = torch.cumsum(tw * th, 0) - tw * th  # first global tile id of each used view

    # ---- requested pixels -> (unit = requested grid tile of a view, local pixel)
    pv, px, py = request.pixel_coords()
    pidx = torch.nonzero(valid_cpu).squeeze(1)
    pvu = torch.searchsorted(views_used, pv[pidx])
    pgx, pgy = px[pidx] // TILE_SIZE, py[pidx] // TILE_SIZE
    ptile = tile_base[pvu] + pgy * tw[pvu] + pgx
    units, p_unit = torch.unique(ptile, return_inverse=True)  # sorted global tile ids
    n_units = int(units.shape[0])
    p_local = (py[pidx] % TILE_SIZE) * TILE_SIZE + (px[pidx] % TILE_SIZE)
    p_q = p_unit * _TILE_PIX + p_local  # unit-pixel id of each valid output pixel
    u_vu = torch.searchsorted(tile_base, units, right=True) - 1
    u_tile = units - tile_base[u_vu]
    u_gx, u_gy = u_tile % tw[u_vu], u_tile // tw[u_vu]
    wanted = torch.zeros(n_units * _TILE_PIX, dtype=torch.bool)
    wanted[p_q] = True
    unit_of_tile = torch.full((int((tw * th).sum()),), -1, dtype=torch.long)
    unit_of_tile[units] = torch.arange(n_units)

    # ---- intersections (view, Gaussian, unit), only for requested tiles
    with torch.no_grad():
        rng = proj.tile_ranges().cpu()  # [Vu,N,4]
        bx0 = torch.full((len(views_used),), 2**40, dtype=torch.long).scatter_reduce(0, u_vu, u_gx, "amin")
        by0 = torch.full((len(views_used),), 2**40, dtype=torch.long).scatter_reduce(0, u_vu, u_gy, "amin")
        bx1 = torch.full((len(views_used),), -1, dtype=torch.long).scatter_reduce(0, u_vu, u_gx + 1, "amax")
        by1 = torch.full((len(views_used),), -1, dtype=torch.long).scatter_reduce(0, u_vu, u_gy + 1, "amax")
        x0 = torch.maximum(rng[..., 0], bx0[:, None])
        y0 = torch.maximum(rng[..., 1], by0[:, None])
        x1 = torch.minimum(rng[..., 2], bx1[:, None])
        y1 = torch.minimum(rng[..., 3], by1[:, None])
        wx = (x1 - x0).clamp(min=0)
        wy = (y1 - y0).clamp(min=0)
        cnt = (wx * wy).reshape(-1)  # in (view, Gaussian) order
        vg = torch.repeat_interleave(torch.arange(cnt.shape[0]), cnt)
        off = _segment_arange(cnt)
        wxf = wx.reshape(-1)[vg]
        ix_vu = vg // n
        gx = x0.reshape(-1)[vg] + off % wxf
        gy = y0.reshape(-1)[vg] + off // wxf
        i_unit = unit_of_tile[tile_base[ix_vu] + gy * tw[ix_vu] + gx]
        keep = i_unit >= 0
        vg, i_unit = vg[keep], i_unit[keep]
        # depth order (stable: ties keep Gaussian order), then group by unit (stable)
        depth = proj.depths.detach().reshape(-1).cpu()[vg]
        order = torch.argsort(depth, stable=True)
        vg, i_unit = vg[order], i_unit[order]
        order = torch.argsort(i_unit, stable=True)
        vg, i_unit = vg[order], i_unit[order]
        k_count = torch.bincount(i_unit, minlength=n_units)

    # ---- per-(view, Gaussian) values used by the compositing, flattened [Vu*N]
    m2d = proj.means2d.reshape(-1, 2)
    quad = proj.quad.reshape(-1, 3)
    opa = opacities.reshape(1, -1).expand(len(views_used), n).reshape(-1)

    # ---- per intersection: the pixel box inside its tile where alpha can reach 1/255
    # (sigma <= log(255 o) implies |dx| <= sqrt(2 log(255 o) cov_xx), likewise y; 1 px margin)
    with torch.no_grad():
        vg_d = vg.to(dev)
        i_unit_d = i_unit.to(dev)
        cov = proj.cov2d.detach().reshape(-1, 3)[vg_d]
        lg = torch.log(255.0 * opa.detach()[vg_d].clamp_min(1e-30).double()).clamp_min(0)
        ex = torch.sqrt(2 * lg * cov[:, 0].double()) + 1.0
        ey = torch.sqrt(2 * lg * cov[:, 2].double()) + 1.0
        mu = m2d.detach()[vg_d].double()
        ux0 = (u_gx.to(dev) * TILE_SIZE)[i_unit_d]
        uy0 = (u_gy.to(dev) * TILE_SIZE)[i_unit_d]
        big = float(2**40)
        bx0 = torch.ceil(mu[:, 0] - ex - 0.5).clamp(-big, big).long().maximum(ux0)
        bx1 = torch.floor(mu[:, 0] + ex - 0.5).clamp(-big, big).long().minimum(ux0 + TILE_SIZE - 1) + 1
        by0 = torch.ceil(mu[:, 1] - ey - 0.5).clamp(-big, big).long().maximum(uy0)
        by1 = torch.floor(mu[:, 1] + ey - 0.5).clamp(-big, big).long().minimum(uy0 + TILE_SIZE - 1) + 1
        bw = (bx1 - bx0).clamp(min=0)
        bh = (by1 - by0).clamp(min=0)
        # each box's rows (none where it is empty or alpha cannot reach 1/255); chunks of whole units
        # (segments never cross units) of at most ~max_pairs lanes: 16 per box row
        box_rows = torch.where((lg > 0) & (bw > 0), bh, torch.zeros_like(bh))
        unit_pairs = torch.zeros(n_units, dtype=torch.long, device=dev).index_add_(0, i_unit_d, box_rows * TILE_SIZE)
        unit_pairs = unit_pairs.cpu()
        unit_end = torch.cumsum(unit_pairs, 0)
        k_end = torch.cumsum(k_count, 0)
        wanted_d = wanted.to(dev)

    all_wanted = bool(wanted.all())
    lx0_all = bx0 - ux0  # box origin inside its tile, 0..15
    ly0_all = by0 - uy0
    ux0_t = ux0.to(dtype) + 0.5
    uy0_t = uy0.to(dtype) + 0.5
    cols = torch.arange(TILE_SIZE, device=dev)
    cols_t = cols.to(dtype)
    T_q = torch.ones(n_units * _TILE_PIX, dtype=dtype, device=dev)
    e_q, e_vg, e_w = [], [], []
    u0 = 0
    while u0 < n_units:
        base = int(unit_end[u0 - 1]) if u0 > 0 else 0
        u1 = int(torch.searchsorted(unit_end, torch.tensor(base + max_pairs), right=True))
        u1 = min(max(u1, u0 + 1), n_units)
        i0 = int(k_end[u0 - 1]) if u0 > 0 else 0
        i1 = int(k_end[u1 - 1])
        q0 = u0 * _TILE_PIX
        u0 = u1
        if i1 == i0:
            continue
        # expand every intersection into the rows of its box, each row a 16-wide strip of its tile
        # whose columns past the box are masked: one gather per row, none per pixel
        with torch.no_grad():
            c_rows = box_rows[i0:i1]
            n_rows = int(c_rows.sum())
            if n_rows == 0:
                continue
            rep = torch.repeat_interleave(torch.arange(i1 - i0, device=dev), c_rows, output_size=n_rows)
            row_in_box = torch.arange(n_rows, device=dev) - (torch.cumsum(c_rows, 0) - c_rows)[rep]
            ints = torch.stack([lx0_all[i0:i1], ly0_all[i0:i1], bw[i0:i1], i_unit_d[i0:i1] * _TILE_PIX - q0,
                                vg_d[i0:i1]], 1)[rep]  # per row: box origin, width, unit base, Gaussian
            lx0, ly = ints[:, 0], ints[:, 1] + row_in_box
        gid_i = vg_d[i0:i1]
        qd_i = quad[gid_i]
        # per intersection: the mean minus the centre of its tile's first pixel, the form, the opacity
        per = torch.stack([m2d[gid_i, 0] - ux0_t[i0:i1], m2d[gid_i, 1] - uy0_t[i0:i1], qd_i[:, 0], qd_i[:, 1],
                           qd_i[:, 2], opa[gid_i]], 1)[rep]
        dy = per[:, 1] - ly.to(dtype)
        dx = per[:, 0, None] - (lx0.to(dtype)[:, None] + cols_t)  # [rows, 16]
        e = dx - (per[:, 3] * dy)[:, None]
        sigma = 0.5 * (per[:, 2, None] * e * e + (per[:, 4] * dy * dy)[:, None])
        alpha = torch.clamp(per[:, 5, None] * torch.exp(-sigma), max=ALPHA_MAX)
        with torch.no_grad():  # sigma is never negative in this form: alpha alone decides
            sel = torch.nonzero(((alpha >= ALPHA_MIN) & (cols < ints[:, 2, None])).reshape(-1)).squeeze(1)
            if sel.numel() == 0:
                continue
            # chunk-local unit-pixel of each entry (row = sel // 16, column = sel % 16)
            q = (ints[:, 3] + ly * TILE_SIZE + lx0)[sel >> 4] + (sel & (TILE_SIZE - 1))
            if not all_wanted:
                keep = torch.nonzero(wanted_d[q + q0]).squeeze(1)
                sel, q = sel[keep], q[keep]
                if sel.numel() == 0:
                    continue
            # group by unit-pixel; a stable sort keeps the depth order the pairs were made in
            q, order = torch.sort(q.int(), stable=True)
            sel = sel[order]
            q = q.long()
        alpha = alpha.reshape(-1)[sel]
        # front-to-back transmittance per unit-pixel: a product over each pixel's segment, laid out
        # as rows of padded matrices so that it is a plain sequential cumprod, as in gsplat
        with torch.no_grad():
            n_e = len(q)
            first = torch.ones(n_e, dtype=torch.bool, device=dev)
            first[1:] = q[1:] != q[:-1]
            start = torch.nonzero(first).squeeze(1)
            seg_len = torch.diff(start, append=start.new_tensor([n_e]))
            # rows padded to the next power of two of their length, one matrix per such width, the
            # matrices one after the other in one buffer (rows in segment order within each)
            width = torch.ones_like(seg_len)
            while bool((width < seg_len).any()):
                width = torch.where(width < seg_len, width * 2, width)
            by_width = torch.argsort(width, stable=True)
            w_sorted = width[by_width]
            row_base = torch.empty_like(width)
            row_base[by_width] = torch.cumsum(w_sorted, 0) - w_sorted
            seg = torch.cumsum(first, 0) - 1
            flat = (row_base - start)[seg] + torch.arange(n_e, device=dev)  # row base + position in segment
            widths, counts = torch.unique_consecutive(w_sorted, return_counts=True)
        F = torch.ones(int(w_sorted.sum()), dtype=dtype, device=dev).index_put((flat,), 1.0 - alpha)
        parts, at = [], 0
        for wd, n_seg in zip(widths.tolist(), counts.tolist()):
            parts.append(torch.cumprod(F[at:at + wd * n_seg].view(n_seg, wd), dim=1).reshape(-1))
            at += wd * n_seg
        cp = torch.cat(parts)
        t_incl = cp[flat]
        w = alpha * torch.where(first, torch.ones_like(t_incl), cp[(flat - 1).clamp(min=0)])
        with torch.no_grad():
            alive = t_incl > T_MIN  # a prefix of each segment
            last = alive.clone()  # each segment's last alive entry
            last[:-1] &= ~(alive[1:] & ~first[1:])
            last = torch.nonzero(last).squeeze(1)
        T_q = T_q.index_put((q[last] + q0,), t_incl[last])
        idx = torch.nonzero(alive).squeeze(1)
        e_q.append(q[idx] + q0)
        e_vg.append(ints[:, 4][sel[idx] >> 4])
        e_w.append(w[idx])

    # ---- transmittance of every output pixel
    pidx_d, p_q_d = pidx.to(dev), p_q.to(dev)
    trans = torch.ones(request.num_pixels, dtype=dtype, device=dev)
    trans = trans.index_put((pidx_d,), T_q[p_q_d])
    if not e_q:
        out = _empty(request, n, dtype, dev, valid)
        out.transmittance = trans
        return out

    # ---- entries (already grouped by unit-pixel, in depth order) joined to output pixels
    q = torch.cat(e_q)
    evg = torch.cat(e_vg)
    w = torch.cat(e_w)
    q_count = torch.bincount(q, minlength=n_units * _TILE_PIX)
    q_start = torch.cumsum(q_count, 0) - q_count
    c = q_count[p_q_d]
    total = int(c.sum())
    # entry k of output pixel j sits at q_start[p_q[j]] + k: each pixel's run of the output, shifted
    shift = q_start[p_q_d] - (torch.cumsum(c, 0) - c)
    sel = torch.arange(total, device=dev) + torch.repeat_interleave(shift, c, output_size=total)
    pixel = torch.repeat_interleave(pidx_d, c, output_size=total)
    evg, w = evg[sel], w[sel]

    # ---- distinct (view, Gaussian) pairs, sorted by view * N + gaussian (views_used is sorted, so
    # the flat (used view, Gaussian) id has the same order)
    present = torch.zeros(len(views_used) * n, dtype=torch.bool, device=dev)
    present[evg] = True
    pair_vg = torch.nonzero(present).squeeze(1)
    pair_of = torch.cumsum(present, 0) - 1
    pair = pair_of[evg]
    pair_view = views_used.to(dev)[pair_vg // n]
    pair_gaussian = pair_vg % n
    pair_depth = proj.depths.reshape(-1)[pair_vg]
    return Contributions(
        request=request,
        num_gaussians=n,
        pair_view=pair_view,
        pair_gaussian=pair_gaussian,
        pair_depth=pair_depth,
        pixel=pixel,
        pair=pair,
        weight=w,
        transmittance=trans,
        valid=valid,
    )
