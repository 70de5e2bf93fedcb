"""Procedural evaluation scenes with a known recoloured truth.

Each scene is a few objects made of flat Gaussians laid on primitive surfaces (spheres, boxes,
cylinders, tori), on a checkered floor inside a backdrop shell, so every pixel is covered. A
Gaussian's colour for a camera is ``albedo * shade + ks * lobe``: Lambert shading under one
directional light (view-independent, so it belongs to the diffuse colour) plus a white Phong lobe
around the light's mirror direction (the view-dependent part). The *truth* of a recolour is the
same Gaussians with the target object's albedo hue-rotated (saturation and value kept, the lobe
unchanged): what the scene would look like had the object been painted another colour.

Because a hue rotation keeps HSV saturation and value, and adding grey (the lobe) changes neither
hue nor the rotation's result, the scene's recolour rule (:class:`~virgi_ns.recolor.RecolorRule`)
applied to a photo of a single-object pixel gives exactly the truth; they differ only where a
pixel blends the target with its neighbours, or where the rule's thresholds leave a target pixel
out. The benchmark edits one training photo with the rule, as a user would, and scores the edit
against the truth on held-out views.

:func:`write_scene` writes a nerfstudio-format capture (``images/``, ``transforms.json``, the
Gaussians as ``geometry.ply`` in the capture's frame, ``sparse_pc.ply``), the truth renders
(``truth/``), each Gaussian's object label (``labels.npy``), each pixel's (``labels/``) and
``scene.json``. Deterministic for
a given spec, size and seed.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from virgi_ns.edit.recolor import RecolorRule, hsv_to_rgb, rgb_to_hsv
from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.raster import Cameras, Request, composite, rasterize

FLOOR, BACKDROP = "floor", "backdrop"


# ------------------------------------------------------------------------------ specs
@dataclass(frozen=True)
class Part:
    """One primitive surface of one object.

    ``shape``: ``sphere`` (size: radius), ``box`` (size: half extents x, y, z), ``cylinder`` (size:
    radius, half height; side and top cap), ``torus`` (size: ring radius, tube radius; ring in the
    plane spanned by ``axis_u`` and world z, centred at ``centre``; ``arc``: the part of the ring
    kept, in degrees from ``axis_u``). ``patches``: spots of another colour on this part, each
    (direction from the centre (x, y, z), angular radius in degrees, albedo): Gaussians whose
    direction from the centre lies within the angle take the spot's albedo and the label
    ``<label>_spots``."""

    label: str
    shape: str
    centre: tuple[float, float, float]
    size: tuple[float, ...]
    albedo: tuple[float, float, float]
    ks: float = 0.0
    """Strength of the white specular lobe (0: matte)."""
    power: float = 30.0
    """Phong exponent of the lobe (larger: a smaller, sharper highlight)."""
    axis_u: tuple[float, float, float] = (1.0, 0.0, 0.0)
    arc: tuple[float, float] = (0.0, 360.0)
    patches: tuple[tuple[tuple[float, float, float], float, tuple[float, float, float]], ...] = ()


@dataclass(frozen=True)
class SceneSpec:
    """A procedural scene, its recolour (the target label's albedo hue-rotated by the rule's shift)
    and the rule a user would apply to a photo to make that edit."""

    name: str
    parts: tuple[Part, ...]
    target: str
    """The label whose albedo the truth recolours."""
    rule: RecolorRule
    why: str
    """One line: what the scene tests and why the rule is what it is (written once, kept)."""
    floor_albedo: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.55, 0.42, 0.30),
                                                                                   (0.45, 0.33, 0.22))
    floor_check: float = 0.5
    """Side of the floor's checker squares."""
    backdrop_albedo: tuple[float, float, float] = (0.62, 0.66, 0.70)
    light: tuple[float, float, float] = (0.4, -0.5, 1.0)
    """Direction towards the light."""
    cam_radius: float = 3.2
    cam_heights: tuple[float, ...] = (0.9, 1.8)
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.35)
    fov_deg: float = 50.0
    """Horizontal field of view."""


# ------------------------------------------------------------------------------ the set
def _hue_rule(h0: float, h1: float, shift: float, s_min: float, v_min: float) -> RecolorRule:
    return RecolorRule(h0, h1, shift, s_min, v_min)


def studs(label: str, grey_label: str, body_centre: tuple[float, float, float],
          half: tuple[float, float, float], radius: float, pitch: float, albedo: tuple[float, float, float],
          grey: tuple[float, float, float], grey_every: int = 4, ks: float = 0.25, power: float = 25.0
          ) -> tuple[Part, ...]:
    """Small spheres of ``radius`` packed on the four vertical faces of a box (``body_centre``, half
    extents ``half``), ``pitch`` apart on a grid over each face, each centre ``0.4 radius`` outside
    the face, so a stud sinks into the body and its Gaussians sit among the body's. Every
    ``grey_every``-th stud is ``grey`` (label ``grey_label``), the rest ``albedo`` (``label``)."""
    cx, cy, cz = body_centre
    hx, hy, hz = half
    out: list[Part] = []
    k = 0
    for axis, sign in ((1, -1.0), (0, 1.0), (1, 1.0), (0, -1.0)):
        along = half[1 - axis]  # the face's horizontal half extent
        n_h, n_v = max(1, int(2 * along / pitch)), max(1, int(2 * hz / pitch))
        for i in range(n_h):
            u = -along + (i + 0.5) * 2 * along / n_h
            for j in range(n_v):
                z = cz - hz + (j + 0.5) * 2 * hz / n_v
                c = [cx, cy, z]
                c[axis] += sign * (half[axis] + 0.4 * radius)
                c[1 - axis] += u
                is_grey = k % grey_every == grey_every - 1
                out.append(Part(grey_label if is_grey else label, "sphere", (c[0], c[1], c[2]), (radius,),
                                grey if is_grey else albedo, ks=ks, power=power))
                k += 1
    return tuple(out)


SCENES: dict[str, SceneSpec] = {
    spec.name: spec
    for spec in (
        SceneSpec(
            name="mug_handle",
            parts=(
                Part("mug", "cylinder", (0.0, 0.0, 0.0), (0.26, 0.3), (0.90, 0.90, 0.86), ks=0.35, power=40.0),
                Part("handle", "torus", (0.26, 0.0, 0.3), (0.16, 0.045), (0.78, 0.10, 0.09), ks=0.35, power=40.0,
                     axis_u=(1.0, 0.0, 0.0), arc=(-80.0, 80.0)),
                Part("apple", "sphere", (-0.75, 0.45, 0.22), (0.22,), (0.35, 0.62, 0.12), ks=0.15),
                Part("box", "box", (0.55, -0.7, 0.15), (0.2, 0.15, 0.15), (0.15, 0.3, 0.7)),
            ),
            target="handle",
            rule=_hue_rule(340.0, 20.0, 120.0, 0.4, 0.15),
            why="a small object (~1% of the view): the mug's red handle -> green; the rule takes reds "
                "above s 0.4 (the wood floor's orange, hue ~30, stays out)",
            cam_radius=3.0,
        ),
        SceneSpec(
            name="toy_on_white",
            parts=(
                Part("toy", "box", (0.0, 0.0, 0.35), (0.38, 0.28, 0.35), (0.88, 0.76, 0.10), ks=0.25, power=25.0),
                Part("toy", "sphere", (0.0, 0.0, 0.95), (0.27,), (0.88, 0.76, 0.10), ks=0.25, power=25.0,
                     patches=(((0.55, -0.8, 0.25), 16.0, (0.80, 0.10, 0.08)),
                              ((-0.55, -0.8, 0.25), 16.0, (0.80, 0.10, 0.08)),
                              ((0.0, 0.8, 0.5), 22.0, (0.80, 0.10, 0.08)))),
                Part("toy_spots", "cylinder", (0.0, -0.29, 0.45), (0.11, 0.06), (0.80, 0.10, 0.08), ks=0.25, power=25.0),
            ),
            target="toy",
            rule=_hue_rule(35.0, 75.0, 180.0, 0.35, 0.2),
            why="a large object (10-20%) with red parts inside it, on white: yellow -> blue (a 180-degree "
                "shift); the rule takes yellows above s 0.35, the red spots and button (hue 0-5) stay out",
            floor_albedo=((0.93, 0.93, 0.92), (0.90, 0.90, 0.89)),
            backdrop_albedo=(0.95, 0.95, 0.95),
            cam_radius=3.2,
            look_at=(0.0, 0.0, 0.55),
        ),
        SceneSpec(
            name="dark_vase",
            parts=(
                Part("vase", "cylinder", (0.0, 0.0, 0.0), (0.2, 0.32), (0.05, 0.08, 0.30), ks=0.5, power=50.0),
                Part("vase", "sphere", (0.0, 0.0, 0.62), (0.17,), (0.05, 0.08, 0.30), ks=0.5, power=50.0),
                Part("block", "box", (0.65, 0.25, 0.22), (0.22, 0.22, 0.22), (0.62, 0.68, 0.76)),
                Part("ball", "sphere", (-0.6, -0.35, 0.18), (0.18,), (0.90, 0.45, 0.10), ks=0.2),
            ),
            target="vase",
            rule=_hue_rule(210.0, 250.0, 130.0, 0.5, 0.05),
            why="a dark target (value ~0.3): the navy vase -> dark red; beside it a pale blue-grey block of "
                "the same hue, which s >= 0.5 leaves out",
            floor_albedo=((0.50, 0.50, 0.50), (0.40, 0.40, 0.40)),
        ),
        SceneSpec(
            name="pastel_cushion",
            parts=(
                Part("cushion", "sphere", (0.0, 0.0, 0.3), (0.32,), (0.98, 0.74, 0.80), ks=0.1),
                Part("cushion", "box", (0.0, 0.0, 0.08), (0.4, 0.4, 0.08), (0.98, 0.74, 0.80), ks=0.1),
                Part("crate", "box", (0.75, -0.3, 0.2), (0.2, 0.2, 0.2), (0.92, 0.92, 0.90)),
                Part("pot", "cylinder", (-0.7, 0.35, 0.0), (0.16, 0.22), (0.08, 0.50, 0.50), ks=0.2),
            ),
            target="cushion",
            rule=_hue_rule(320.0, 10.0, 60.0, 0.12, 0.3),
            why="a bright, pale target (value ~1, saturation ~0.25): pink -> peach (+60); the rule's low "
                "saturation floor (0.12) still leaves the white crate and grey floor out",
            floor_albedo=((0.70, 0.70, 0.70), (0.62, 0.62, 0.62)),
        ),
        SceneSpec(
            name="glossy_ball",
            parts=(
                Part("ball", "sphere", (0.0, 0.0, 0.5), (0.5,), (0.10, 0.58, 0.16), ks=0.9, power=60.0),
                Part("cube", "box", (0.8, 0.55, 0.12), (0.12, 0.12, 0.12), (0.75, 0.12, 0.1)),
            ),
            target="ball",
            rule=_hue_rule(90.0, 160.0, 160.0, 0.3, 0.1),
            why="a large (25-35%), strongly specular target with sharp highlights: green -> purple (+160); "
                "the highlights (low saturation) are outside the rule and must stay white",
            floor_albedo=((0.30, 0.30, 0.32), (0.24, 0.24, 0.26)),
            cam_radius=2.6,
            look_at=(0.0, 0.0, 0.45),
        ),
        SceneSpec(
            name="duck_beak",
            parts=(
                Part("duck", "sphere", (0.0, 0.0, 0.12), (0.12,), (0.92, 0.80, 0.12), ks=0.3),
                Part("duck", "sphere", (0.08, 0.0, 0.28), (0.075,), (0.92, 0.80, 0.12), ks=0.3),
                Part("beak", "sphere", (0.16, 0.0, 0.27), (0.035,), (0.85, 0.30, 0.05), ks=0.3),
                Part("bowl", "cylinder", (-0.7, -0.4, 0.0), (0.28, 0.1), (0.20, 0.35, 0.75), ks=0.2),
                Part("book", "box", (0.6, 0.6, 0.05), (0.3, 0.22, 0.05), (0.10, 0.45, 0.25)),
            ),
            target="duck",
            rule=_hue_rule(40.0, 70.0, 150.0, 0.4, 0.2),
            why="a small object (~1%) with a part of another colour: the yellow duck -> sky blue (+150), its "
                "orange beak (hue ~20) outside the rule and to keep",
            cam_radius=2.6,
            look_at=(0.0, 0.0, 0.2),
        ),
        SceneSpec(
            name="studded_robot",
            parts=(
                Part("robot", "box", (0.0, 0.0, 0.35), (0.34, 0.26, 0.35), (0.88, 0.76, 0.10), ks=0.25, power=25.0),
                Part("robot", "sphere", (0.0, 0.0, 0.95), (0.26,), (0.88, 0.76, 0.10), ks=0.25, power=25.0),
            ) + studs("studs", "bolts", (0.0, 0.0, 0.35), (0.34, 0.26, 0.35), 0.025, 0.14, (0.80, 0.10, 0.08),
                      (0.50, 0.50, 0.52)),
            target="robot",
            rule=_hue_rule(35.0, 75.0, 180.0, 0.35, 0.2),
            why="small parts of another colour packed on a recoloured body (a model's studs, not separate "
                "blobs): the yellow robot -> blue (+180); its red studs (hue ~3) and grey bolts (s ~0.04) lie "
                "outside the rule, visible in the edited photo and to keep in every view",
            floor_albedo=((0.93, 0.93, 0.92), (0.90, 0.90, 0.89)),
            backdrop_albedo=(0.95, 0.95, 0.95),
            cam_radius=3.2,
            look_at=(0.0, 0.0, 0.55),
        ),
    )
}
"""The known-truth scenes of the evaluation set (fixed before any tuning; see each ``why``)."""


# ------------------------------------------------------------------------------ geometry
@dataclass
class SurfacePoints:
    means: Tensor  # [N,3]
    normals: Tensor  # [N,3]
    albedo: Tensor  # [N,3]
    ks: Tensor  # [N]
    power: Tensor  # [N]
    labels: list[str]  # [N]
    lit: Tensor  # [N] bool: shaded by the light (the backdrop is not: an evenly lit studio wall)


def _fibonacci_sphere(n: int) -> Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def _sample_part(p: Part, spacing: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Points and outward normals on one primitive, about ``spacing`` apart."""
    c = torch.tensor(p.centre, dtype=torch.float64)
    jitter = lambda n: (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5)  # noqa: E731
    if p.shape == "sphere":
        r = p.size[0]
        n = max(16, int(4 * math.pi * r * r / spacing**2))
        d = _fibonacci_sphere(n)
        return c + r * d, d
    if p.shape == "box":
        hx, hy, hz = p.size
        pts, nrm = [], []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                a, b = [k for k in range(3) if k != axis]
                ha, hb = p.size[a], p.size[b]
                na, nb = max(2, int(2 * ha / spacing)), max(2, int(2 * hb / spacing))
                u = (torch.arange(na, dtype=torch.float64) + 0.5) / na * 2 * ha - ha
                v = (torch.arange(nb, dtype=torch.float64) + 0.5) / nb * 2 * hb - hb
                uu, vv = torch.meshgrid(u, v, indexing="ij")
                q = torch.zeros(uu.numel(), 3, dtype=torch.float64)
                q[:, a], q[:, b] = uu.flatten(), vv.flatten()
                q[:, axis] = sign * p.size[axis]
                nv = torch.zeros_like(q)
                nv[:, axis] = sign
                pts.append(q)
                nrm.append(nv)
        return c + torch.cat(pts), torch.cat(nrm)
    if p.shape == "cylinder":
        r, h = p.size
        n_around = max(8, int(2 * math.pi * r / spacing))
        n_up = max(2, int(2 * h / spacing))
        ang = (torch.arange(n_around, dtype=torch.float64) + 0.5) / n_around * 2 * math.pi
        zs = (torch.arange(n_up, dtype=torch.float64) + 0.5) / n_up * 2 * h
        A, Z = torch.meshgrid(ang, zs, indexing="ij")
        A = A + 0.5 * (torch.arange(n_up, dtype=torch.float64)[None] % 2) * 2 * math.pi / n_around
        side_n = torch.stack([torch.cos(A), torch.sin(A), torch.zeros_like(A)], -1).reshape(-1, 3)
        side = side_n * r + torch.stack([torch.zeros_like(Z), torch.zeros_like(Z), Z], -1).reshape(-1, 3)
        n_cap = max(4, int(math.pi * r * r / spacing**2))
        rad = r * torch.sqrt((torch.arange(n_cap, dtype=torch.float64) + 0.5) / n_cap)
        phi = math.pi * (3.0 - math.sqrt(5.0)) * torch.arange(n_cap, dtype=torch.float64)
        cap = torch.stack([rad * torch.cos(phi), rad * torch.sin(phi), torch.full_like(rad, 2 * h)], -1)
        cap_n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(cap)
        return c + torch.cat([side, cap]), torch.cat([side_n, cap_n])
    if p.shape == "torus":
        R, r = p.size
        u = torch.nn.functional.normalize(torch.tensor(p.axis_u, dtype=torch.float64), dim=0)
        w = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        lo, hi = (math.radians(a) for a in p.arc)
        n_ring = max(8, int((hi - lo) * R / spacing))
        n_tube = max(6, int(2 * math.pi * r / spacing))
        t = lo + (torch.arange(n_ring, dtype=torch.float64) + 0.5) / n_ring * (hi - lo)
        s = (torch.arange(n_tube, dtype=torch.float64) + 0.5) / n_tube * 2 * math.pi
        T, S = torch.meshgrid(t, s, indexing="ij")
        radial = torch.cos(T)[..., None] * u + torch.sin(T)[..., None] * w  # in the ring's plane
        binorm = torch.linalg.cross(u, w)
        nrm = torch.cos(S)[..., None] * radial + torch.sin(S)[..., None] * binorm
        pts = R * radial + r * nrm
        return c + pts.reshape(-1, 3), nrm.reshape(-1, 3)
    raise ValueError(f"unknown shape {p.shape!r}")


def _in_patch(points: Tensor, p: Part) -> tuple[Tensor, Tensor]:
    """(bool [N]: inside one of the part's patches, albedo [N,3] of that patch)."""
    inside = torch.zeros(points.shape[0], dtype=torch.bool)
    colour = torch.zeros(points.shape[0], 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(points - torch.tensor(p.centre, dtype=torch.float64), dim=-1)
    for direction, radius_deg, albedo in p.patches:
        a = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float64), dim=0)
        hit = (d @ a) >= math.cos(math.radians(radius_deg))
        inside |= hit
        colour[hit] = torch.tensor(albedo, dtype=torch.float64)
    return inside, colour


def surface_points(spec: SceneSpec, spacing: float, seed: int = 0) -> SurfacePoints:
    """Every Gaussian's position, normal, albedo, lobe and label: the objects, the floor (a disc of
    radius ``1.6 cam_radius``) and the backdrop (a sphere of radius ``2.2 cam_radius`` facing in)."""
    gen = torch.Generator().manual_seed(seed)
    means, normals, albedo, ks, power, labels = [], [], [], [], [], []

    def add(m: Tensor, n: Tensor, alb: Tensor, k: float, pw: float, lab: Sequence[str]) -> None:
        means.append(m)
        normals.append(n)
        albedo.append(alb)
        ks.append(torch.full((m.shape[0],), k, dtype=torch.float64))
        power.append(torch.full((m.shape[0],), pw, dtype=torch.float64))
        labels.extend(lab)

    for p in spec.parts:
        m, n = _sample_part(p, spacing, gen)
        alb = torch.tensor(p.albedo, dtype=torch.float64).expand(m.shape[0], 3).clone()
        lab = [p.label] * m.shape[0]
        if p.patches:
            hit, col = _in_patch(m, p)
            alb[hit] = col[hit]
            lab = [f"{p.label}_spots" if h else p.label for h in hit.tolist()]
        add(m, n, alb, p.ks, p.power, lab)
    # floor: a disc at z = 0, coarser away from the objects
    R = 1.6 * spec.cam_radius
    n_floor = int(math.pi * R * R / (2.0 * spacing) ** 2)
    rad = R * torch.sqrt((torch.arange(n_floor, dtype=torch.float64) + 0.5) / n_floor)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * torch.arange(n_floor, dtype=torch.float64)
    fl = torch.stack([rad * torch.cos(phi), rad * torch.sin(phi), torch.zeros_like(rad)], -1)
    check = ((torch.floor(fl[:, 0] / spec.floor_check) + torch.floor(fl[:, 1] / spec.floor_check)) % 2 == 0)
    a0, a1 = (torch.tensor(a, dtype=torch.float64) for a in spec.floor_albedo)
    add(fl, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(fl).clone(),
        torch.where(check[:, None], a0, a1), 0.0, 1.0, [FLOOR] * n_floor)
    # backdrop: an inward-facing sphere
    Rb = 2.2 * spec.cam_radius
    n_back = int(4 * math.pi * Rb * Rb / (6.0 * spacing) ** 2)
    d = _fibonacci_sphere(n_back)
    add(Rb * d, -d, torch.tensor(spec.backdrop_albedo, dtype=torch.float64).expand(n_back, 3).clone(), 0.0, 1.0,
        [BACKDROP] * n_back)
    lit = torch.tensor([lab != BACKDROP for lab in labels])
    return SurfacePoints(torch.cat(means), torch.cat(normals), torch.cat(albedo), torch.cat(ks), torch.cat(power),
                         labels, lit)


def _quat_z_to(normals: Tensor) -> Tensor:
    """Unit quaternions (w x y z) rotating +z onto each normal."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=normals.dtype)
    axis = torch.linalg.cross(z.expand_as(normals), normals)
    cos = normals[:, 2].clamp(-1.0, 1.0)
    half = torch.acos(cos) / 2
    s = axis.norm(dim=-1, keepdim=True)
    axis = torch.where(s > 1e-9, axis / s.clamp_min(1e-12), torch.tensor([1.0, 0.0, 0.0], dtype=normals.dtype))
    return torch.cat([torch.cos(half)[:, None], torch.sin(half)[:, None] * axis], -1)


def gaussians_of(points: SurfacePoints, spacing: float) -> Gaussians:
    """Flat Gaussians (discs about 0.7 ``spacing`` wide, a tenth as thick) on the sampled surfaces;
    floor and backdrop discs are larger, as their points are sparser. SH degree 0 from the
    albedo (shading and lobe are not in the file: the photos carry them)."""
    n = points.means.shape[0]
    tangent = torch.full((n,), 0.7 * spacing, dtype=torch.float64)
    tangent[[lab == FLOOR for lab in points.labels]] = 1.4 * spacing
    tangent[[lab == BACKDROP for lab in points.labels]] = 4.2 * spacing
    scales = torch.stack([tangent, tangent, 0.1 * tangent], -1)
    return Gaussians(
        means=points.means.float(),
        scales=torch.log(scales).float(),
        quats=_quat_z_to(points.normals).float(),
        opacities=torch.full((n,), 4.0),
        sh=((points.albedo.float() - 0.5) / SH_C0)[:, None, :],
    )


# ------------------------------------------------------------------------------ cameras
def _look_at(eye: Tensor, target: Tensor) -> Tensor:
    """OpenCV world-to-camera matrix (world up +z)."""
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype)),
                                          dim=0)
    down = torch.linalg.cross(fwd, right)
    M = torch.eye(4, dtype=eye.dtype)
    M[:3, :3] = torch.stack([right, down, fwd])
    M[:3, 3] = -M[:3, :3] @ eye
    return M


def scene_cameras(spec: SceneSpec, views: int, width: int, height: int) -> Cameras:
    """``views`` cameras on rings at ``cam_heights`` (alternating), evenly around the scene."""
    f = 0.5 * width / math.tan(math.radians(spec.fov_deg) / 2)
    target = torch.tensor(spec.look_at, dtype=torch.float64)
    mats = []
    for i in range(views):
        a = 2 * math.pi * i / views + 0.3
        h = spec.cam_heights[i % len(spec.cam_heights)]
        eye = torch.tensor([spec.cam_radius * math.cos(a), spec.cam_radius * math.sin(a), h], dtype=torch.float64)
        mats.append(_look_at(eye, target))
    return Cameras.from_params(f, f, width / 2, height / 2, torch.stack(mats).float(), width, height)


# ------------------------------------------------------------------------------ shading
def hue_rotate(rgb: Tensor, shift: float, sat_scale: float = 1.0) -> Tensor:
    """Rotate hue by ``shift`` degrees, scale saturation, keep value (the rule's colour change)."""
    hsv = rgb_to_hsv(rgb.clamp(0.0, 1.0))
    h = torch.remainder(hsv[..., 0] + shift, 360.0)
    return hsv_to_rgb(torch.stack([h, (hsv[..., 1] * sat_scale).clamp(0.0, 1.0), hsv[..., 2]], -1))


def shaded_colours(points: SurfacePoints, albedo: Tensor, light: Tensor, centres: Tensor, pair_view: Tensor,
                   pair_gaussian: Tensor) -> Tensor:
    """Colour [U,3] of each (view, Gaussian) pair: albedo x Lambert shade + white Phong lobe."""
    g, v = pair_gaussian.long(), pair_view.long()
    n = points.normals[g].to(light)
    L = light / light.norm()
    shade = torch.where(points.lit[g], 0.45 + 0.55 * (n @ L).clamp_min(0.0), 0.95)
    refl = 2 * (n @ L)[:, None] * n - L
    view = torch.nn.functional.normalize(centres[v].to(light) - points.means[g].to(light), dim=-1)
    lobe = points.ks[g].to(light) * (refl * view).sum(-1).clamp_min(0.0) ** points.power[g].to(light)
    return (albedo[g].to(light) * shade[:, None] + lobe[:, None]).clamp(0.0, 1.0)


@dataclass
class Rendered:
    images: Tensor  # [V,H,W,3] photos
    truth: Tensor  # [V,H,W,3] the same views after the recolour
    target_mask: Tensor  # [V,H,W] bool: pixels where the target object's weight is at least half
    label_maps: Tensor  # [V,H,W] uint8: the label with the largest weight at each pixel (index into names)


@torch.no_grad()
def render_scene(spec: SceneSpec, points: SurfacePoints, g: Gaussians, cams: Cameras, backend: str = "auto",
                 device: str = "cpu", progress: Optional[Callable[[int, int], None]] = None) -> Rendered:
    """Photos and truth renders of every view (one rasterization each, two composites)."""
    dev = torch.device(device)
    points = SurfacePoints(points.means.to(dev), points.normals.to(dev), points.albedo.to(dev), points.ks.to(dev),
                           points.power.to(dev), points.labels, points.lit.to(dev))
    target = torch.tensor([lab == spec.target for lab in points.labels], device=dev)
    albedo = points.albedo.float().to(dev)
    truth_albedo = torch.where(target[:, None], hue_rotate(albedo, spec.rule.shift, spec.rule.sat_scale), albedo)
    light = torch.tensor(spec.light, dtype=torch.float32, device=dev)
    means, quats = g.means.to(dev), g.quats.to(dev)
    scales, opac = torch.exp(g.scales).to(dev), torch.sigmoid(g.opacities).to(dev)
    names = sorted(set(points.labels))
    label_ids = torch.tensor([names.index(lab) for lab in points.labels], device=dev)
    one_hot = torch.nn.functional.one_hot(label_ids, len(names)).float()
    images, truth, masks, label_maps = [], [], [], []
    for i in range(len(cams)):
        cam = cams.index(i).to(dev)
        c = rasterize(means, quats, scales, opac, cam, Request.whole_images(cam), backend=backend)
        centres = cam.camera_centers()
        pv, pg = c.pair_view, c.pair_gaussian
        images.append(composite(shaded_colours(points, albedo, light, centres, pv, pg), c, 0.0)[0].clamp(0, 1))
        truth.append(composite(shaded_colours(points, truth_albedo, light, centres, pv, pg), c, 0.0)[0].clamp(0, 1))
        share = composite(target[pg.long()].float()[:, None], c, 0.0)[0, ..., 0]
        masks.append(share >= 0.5)
        label_maps.append(composite(one_hot[pg.long()], c, 0.0)[0].argmax(-1).to(torch.uint8))
        if progress is not None:
            progress(i + 1, len(cams))
    return Rendered(torch.stack(images).cpu(), torch.stack(truth).cpu(), torch.stack(masks).cpu(),
                    torch.stack(label_maps).cpu())


# ------------------------------------------------------------------------------ writing
def _png(path: Path, img: Tensor) -> None:
    from PIL import Image

    Image.fromarray((img.numpy() * 255.0 + 0.5).astype(np.uint8)).save(path)


def write_scene(spec: SceneSpec, out: Path, views: int = 48, width: int = 400, height: int = 300,
                spacing: float = 0.02, seed: int = 0, backend: str = "auto", device: str = "cpu",
                progress: Optional[Callable[[int, int], None]] = None) -> dict:
    """Write the capture (see the module docstring); returns ``scene.json``'s contents."""
    from PIL import Image

    from virgi_ns.io import save_ply

    pts = surface_points(spec, spacing, seed)
    g = gaussians_of(pts, spacing)
    cams = scene_cameras(spec, views, width, height)
    r = render_scene(spec, pts, g, cams, backend, device, progress)
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    (out / "truth").mkdir(exist_ok=True)
    (out / "labels").mkdir(exist_ok=True)
    frames = []
    for i in range(views):
        name = f"frame_{i:03d}.png"
        _png(out / "images" / name, r.images[i])
        _png(out / "truth" / name, r.truth[i])
        Image.fromarray(r.label_maps[i].numpy()).save(out / "labels" / name)
        c2w = torch.linalg.inv(cams.viewmats[i].double())
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    K = cams.Ks[0]
    meta = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "w": width, "h": height, "camera_model": "OPENCV", "frames": frames,
            "applied_transform": np.eye(4)[:3].tolist(), "ply_file_path": "sparse_pc.ply"}
    (out / "transforms.json").write_text(json.dumps(meta))
    save_ply(g, out / "geometry.ply")
    _write_points(out / "sparse_pc.ply", pts.means[:: max(1, len(pts.labels) // 20000)].float().numpy())
    names = sorted(set(pts.labels))
    np.save(out / "labels.npy", np.array([names.index(lab) for lab in pts.labels], dtype=np.int16))
    info = {
        "name": spec.name, "target": spec.target, "labels": names, "rule": spec.rule.to_dict(), "why": spec.why,
        "gaussians": len(g), "views": views, "width": width, "height": height, "spacing": spacing, "seed": seed,
        "target_fraction": float(r.target_mask.float().mean()),
        "rule_fraction_photos": float(_rule_share(r.images, spec.rule)),
    }
    (out / "scene.json").write_text(json.dumps(info, indent=1))
    return info


def _rule_share(images: Tensor, rule: RecolorRule) -> float:
    from virgi_ns.edit.recolor import rule_mask

    return float(rule_mask(images, rule).float().mean())


def _write_points(path: Path, xyz: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["r"] = rec["g"] = rec["b"] = 128
    path.write_bytes(header + rec.tobytes())


def scene_info(root: Path) -> dict:
    return json.loads((root / "scene.json").read_text())


__all__ = ["Part", "SceneSpec", "SCENES", "studs", "surface_points", "gaussians_of", "scene_cameras", "render_scene",
           "write_scene", "hue_rotate", "scene_info"]
