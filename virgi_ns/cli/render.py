"""``virgi-render SPLAT --camera CAM.json --out OUT``: render a splat file from one camera.

Colours come from the splat's spherical harmonics evaluated for the view direction (degree 0:
``0.2820948 f_dc + 0.5``, clamped below at 0); the image is the rasterizer's contributions
composited over ``--background``. ``OUT`` ending in ``.npy`` gets the float32 HxWx3 image,
``.png`` an 8-bit one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import tyro
from rich.console import Console

from virgi_ns.cli import run_command
from virgi_ns.errors import InputError, atomic_path

OUT_SUFFIXES = (".npy", ".png")


@dataclass
class Render:
    """Render a splat (.ply, .compressed.ply, .spz, .sog, splatfacto .ckpt or config.yml) from a camera."""

    splat: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SPLAT")]
    """Input splat: .ply, .compressed.ply, .spz, .sog (zip or folder), a splatfacto .ckpt or its config.yml."""
    camera: Path
    """CAM.json: width, height, fx, fy, cx, cy and world_to_camera (4x4, OpenCV axes)."""
    out: Path
    """Output image: .npy (float32 HxWx3) or .png (8-bit)."""
    backend: Literal["auto", "reference", "cuda"] = "auto"
    """Rasterizer: our CUDA kernels when a GPU is present (auto), or the torch reference."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background colour R G B in [0, 1]."""


def render_image(g, spec, backend: str = "auto", background=(0.0, 0.0, 0.0), device=None) -> np.ndarray:
    """HxWx3 float32 image of Gaussians ``g`` seen by camera ``spec`` (a CameraSpec)."""
    from virgi_ns.colour.sh import view_colors
    from virgi_ns.raster import Request, composite, rasterize

    if device is None:
        device = torch.device("cuda" if backend != "reference" and torch.cuda.is_available() else "cpu")
    g = g.to(device=device, dtype=torch.float32)
    cams = spec.to_cameras(torch.float32, device)
    contrib = rasterize(
        g.means, g.normalized_quats(), torch.exp(g.scales), torch.sigmoid(g.opacities), cams,
        Request.whole_images(cams), backend=backend,
    )
    center = cams.camera_centers()[0]
    colors = view_colors(g.sh, g.means, center)[contrib.pair_gaussian]
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    img = composite(colors, contrib, bg)[0]
    return img.detach().cpu().numpy().astype(np.float32)


def run(args: Render) -> str:
    suffix = args.out.suffix.lower()
    if suffix not in OUT_SUFFIXES:
        raise InputError(f"output {args.out} must end in .npy or .png")
    if not all(np.isfinite(args.background)):
        raise InputError(f"--background must be finite numbers, got {args.background}")
    from virgi_ns.io import load_splat
    from virgi_ns.io.camera_json import read_camera_json

    spec = read_camera_json(args.camera)
    if args.backend == "cuda" and not torch.cuda.is_available():
        raise InputError("--backend cuda needs a CUDA GPU; none is available (use auto or reference)")
    console = Console(stderr=True)
    with console.status(f"reading {args.splat}"):
        g = load_splat(args.splat)
    with console.status(f"rendering {len(g):,} Gaussians at {spec.width}x{spec.height} ({args.backend})"):
        try:
            img = render_image(g, spec, args.backend, args.background)
        except RuntimeError as e:
            if "cuda" in str(e).lower() and args.backend == "cuda":
                raise InputError(f"--backend cuda failed: {str(e).splitlines()[0]}") from None
            raise
    with atomic_path(args.out) as tmp:
        if suffix == ".npy":
            with open(tmp, "wb") as f:
                np.save(f, img)
        else:
            from PIL import Image

            Image.fromarray((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(tmp, format="PNG")
    return f"{args.out}: {spec.width}x{spec.height} image of {len(g):,} Gaussians"


def entrypoint() -> None:
    run_command(Render, run)


if __name__ == "__main__":
    entrypoint()
