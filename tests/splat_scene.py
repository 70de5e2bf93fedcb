"""A small synthetic splat for the splat dataparser's tests: two coloured objects (a red ball and a
blue box, a few thousand Gaussians), the box with a weak view-dependent (degree-1) sheen, written as
an INRIA .ply in a frame of its own (shifted, in units of ten)."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.io import save_ply

RED = (0.8, 0.15, 0.1)
BLUE = (0.1, 0.25, 0.8)
CENTRE = (3.0, -2.0, 5.0)
UNIT = 10.0


def make_splat(n_per_object: int = 1500, seed: int = 0) -> tuple[Gaussians, torch.Tensor]:
    """(Gaussians, bool [N] True on the red ball). The ball sits at -x, the box at +x."""
    gen = torch.Generator().manual_seed(seed)
    ball = torch.nn.functional.normalize(torch.randn(n_per_object, 3, generator=gen), dim=-1) * 0.35
    ball = ball + torch.tensor([-0.55, 0.0, 0.0])
    # the box's surface: a random face per point, uniform on it
    face = torch.randint(6, (n_per_object,), generator=gen)
    uv = torch.rand(n_per_object, 2, generator=gen) * 0.6 - 0.3
    box = torch.zeros(n_per_object, 3)
    axis = face // 2
    sign = (face % 2).float() * 2 - 1
    for a in range(3):
        others = [b for b in range(3) if b != a]
        sel = axis == a
        box[sel, a] = 0.3 * sign[sel]
        box[sel, others[0]] = uv[sel, 0]
        box[sel, others[1]] = uv[sel, 1]
    box = box + torch.tensor([0.55, 0.0, 0.0])
    means = torch.cat([ball, box]) * UNIT + torch.tensor(CENTRE)
    n = means.shape[0]
    red = torch.zeros(n, dtype=torch.bool)
    red[:n_per_object] = True
    albedo = torch.where(red[:, None], torch.tensor(RED), torch.tensor(BLUE))
    sh = torch.zeros(n, 4, 3)
    sh[:, 0] = (albedo - 0.5) / SH_C0
    sh[~red, 2] = 0.15  # the box brightens a little seen along one axis
    g = Gaussians(means=means, scales=torch.full((n, 3), math.log(0.05 * UNIT)),
                  quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
                  opacities=torch.full((n,), 4.0), sh=sh)
    return g, red


def write_splat(path: Path, **kwargs) -> tuple[Gaussians, torch.Tensor]:
    g, red = make_splat(**kwargs)
    save_ply(g, path)
    return g, red
