"""The rasterizer contract shared by every backend.

With geometry frozen, a rendered pixel is a fixed weighted sum of Gaussian colours::

    pixel(p) = sum_k w_pk * C[g_pk] + T_p * background,     w = T * alpha

so a backend's only job is to say who contributes to which pixel with which weight
(:class:`Contributions`). :func:`composite` then turns colours into pixels with plain torch
autograd, on any device. Nothing here knows of nerfstudio.

Conventions (gsplat 1.4.0, classic mode): cameras are pinhole with OpenCV axes (x right,
y down, z forward); ``viewmats`` are world-to-camera; pixel centres at (x + 0.5, y + 0.5).

A :class:`Request` is a list of equally sized rectangles ("items"), each on one view: whole
images (origin 0, the image's size) or tiles (16, 32 or 64 px, any position; pixels that fall
outside the image are marked invalid and get no contributions). The output pixel of item ``i``
at row ``r``, column ``c`` has the flat index ``p = (i * height + r) * width + c``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Cameras:
    """V pinhole cameras. ``Ks`` [V,3,3], ``viewmats`` [V,4,4] world-to-camera (OpenCV axes),
    ``widths`` / ``heights`` [V] integer image sizes."""

    Ks: Tensor
    viewmats: Tensor
    widths: Tensor
    heights: Tensor

    def __post_init__(self) -> None:
        v = self.Ks.shape[0]
        if self.Ks.shape != (v, 3, 3) or self.viewmats.shape != (v, 4, 4):
            raise ValueError(f"Cameras: Ks {tuple(self.Ks.shape)} / viewmats {tuple(self.viewmats.shape)}")
        self.widths = torch.as_tensor(self.widths, dtype=torch.long).reshape(-1).expand(v).cpu().clone()
        self.heights = torch.as_tensor(self.heights, dtype=torch.long).reshape(-1).expand(v).cpu().clone()

    def __len__(self) -> int:
        return int(self.Ks.shape[0])

    @staticmethod
    def from_params(fx, fy, cx, cy, viewmats: Tensor, width, height) -> "Cameras":
        """Cameras from intrinsics (scalars or [V] tensors) and [V,4,4] world-to-camera matrices."""
        v = viewmats.shape[0]
        K = torch.zeros(v, 3, 3, dtype=viewmats.dtype, device=viewmats.device)
        K[:, 0, 0] = torch.as_tensor(fx, dtype=viewmats.dtype)
        K[:, 1, 1] = torch.as_tensor(fy, dtype=viewmats.dtype)
        K[:, 0, 2] = torch.as_tensor(cx, dtype=viewmats.dtype)
        K[:, 1, 2] = torch.as_tensor(cy, dtype=viewmats.dtype)
        K[:, 2, 2] = 1
        return Cameras(K, viewmats, width, height)

    def to(self, device=None, dtype=None) -> "Cameras":
        return Cameras(self.Ks.to(device, dtype), self.viewmats.to(device, dtype), self.widths, self.heights)

    def index(self, idx) -> "Cameras":
        idx = torch.as_tensor(idx, dtype=torch.long).reshape(-1)
        return Cameras(self.Ks[idx.to(self.Ks.device)], self.viewmats[idx.to(self.Ks.device)],
                       self.widths[idx], self.heights[idx])

    def camera_centers(self) -> Tensor:
        """[V,3] camera centres in world coordinates."""
        R = self.viewmats[:, :3, :3]
        t = self.viewmats[:, :3, 3]
        return -(R.transpose(1, 2) @ t[:, :, None])[:, :, 0]

    def project_points(self, points: Tensor, views: Tensor, near: float = 0.01) -> tuple[Tensor, Tensor]:
        """Point ``points[i]`` [B,3] seen by view ``views[i]`` [B]: its pixel position [B,2]
        (pixel-edge coordinates, pinhole, no skew) and whether it lies in front of the camera
        (depth > ``near``) and inside the image, ``[0, W) x [0, H)`` [B]. Occlusion is not checked."""
        vm = self.viewmats.to(points)[views]
        K = self.Ks.to(points)[views]
        pc = torch.einsum("bij,bj->bi", vm[:, :3, :3], points) + vm[:, :3, 3]
        z = pc[:, 2]
        zs = z.clamp_min(1e-6)
        u = K[:, 0, 0] * pc[:, 0] / zs + K[:, 0, 2]
        v = K[:, 1, 1] * pc[:, 1] / zs + K[:, 1, 2]
        W = self.widths.to(points)[views]
        H = self.heights.to(points)[views]
        return torch.stack([u, v], -1), (z > near) & (u >= 0) & (v >= 0) & (u < W) & (v < H)


@dataclass
class Request:
    """Equally sized rectangles on views: item i covers pixels [x0, x0+width) x [y0, y0+height)
    of view ``views[i]``."""

    views: Tensor  # [T] long
    x0: Tensor  # [T] long
    y0: Tensor  # [T] long
    width: int
    height: int

    def __post_init__(self) -> None:
        self.views = torch.as_tensor(self.views, dtype=torch.long).reshape(-1).cpu()
        self.x0 = torch.as_tensor(self.x0, dtype=torch.long).reshape(-1).cpu().expand(len(self.views)).clone()
        self.y0 = torch.as_tensor(self.y0, dtype=torch.long).reshape(-1).cpu().expand(len(self.views)).clone()
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Request: size {self.width}x{self.height}")

    def __len__(self) -> int:
        return int(self.views.shape[0])

    @property
    def num_pixels(self) -> int:
        return len(self) * self.width * self.height

    @staticmethod
    def whole_images(cameras: Cameras, views=None) -> "Request":
        """Whole images of ``views`` (all of them by default); they must share one size."""
        views = torch.arange(len(cameras)) if views is None else torch.as_tensor(views, dtype=torch.long).reshape(-1)
        w = cameras.widths[views].unique()
        h = cameras.heights[views].unique()
        if len(w) != 1 or len(h) != 1:
            raise ValueError("Request.whole_images: the requested views differ in size; request them separately")
        return Request(views, 0, 0, int(w[0]), int(h[0]))

    @staticmethod
    def tiles(views, x0, y0, size: int) -> "Request":
        return Request(views, x0, y0, size, size)

    def pixel_coords(self, device=None) -> tuple[Tensor, Tensor, Tensor]:
        """(view, x, y) of every output pixel, each [P] long, in output order, on ``device`` (the
        host by default)."""
        t = len(self)
        r = torch.arange(self.height, device=device).view(1, -1, 1)
        c = torch.arange(self.width, device=device).view(1, 1, -1)
        x = (self.x0.to(device).view(-1, 1, 1) + c).expand(t, self.height, self.width)
        y = (self.y0.to(device).view(-1, 1, 1) + r).expand(t, self.height, self.width)
        v = self.views.to(device).view(-1, 1, 1).expand(t, self.height, self.width)
        return v.reshape(-1), x.reshape(-1), y.reshape(-1)

    def valid_mask(self, cameras: Cameras, device=None) -> Tensor:
        """[P] bool on ``device`` (the host by default): the output pixel lies inside its view's image."""
        v, x, y = self.pixel_coords(device)
        return (x >= 0) & (y >= 0) & (x < cameras.widths.to(device)[v]) & (y < cameras.heights.to(device)[v])


@dataclass
class Contributions:
    """Who contributes to which pixel, for one :class:`Request`.

    ``pair_view`` / ``pair_gaussian`` [U]: the distinct (view, Gaussian) pairs that contribute
    anywhere in the request (sorted by ``view * N + gaussian``); colours are given per pair, so
    a caller evaluates its colour model only for these. ``pair_depth`` [U]: camera-space z.

    ``pixel`` [M], ``pair`` [M], ``weight`` [M]: one entry per (pixel, contributing Gaussian),
    ``weight = T * alpha``; entries are grouped by pixel (ascending) and, within a pixel, in
    front-to-back compositing order. ``transmittance`` [P]: each pixel's final T (1 for invalid
    pixels). ``valid`` [P]: the pixel lies inside its image.

    ``weight`` carries autograd history to the geometry when the backend supports it (the
    reference does); everything else is integer bookkeeping.
    """

    request: Request
    num_gaussians: int
    pair_view: Tensor
    pair_gaussian: Tensor
    pair_depth: Tensor
    pixel: Tensor
    pair: Tensor
    weight: Tensor
    transmittance: Tensor
    valid: Tensor

    @property
    def num_pixels(self) -> int:
        return self.request.num_pixels

    @property
    def shape(self) -> tuple[int, int, int]:
        return len(self.request), self.request.height, self.request.width

    @property
    def num_entries(self) -> int:
        """M, the number of (pixel, Gaussian) entries."""
        return int(self.weight.numel())

    def gaussian(self) -> Tensor:
        """[M] Gaussian index of each entry."""
        return self.pair_gaussian[self.pair]

    def gather(self, per_gaussian: Tensor) -> Tensor:
        """Per-Gaussian values [N, ...] -> per-pair values [U, ...]. ``index_select``: its gradient
        is an ``index_add_`` (atomics), where advanced indexing's sorts the indices first."""
        return per_gaussian.index_select(0, self.pair_gaussian.to(per_gaussian.device))

    def accumulation(self) -> Tensor:
        """[T,h,w] opacity (1 - final transmittance)."""
        return (1.0 - self.transmittance).reshape(self.shape)

    def composite(self, colours: Tensor, background: Tensor | float | None = None) -> Tensor:
        """What :func:`composite` computes; a backend's subclass may override it with a fused
        version of the same function (the plain torch path is :func:`composite_plain`)."""
        return composite_plain(colours, self, background)


def composite(colours: Tensor, contrib: Contributions, background: Tensor | float | None = None) -> Tensor:
    """Per-pair colours [U, D] -> images [T, h, w, D]. Differentiable in ``colours`` (and in the
    weights, where they carry history). ``background`` is a [D] vector, a scalar, or None (0).
    Defers to ``contrib.composite``, so a backend's lists can use its fused kernels."""
    return contrib.composite(colours, background)


def composite_plain(colours: Tensor, contrib: Contributions, background: Tensor | float | None = None) -> Tensor:
    """:func:`composite` in plain torch (gather + ``index_add``), for any backend's lists."""
    if colours.shape[0] != contrib.pair_view.shape[0]:
        raise ValueError(f"composite: {colours.shape[0]} colours for {contrib.pair_view.shape[0]} pairs")
    d = colours.shape[1]
    w = contrib.weight.to(colours.dtype)
    vals = colours.index_select(0, contrib.pair) * w[:, None]
    out = colours.new_zeros(contrib.num_pixels, d).index_add(0, contrib.pixel, vals)
    if background is not None:
        bg = torch.as_tensor(background, dtype=colours.dtype, device=colours.device).reshape(1, -1)
        out = out + contrib.transmittance.to(colours.dtype)[:, None] * bg
    t, h, wd = contrib.shape
    return out.reshape(t, h, wd, d)


def composite_depth(contrib: Contributions, eps: float = 1e-10) -> Tensor:
    """Expected depth [T,h,w,1]: sum(w z) / sum(w), 0 where nothing contributes."""
    num = composite(contrib.pair_depth[:, None], contrib)
    return expected_depth(num, contrib.accumulation()[..., None].to(num.dtype), eps)


def expected_depth(weighted_depth: Tensor, accumulation: Tensor, eps: float = 1e-10) -> Tensor:
    """``sum(w z) / sum(w)`` from its two composites (same shapes), 0 where nothing contributes;
    for callers that composite depth together with other channels."""
    return torch.where(accumulation > eps, weighted_depth / accumulation.clamp_min(eps), torch.zeros_like(weighted_depth))
