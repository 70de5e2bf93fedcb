"""A tiny procedural scene with known albedo for the edit tests.

Three spheres of Gaussians, z up: a glossy blue one at the origin (a Phong lobe added before the
sigmoid, so its highlight is near-white), a matte green one and a matte yellow one. Eight
cameras on a ring look at the origin. The colour field is fitted briefly and directly to the
known per-Gaussian ``c_d = logit(albedo)`` and per-(view, Gaussian) ``c_s`` (no rendering), which
takes a second or two on a CPU.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Iterator

import torch

from virgi_ns.colour.field import ColourFieldConfig, DecoupledColourField, view_directions
from virgi_ns.edit.scene import FrozenScene
from virgi_ns.raster import Cameras

BLUE, GREEN, YELLOW = 0, 1, 2
ALBEDO = torch.tensor([[0.10, 0.20, 0.80], [0.15, 0.70, 0.20], [0.80, 0.75, 0.15]])
CENTRES = torch.tensor([[0.0, 0.0, 0.0], [1.25, 0.4, 0.0], [-1.25, 0.4, 0.0]])
RADII = (0.5, 0.4, 0.4)
LIGHT = torch.nn.functional.normalize(torch.tensor([0.0, -1.0, 1.2]), dim=0)
SPEC_GAIN, SPEC_POWER = 8.0, 4.0
W, H, F = 64, 48, 58.0


@dataclass
class EditScene:
    scene: FrozenScene
    cameras: Cameras
    labels: torch.Tensor  # [N] object id per Gaussian
    normals: torch.Tensor  # [N,3]


def look_at(eye: torch.Tensor, target: torch.Tensor, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target``."""
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor(up)), dim=0)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    M = torch.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    return M


def ring_cameras(n: int = 8, radius: float = 4.0, height: float = 1.2) -> Cameras:
    mats = []
    for i in range(n):
        a = -math.pi / 2 + 2 * math.pi * i / n  # view 0 looks along +y at the fronts
        eye = torch.tensor([radius * math.cos(a), radius * math.sin(a), height])
        mats.append(look_at(eye, torch.zeros(3)))
    return Cameras.from_params(F, F, W / 2, H / 2, torch.stack(mats), W, H)


def specular_logit(means: torch.Tensor, normals: torch.Tensor, labels: torch.Tensor, centre: torch.Tensor,
                   glossy: int = BLUE) -> torch.Tensor:
    """The true pre-sigmoid specular term [N] for a camera at ``centre`` (the ``glossy`` sphere only)."""
    v = torch.nn.functional.normalize(centre - means, dim=-1)
    refl = 2 * (normals @ LIGHT)[:, None] * normals - LIGHT
    s = SPEC_GAIN * torch.clamp((refl * v).sum(-1), min=0) ** SPEC_POWER
    return torch.where(labels == glossy, s, torch.zeros_like(s))


def build(seed: int = 0, per_object: int = 400, fit_steps: int = 150, albedo: torch.Tensor = ALBEDO,
          centres: torch.Tensor = CENTRES, radii: tuple = RADII, glossy: int = BLUE, scale: float = 0.07) -> EditScene:
    """The scene; ``albedo``, ``centres``, ``radii`` [objects, ...] set other spheres, and ``glossy``
    is the label of the one sphere with the highlight (-1: none); ``scale``: the Gaussians' size
    (larger: softer edges between the spheres in the renders)."""
    g = torch.Generator().manual_seed(seed)
    means, normals, labels = [], [], []
    for obj in range(len(radii)):
        d = torch.nn.functional.normalize(torch.randn(per_object, 3, generator=g), dim=-1)
        means.append(centres[obj] + radii[obj] * d)
        normals.append(d)
        labels.append(torch.full((per_object,), obj))
    means, normals, labels = torch.cat(means), torch.cat(normals), torch.cat(labels)
    n = means.shape[0]
    scales = torch.full((n, 3), scale)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1)
    opac = torch.full((n,), 0.9)
    cams = ring_cameras()

    cfg = ColourFieldConfig(levels=6, log2_hashmap_size=12, base_res=8, growth=1.7, sh_dir_degree=4)
    torch.manual_seed(seed)
    field = DecoupledColourField(cfg, torch.tensor([[-2.0, -2.0, -1.0], [2.0, 2.0, 1.0]]))
    c_d_true = torch.logit(albedo[labels])
    eyes = cams.camera_centers()
    spec_true = torch.stack([specular_logit(means, normals, labels, c, glossy) for c in eyes])  # [V,N]
    opt = torch.optim.Adam(field.parameters(), lr=3e-2)
    dirs = torch.cat([view_directions(means, c.expand_as(means)) for c in eyes])  # [V*N,3]
    V = len(cams)
    for _ in range(fit_steps):
        f = field.encode(means)
        h1, h2 = field.diffuse_hidden(f)
        c_d = field.diffuse(h2)
        c_s = field.specular(f.repeat(V, 1), dirs, h1.repeat(V, 1), h2.repeat(V, 1))
        loss = ((c_d - c_d_true) ** 2).mean() + ((c_s - spec_true.reshape(-1, 1)) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    field.eval()
    for p in field.parameters():
        p.requires_grad_(False)
    scene = FrozenScene(means, quats, scales, opac, field, torch.zeros(3), backend="reference")
    return EditScene(scene, cams, labels, normals)


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """torch on one thread inside: tiny tensors, where threads only add contention on a shared machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def on_gpu(scene: FrozenScene) -> FrozenScene:
    """``scene`` on the GPU, with its own copy of the colour field."""
    import copy

    return FrozenScene(scene.means.cuda(), scene.quats.cuda(), scene.scales.cuda(), scene.opacities.cuda(),
                       copy.deepcopy(scene.field).cuda(), scene.background.cuda(), backend="auto")
