"""A tiny procedural capture for the model tests: two spheres of Gaussians (one matte, one with a
known specular lobe), a ring of cameras, images rendered with the reference rasterizer and written
as a nerfstudio-format dataset, and the geometry as an INRIA .ply in the capture's frame."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.io import save_ply
from virgi_ns.nerfstudio.frames import quat_multiply, rotmat_to_quat
from virgi_ns.raster import Cameras, Request, composite
from virgi_ns.raster.reference import rasterize

MATTE_ALBEDO = (0.75, 0.25, 0.2)
GLOSSY_ALBEDO = (0.15, 0.3, 0.7)
LOBE_AXIS = (0.0, 0.0, -1.0)  # brightest for cameras looking down (the upper ring)
LOBE_GAIN = 0.6
LOBE_POWER = 2.0


@dataclass
class Scene:
    gaussians: Gaussians
    albedo: torch.Tensor  # [N,3]
    glossy: torch.Tensor  # [N] bool
    cameras: Cameras
    images: torch.Tensor  # [V,H,W,3]
    root: Path
    ply: Path


# A highlight: a sharp lobe seen from one training camera (index 2, upper ring) and faintly from its
# neighbours, as a specular highlight is seen from few directions. The default lobe above is a broad
# sheen, present in every upper-ring view (half of them): under an L1 loss the split of such a sheen
# between diffuse and specular is not determined (any diffuse between the two levels fits as well).
HIGHLIGHT_AXIS = (-0.414, -0.563, -0.716)  # camera 2 -> the glossy sphere's centre
HIGHLIGHT_POWER = 8.0


def lobe(dirs: torch.Tensor, axis=LOBE_AXIS, power: float = LOBE_POWER, gain: float = LOBE_GAIN) -> torch.Tensor:
    """Specular term for camera->point directions: ``gain * max(0, d . axis)^power`` (by default
    strongest when the camera looks down, -z world)."""
    a = torch.nn.functional.normalize(torch.tensor(axis, dtype=dirs.dtype), dim=0)
    return gain * (dirs @ a).clamp_min(0) ** power


def true_colours(g: Gaussians, albedo: torch.Tensor, glossy: torch.Tensor, cams: Cameras, pv, pg,
                 **lobe_args) -> torch.Tensor:
    centres = cams.camera_centers()
    d = torch.nn.functional.normalize(g.means[pg] - centres[pv], dim=-1)
    spec = lobe(d, **lobe_args)[:, None] * glossy[pg, None].to(d.dtype)
    return (albedo[pg] + spec).clamp(0, 1)


def _sphere_points(n: int, centre, radius: float, gen: torch.Generator) -> torch.Tensor:
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
    return torch.tensor(centre) + radius * v


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """OpenCV world-to-camera for a camera at ``eye`` looking at ``target`` (world up +z)."""
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    up = torch.tensor([0.0, 0.0, 1.0])
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up), dim=0)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])  # rows: camera axes in world
    M = torch.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    return M


def make_scene(root: Path, n_per_sphere: int = 120, views: int = 16, width: int = 48, height: int = 40,
               seed: int = 0, **lobe_args) -> Scene:
    """``lobe_args``: :func:`lobe`'s ``axis``, ``power``, ``gain`` (default: the broad sheen)."""
    gen = torch.Generator().manual_seed(seed)
    a = _sphere_points(n_per_sphere, (-0.6, 0.0, 0.0), 0.45, gen)
    b = _sphere_points(n_per_sphere, (0.6, 0.0, 0.0), 0.45, gen)
    means = torch.cat([a, b])
    n = means.shape[0]
    glossy = torch.zeros(n, dtype=torch.bool)
    glossy[n_per_sphere:] = True
    albedo = torch.where(glossy[:, None], torch.tensor(GLOSSY_ALBEDO), torch.tensor(MATTE_ALBEDO))
    sh = ((albedo - 0.5) / SH_C0)[:, None, :]
    g = Gaussians(
        means=means,
        scales=torch.full((n, 3), math.log(0.12)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        opacities=torch.full((n,), 3.0),
        sh=sh,
    )
    # cameras on two rings (above and level), looking at the origin
    vms = []
    for i in range(views):
        ang = 2 * math.pi * i / views
        elev = 0.9 if i % 2 == 0 else 0.25
        eye = torch.tensor([3.2 * math.cos(ang), 3.2 * math.sin(ang), 3.2 * elev])
        vms.append(look_at(eye, torch.zeros(3)))
    viewmats = torch.stack(vms)
    f = 40.0
    cams = Cameras.from_params(f, f, width / 2, height / 2, viewmats, width, height)
    req = Request.whole_images(cams)
    with torch.no_grad():
        contrib = rasterize(g.means, g.quats, torch.exp(g.scales), torch.sigmoid(g.opacities), cams, req)
        cols = true_colours(g, albedo, glossy, cams, contrib.pair_view, contrib.pair_gaussian, **lobe_args)
        images = composite(cols, contrib, 0.0).clamp(0, 1)

    root.mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    frames = []
    for i in range(views):
        name = f"images/frame_{i:03d}.png"
        Image.fromarray((images[i].numpy() * 255 + 0.5).astype(np.uint8)).save(root / name)
        c2w = torch.linalg.inv(viewmats[i])
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    meta = {"fl_x": f, "fl_y": f, "cx": width / 2, "cy": height / 2, "w": width, "h": height,
            "camera_model": "OPENCV", "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    ply = root / "scene.ply"
    save_ply(g, ply)
    return Scene(g, albedo, glossy, cams, images, root, ply)


def use_scene(cfg, scene: Scene, pixel_budget: int, cache_on_device: bool = True):
    """Point a virgi trainer config's datamanager at ``scene``: nerfstudio's parser (every 8th view
    held out), 16-px tiles, ``pixel_budget`` pixels per colour step; ``cache_on_device`` caches the
    images as "gpu", which keeps them on the manager's device (the CPU here). Returns the datamanager
    config."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    dm = cfg.pipeline.datamanager
    dm.data = scene.root
    dm.dataparser = NerfstudioDataParserConfig(data=scene.root, load_3D_points=False, eval_mode="interval",
                                               eval_interval=8)
    dm.tile_size = 16
    dm.pixel_budget = pixel_budget
    if cache_on_device:
        dm.cache_images = "gpu"
    return dm


def axis_angle(axis, degrees: float) -> torch.Tensor:
    a = torch.nn.functional.normalize(torch.tensor(axis, dtype=torch.float64), dim=0)
    Kx = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    t = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(t) * Kx + (1 - math.cos(t)) * Kx @ Kx


def rotated_copy(sc: Scene, root: Path, R0: torch.Tensor, shift=(0.3, -0.2, 0.5)) -> Scene:
    """The same capture (same images) expressed in a rotated and shifted world frame, so that the
    dataparser's transform back to its frame is far from the identity."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "images").symlink_to(sc.root / "images")
    t0 = torch.tensor(shift, dtype=torch.float64)
    meta = json.loads((sc.root / "transforms.json").read_text())
    for fr in meta["frames"]:
        c2w = torch.tensor(fr["transform_matrix"], dtype=torch.float64)
        c2w[:3, :3] = R0 @ c2w[:3, :3]
        c2w[:3, 3] = R0 @ c2w[:3, 3] + t0
        fr["transform_matrix"] = c2w.tolist()
    (root / "transforms.json").write_text(json.dumps(meta))
    g = sc.gaussians
    R0f = R0.float()
    qR = rotmat_to_quat(R0f)
    g2 = g.replace(means=g.means @ R0f.T + t0.float(),
                   quats=quat_multiply(qR.expand(len(g), 4), torch.nn.functional.normalize(g.quats, dim=-1)))
    save_ply(g2, root / "scene.ply")
    inv = torch.eye(4, dtype=torch.float64)
    inv[:3, :3] = R0.T
    inv[:3, 3] = -R0.T @ t0
    vms = (sc.cameras.viewmats.double() @ inv).float()
    cams = Cameras(sc.cameras.Ks, vms, sc.cameras.widths, sc.cameras.heights)
    return Scene(g2, sc.albedo, sc.glossy, cams, sc.images, root, root / "scene.ply")
