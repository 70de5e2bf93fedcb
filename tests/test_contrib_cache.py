"""The contribution cache serves exactly what the rasterizer returns for the same request."""

from __future__ import annotations

import torch

from virgi_ns.nerfstudio.contrib_cache import ContributionCache
from virgi_ns.raster import Request, composite
from virgi_ns.raster.reference import rasterize

from virgi_scene import make_scene


def test_cached_tiles_equal_rasterized_tiles(tmp_path):
    sc = make_scene(tmp_path, n_per_sphere=60, views=6, width=48, height=40)
    g = sc.gaussians
    args = (g.means, g.quats, torch.exp(g.scales), torch.sigmoid(g.opacities))
    calls = []

    def raster(cams, req):
        calls.append(len(req))
        return rasterize(*args, cams, req)

    cache = ContributionCache(sc.cameras, len(g), raster)
    assert len(calls) == 6 and cache.num_entries > 0
    gen = torch.Generator().manual_seed(1)
    # tiles on several views, some hanging over the image border, one view twice
    views = torch.tensor([3, 0, 5, 3, 1])
    x0 = torch.randint(-8, 40, (5,), generator=gen)
    y0 = torch.randint(-8, 32, (5,), generator=gen)
    req = Request.tiles(views, x0, y0, 16)
    got = cache.contributions(req, g.means)
    want = rasterize(*args, sc.cameras, req)
    for name in ("pair_view", "pair_gaussian", "pixel", "pair", "valid"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
    torch.testing.assert_close(got.weight, want.weight.detach())
    torch.testing.assert_close(got.transmittance, want.transmittance.detach())
    torch.testing.assert_close(got.pair_depth, want.pair_depth.detach(), rtol=1e-5, atol=1e-5)
    colours = torch.rand(len(got.pair_gaussian), 3, generator=gen)
    torch.testing.assert_close(composite(colours, got, 0.3), composite(colours, want, 0.3).detach())
    # the cache knows its cameras
    assert cache.matches(sc.cameras) and not cache.matches(sc.cameras.index([0, 1]))
