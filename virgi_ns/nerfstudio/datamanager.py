"""Multi-view tile batches for the colour stage.

Each colour-stage step fills a pixel budget with mini-batches. A multi-view mini-batch picks one
anchor Gaussian (opaque ones, uniformly), up to ``views_per_anchor`` training views whose image
holds the anchor's projection (in front of the camera, inside the frame; occlusion is not
checked), and cuts a ``tile_size`` square centred on the projection in each (shifted to stay
inside the image). The single-view mode (the ablation's baseline) spends the same budget on
tiles around anchors of one randomly chosen view per step.

During the geometry stage the manager behaves as nerfstudio's :class:`FullImageDatamanager`
(one whole image per step).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Type

import torch
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from torch import Tensor

from virgi_ns.nerfstudio.cameras import raster_cameras
from virgi_ns.raster import Cameras, Request

GRID = 16  # the rasterizer's tile grid (gsplat's tile size)

@dataclass
class TileBatch:
    """What the model renders in a colour-stage step: ``request`` items on ``cameras`` (all
    training views, indexed by ``request.views``)."""

    cameras: Cameras
    request: Request

    def to(self, device) -> "TileBatch":  # nerfstudio moves inputs with .to(); cameras move here
        return TileBatch(self.cameras.to(device), self.request)


@dataclass
class VirgiDataManagerConfig(FullImageDatamanagerConfig):
    _target: Type = field(default_factory=lambda: VirgiDataManager)
    tile_size: int = 32
    """Side of a training tile in pixels."""
    views_per_anchor: int = 5
    """Tiles (views) per multi-view mini-batch."""
    pixel_budget: int = 163840
    """Pixels per colour-stage step (filled with whole mini-batches; at least one)."""
    batch_mode: Literal["multiview", "singleview"] = "multiview"
    """Multi-view mini-batches around shared anchors, or all tiles from one view per step."""
    min_anchor_opacity: float = 0.5
    """Anchors are drawn among Gaussians at least this opaque (all of them if none is)."""


def _gather_tiles(stack: Tensor, request: Request, valid: Tensor) -> Tensor:
    """Ground-truth pixels [T,s,s,C] of the request's tiles from the training images stacked as
    [V,H_max,W_max,C] (zeros where ``valid`` [P] is False: outside the tile's image), in one
    gather."""
    dev = stack.device
    s_h, s_w = request.height, request.width
    views = request.views.to(dev)
    ys = (request.y0.to(dev)[:, None] + torch.arange(s_h, device=dev)).clamp(0, stack.shape[1] - 1)
    xs = (request.x0.to(dev)[:, None] + torch.arange(s_w, device=dev)).clamp(0, stack.shape[2] - 1)
    out = stack[views[:, None, None], ys[:, :, None], xs[:, None, :]]  # [T,s_h,s_w,C]
    inside = valid.to(dev).reshape(len(request), s_h, s_w, 1)
    return torch.where(inside, out, torch.zeros((), dtype=out.dtype, device=dev))


def sample_tiles(
    means: Tensor,
    anchor_pool: Tensor,
    cameras: Cameras,
    tile_size: int,
    views_per_anchor: int,
    pixel_budget: int,
    mode: str = "multiview",
    generator: torch.Generator | None = None,
) -> Request:
    """Pick tiles for one step (see the module doc). ``anchor_pool``: indices of candidate anchors."""
    dev = means.device
    g = generator
    tile_px = tile_size * tile_size
    if mode == "multiview":
        n_mini = max(1, pixel_budget // (views_per_anchor * tile_px))
        n_try = n_mini * 2 + 8
    else:
        n_mini = max(1, pixel_budget // tile_px)
        n_try = n_mini * 2 + 8
    pick = anchor_pool[torch.randint(len(anchor_pool), (n_try,), generator=g).to(anchor_pool.device)]
    pts = means[pick.to(dev)].float()  # [A,3]
    n_views = len(cameras)
    every_view = torch.arange(n_views, device=dev).repeat(len(pts))  # (anchor, view) pairs, anchor-major
    uv, vis = cameras.project_points(pts.repeat_interleave(n_views, 0), every_view)
    vis = vis.view(-1, n_views).cpu()  # [A,V]
    u, v = uv[:, 0].view(-1, n_views).cpu(), uv[:, 1].view(-1, n_views).cpu()
    Wc, Hc = cameras.widths, cameras.heights

    def origin(a: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        # centred on the projection, snapped to the rasterizer's 16-px grid (fewer grid tiles to
        # bin per request tile; the anchor stays within 8 px of the tile's centre)
        x0 = (torch.round((u[a, view] - tile_size / 2) / GRID) * GRID).long()
        y0 = (torch.round((v[a, view] - tile_size / 2) / GRID) * GRID).long()
        x0 = torch.minimum(x0, Wc[view] - tile_size).clamp_min(0)
        y0 = torch.minimum(y0, Hc[view] - tile_size).clamp_min(0)
        return x0, y0

    if mode == "multiview":
        score = torch.rand(vis.shape, generator=g) + vis.float()  # visible views score in [1, 2)
        k = min(views_per_anchor, vis.shape[1])
        top = score.topk(k, dim=1)
        ok_anchor = vis.any(dim=1).nonzero().flatten()[:n_mini]
        if len(ok_anchor) == 0:  # nothing visible anywhere: fall back to image centres
            return Request.tiles(torch.arange(len(cameras))[:views_per_anchor],
                                 (Wc[:views_per_anchor] - tile_size).clamp_min(0) // 2,
                                 (Hc[:views_per_anchor] - tile_size).clamp_min(0) // 2, tile_size)
        # each anchor's visible views among its top scores, anchor by anchor, best score first
        idx = top.indices[ok_anchor]  # [A,k]
        keep = top.values[ok_anchor] >= 1.0
        views = idx[keep]
        x0, y0 = origin(ok_anchor[:, None].expand_as(idx)[keep], views)
        return Request.tiles(views, x0, y0, tile_size)

    # single view: one random view with visible anchors
    counts = vis.sum(0)
    cand = (counts > 0).nonzero().flatten()
    if len(cand) == 0:
        view = torch.randint(len(cameras), (1,), generator=g)
        return Request.tiles(view, (Wc[view] - tile_size).clamp_min(0) // 2,
                             (Hc[view] - tile_size).clamp_min(0) // 2, tile_size)
    view = cand[torch.randint(len(cand), (1,), generator=g)]
    a = vis[:, view[0]].nonzero().flatten()[:n_mini]
    vv = view.expand(len(a))
    x0, y0 = origin(a, vv)
    return Request.tiles(vv, x0, y0, tile_size)


def views_of_process(request: Request, rank: int, world: int) -> Request:
    """The tiles of ``request`` on every ``world``-th of its distinct views, from the ``rank``-th:
    the processes' shares of one batch. Split by view, so a (view, Gaussian) pair falls in one
    share only and the shares' pair counts add up to the batch's."""
    uniq = request.views.unique()
    mine = torch.isin(request.views, uniq[rank::world])
    return Request(request.views[mine], request.x0[mine], request.y0[mine], request.width, request.height)


def _stack_images(cached: list[dict]) -> Tensor:
    """Stack the cached images [V,H_max,W_max,C] (zero padded) and make each cache entry a view
    into the stack, so the images are held once (each original is released as it is copied; a
    pinned cache stays pinned)."""
    shapes = [tuple(c["image"].shape) for c in cached]
    H = max(s[0] for s in shapes)
    W = max(s[1] for s in shapes)
    first = cached[0]["image"]
    pinned = first.device.type == "cpu" and first.is_pinned()
    stack = torch.zeros((len(cached), H, W, shapes[0][2]), dtype=first.dtype, device=first.device,
                        pin_memory=pinned)
    for k, c in enumerate(cached):
        h, w = shapes[k][:2]
        stack[k, :h, :w] = c["image"]
        c["image"] = stack[k, :h, :w]
    return stack


class VirgiDataManager(FullImageDatamanager):
    """Whole images while geometry trains; multi-view tile batches for the colour field."""

    config: VirgiDataManagerConfig

    def __init__(self, config: VirgiDataManagerConfig, *args, **kwargs) -> None:
        super().__init__(config, *args, **kwargs)
        self._raster_cams: Cameras | None = None
        self._image_stack: Tensor | None = None
        self._generator = torch.Generator().manual_seed(0)
        self._rank, self._world, self._shared_tiles = 0, 1, False  # see split_over_processes
        # the frame an imported capture-frame splat must be moved into, for the model; nerfstudio's
        # COLMAP parser already folds its world-axis swap into dataparser_transform
        T = self.train_dataparser_outputs.dataparser_transform.float()
        capture = T[:3, :4].clone()
        meta = self.train_dataset.metadata
        meta["virgi_capture_transform"] = capture
        meta["virgi_capture_scale"] = float(self.train_dataparser_outputs.dataparser_scale)

    def split_over_processes(self, rank: int, world: int, shared_tiles: bool) -> None:
        """Draw this process's share of each step's batch, ``rank`` of ``world``. Geometry: every
        process walks the same seeded camera order and takes its own consecutive views of each
        step (:meth:`next_train_views`). Colour: with ``shared_tiles`` every process draws the
        same batch of ``pixel_budget`` pixels and keeps the tiles of its views
        (:func:`views_of_process`); otherwise each draws ``pixel_budget / world`` pixels of its
        own, from a generator seeded with its rank (rank 0 draws what one process would)."""
        self._rank, self._world, self._shared_tiles = rank, world, shared_tiles
        if not shared_tiles:
            self._generator = torch.Generator().manual_seed(rank)

    def next_train_views(self, step: int, count: int) -> list[tuple]:
        """This process's (camera, batch) pairs of one geometry step of ``count`` views."""
        per = max(1, count // self._world)
        views = []
        for k in range(count):
            if k // per == self._rank:
                views.append(self.next_train(step))
            else:  # another process's view: only advance the camera order
                self.train_unseen_cameras.pop(0)
                if not self.train_unseen_cameras:
                    self.train_unseen_cameras = self.sample_train_cameras()
        return views

    # ------------------------------------------------------------------ colour stage
    def train_raster_cameras(self) -> Cameras:
        """All training views as rasterizer cameras (after undistortion), on the manager's device."""
        if self._raster_cams is None:
            cached = self.cached_train  # undistorts and fixes the cameras' intrinsics first
            self._image_stack = _stack_images(cached)
            self._raster_cams = raster_cameras(self.train_dataset.cameras).to(self.device)
        return self._raster_cams

    def train_images(self) -> list[Tensor]:
        """The training images (views into :meth:`train_image_stack`)."""
        self.train_raster_cameras()
        return [c["image"] for c in self.cached_train]

    def train_image_stack(self) -> Tensor:
        """The training images as one [V,H_max,W_max,C] tensor (zero padded), where they are cached."""
        self.train_raster_cameras()
        assert self._image_stack is not None
        return self._image_stack

    def next_tile_batch(self, step: int, means: Tensor, opacities: Tensor) -> tuple[TileBatch, dict]:
        """One colour-stage batch: the tiles and their ground truth (``image`` [T,s,s,3] float in
        [0,1], ``valid`` [T,s,s] bool). ``means`` / ``opacities`` (sigmoided) are the frozen geometry."""
        cams = self.train_raster_cameras()
        with torch.no_grad():
            pool = (opacities.reshape(-1) >= self.config.min_anchor_opacity).nonzero().flatten()
            if len(pool) == 0:
                pool = torch.arange(means.shape[0], device=means.device)
            budget = self.config.pixel_budget
            if not self._shared_tiles:
                budget //= self._world
            req = sample_tiles(means, pool, cams, self.config.tile_size, self.config.views_per_anchor,
                               budget, self.config.batch_mode, self._generator)
            if self._shared_tiles and self._world > 1:
                req = views_of_process(req, self._rank, self._world)
        stack = self.train_image_stack()
        valid = req.valid_mask(cams, stack.device)  # where the images are: no per-pixel work on the host
        gt = _gather_tiles(stack, req, valid)
        if gt.dtype == torch.uint8:
            gt = gt.float() / 255.0
        gt = gt.to(self.device)
        s = req.height
        return TileBatch(cams, req), {"image": gt, "valid": valid.reshape(len(req), s, req.width).to(self.device)}
