"""Made-up scenes the benchmarks time the engine on."""

from __future__ import annotations

import math

import torch


@torch.no_grad()
def million_scene(n: int = 1_000_000, width: int = 1280, height: int = 720, device: str = "cuda") -> tuple:
    """(scene, one-view cameras): ``n`` random Gaussians (seeded) filling a ``width`` x ``height`` view,
    with a random colour field (its specular head too)."""
    from virgi_ns.colour.field import ColourFieldConfig, DecoupledColourField
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.raster import Cameras

    dev = torch.device(device)
    g = torch.Generator(device=dev).manual_seed(0)
    f = 0.9 * width
    z = 2.0 + 6.0 * torch.rand(n, generator=g, device=dev)
    x = (torch.rand(n, generator=g, device=dev) - 0.5) * z * width / f * 1.1
    y = (torch.rand(n, generator=g, device=dev) - 0.5) * z * height / f * 1.1
    means = torch.stack([x, y, z], -1)
    scales = torch.exp(math.log(0.004) + math.log(8.0) * torch.rand(n, 3, generator=g, device=dev))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, device=dev), dim=-1)
    opac = 0.3 + 0.7 * torch.rand(n, generator=g, device=dev)
    field_ = DecoupledColourField(ColourFieldConfig(log2_hashmap_size=19 if n > 100_000 else 12),
                                 torch.tensor([[-6.0, -4.0, 1.5], [6.0, 4.0, 8.5]])).to(dev)
    torch.nn.init.normal_(field_.spec_l3.weight, std=0.1)
    cams = Cameras.from_params(f, f, width / 2, height / 2, torch.eye(4, device=dev)[None], width, height)
    return FrozenScene(means, quats, scales, opac, field_, torch.zeros(3, device=dev)), cams
