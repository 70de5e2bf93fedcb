"""The colour stage's batch pieces: ground truth cut from the stacked training images, and the
multi-view tile sampler."""

from __future__ import annotations

import torch

from virgi_ns.nerfstudio.datamanager import GRID, _gather_tiles, _stack_images, sample_tiles
from virgi_ns.raster import Cameras, Request


def _cameras(sizes: list[tuple[int, int]]) -> Cameras:
    v = len(sizes)
    K = torch.tensor([[50.0, 0, 0], [0, 50.0, 0], [0, 0, 1]]).repeat(v, 1, 1)
    K[:, 0, 2] = torch.tensor([w / 2 for _, w in sizes])
    K[:, 1, 2] = torch.tensor([h / 2 for h, _ in sizes])
    vm = torch.eye(4).repeat(v, 1, 1)
    vm[:, 2, 3] = 4.0  # the origin sits 4 units in front of every camera
    vm[:, 0, 3] = torch.linspace(-0.5, 0.5, v)
    return Cameras(K, vm, torch.tensor([w for _, w in sizes]), torch.tensor([h for h, _ in sizes]))


def test_tiles_cut_from_stacked_images_of_different_sizes():
    sizes = [(40, 56), (33, 64), (48, 48)]
    g = torch.Generator().manual_seed(0)
    images = [torch.randint(0, 256, (h, w, 3), generator=g, dtype=torch.uint8) for h, w in sizes]
    cached = [{"image": im.clone()} for im in images]
    stack = _stack_images(cached)
    assert stack.shape == (3, 48, 64, 3)
    for c, im in zip(cached, images):  # the cache now holds views into the stack, same pixels
        assert torch.equal(c["image"], im) and c["image"].data_ptr() >= stack.data_ptr()
    cams = _cameras(sizes)
    # inside, across every border, wholly outside, on a padded image's edge
    req = Request.tiles(torch.tensor([0, 0, 1, 1, 2, 2, 1]), torch.tensor([8, -5, 50, 20, 40, 100, 0]),
                        torch.tensor([4, -7, 25, 10, 40, 0, 30]), 16)
    valid = req.valid_mask(cams)
    out = _gather_tiles(stack, req, valid)
    assert out.shape == (7, 16, 16, 3) and out.dtype == torch.uint8
    for t in range(len(req)):  # per-pixel loop, independent of the gather
        v, x0, y0 = int(req.views[t]), int(req.x0[t]), int(req.y0[t])
        h, w = sizes[v]
        for r in range(16):
            for c in range(16):
                y, x = y0 + r, x0 + c
                want = images[v][y, x] if 0 <= y < h and 0 <= x < w else torch.zeros(3, dtype=torch.uint8)
                assert torch.equal(out[t, r, c], want), (t, r, c)
    assert int(valid.sum()) < valid.numel()  # the request did cross borders


def test_multiview_tiles_share_their_anchor_and_stay_inside():
    sizes = [(96, 128)] * 6
    cams = _cameras(sizes)
    g = torch.Generator().manual_seed(1)
    means = torch.randn(200, 3, generator=g) * 0.3
    pool = torch.arange(200)
    tile = 32
    req = sample_tiles(means, pool, cams, tile, views_per_anchor=4, pixel_budget=4 * tile * tile * 3, generator=g)
    assert len(req) == 12  # three mini-batches of four views (every anchor is visible everywhere)
    assert req.height == req.width == tile
    w = cams.widths[req.views]
    h = cams.heights[req.views]
    assert ((req.x0 >= 0) & (req.y0 >= 0) & (req.x0 + tile <= w) & (req.y0 + tile <= h)).all()
    assert ((req.x0 % GRID == 0) | (req.x0 == w - tile)).all()
    for m in range(3):  # each mini-batch: four distinct views
        assert len(set(req.views[4 * m : 4 * m + 4].tolist())) == 4
    # the same generator state gives the same tiles
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    a = sample_tiles(means, pool, cams, tile, 4, 4 * tile * tile * 3, generator=g1)
    b = sample_tiles(means, pool, cams, tile, 4, 4 * tile * tile * 3, generator=g2)
    assert torch.equal(a.views, b.views) and torch.equal(a.x0, b.x0) and torch.equal(a.y0, b.y0)


def test_each_tile_holds_its_anchor_projection():
    """With one anchor in the pool every tile of the batch is cut around its projection."""
    sizes = [(96, 128)] * 5
    cams = _cameras(sizes)
    means = torch.tensor([[0.1, -0.05, 0.2]])
    req = sample_tiles(means, torch.tensor([0]), cams, 32, views_per_anchor=5, pixel_budget=5 * 32 * 32)
    assert len(req) == 5 and sorted(req.views.tolist()) == [0, 1, 2, 3, 4]
    p = torch.einsum("vij,j->vi", cams.viewmats[:, :3, :3], means[0]) + cams.viewmats[:, :3, 3]
    u = cams.Ks[:, 0, 0] * p[:, 0] / p[:, 2] + cams.Ks[:, 0, 2]
    v = cams.Ks[:, 1, 1] * p[:, 1] / p[:, 2] + cams.Ks[:, 1, 2]
    u, v = u[req.views], v[req.views]
    assert ((u >= req.x0) & (u < req.x0 + 32) & (v >= req.y0) & (v < req.y0 + 32)).all()
