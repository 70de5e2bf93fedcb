"""The capture bundled with the package (``virgi_ns/assets/beercan_small``) and a dataparser for it.

The bundle is a nerfstudio-format capture (``transforms.json``, undistorted pinhole images,
``sparse_pc.ply``) whose frame is COLMAP's (``applied_transform`` is the identity), so a splat
trained on the original COLMAP model imports with ``geometry_frame="capture"``. It is made by
``scripts/make_bundle.py``. Its optional ``geometry.spz`` (or ``geometry.ply``) holds pre-trained Gaussians in that frame.

:class:`BundleDataParserConfig` is nerfstudio's dataparser with the bundle's defaults (every 8th
view held out, no downscaling) that reads the sparse points with the project's own PLY reader
instead of open3d (whose import fails on machines without libusb).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

import numpy as np
import torch
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig

from virgi_ns.errors import InputError

BUNDLED_SCENE = Path(__file__).resolve().parents[1] / "assets" / "beercan_small"
"""The bundled capture's folder."""
GEOMETRY_NAMES = ("geometry.spz", "geometry.ply")
"""File names of pre-trained geometry inside a bundle, in order of preference."""


def bundled_geometry(scene: Path = BUNDLED_SCENE) -> Optional[Path]:
    """The pre-trained geometry file of a bundle, or None."""
    return next((scene / n for n in GEOMETRY_NAMES if (scene / n).is_file()), None)


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz float32 [N,3], rgb uint8 [N,3]) of a binary points PLY (colours white when absent)."""
    from virgi_ns.io.plyfmt import read_ply_bytes

    ply = read_ply_bytes(Path(path).read_bytes(), str(path))
    v = ply.get("vertex")
    if v is None or v.data is None or not {"x", "y", "z"} <= set(v.names):
        raise InputError(f"{path}: no vertex element with x, y, z")
    xyz = np.stack([v.data[k] for k in ("x", "y", "z")], -1).astype(np.float32)
    if {"red", "green", "blue"} <= set(v.names):
        rgb = np.stack([v.data[k] for k in ("red", "green", "blue")], -1).astype(np.uint8)
    else:
        rgb = np.full_like(xyz, 255, dtype=np.uint8)
    return xyz, rgb


@dataclass
class BundleDataParserConfig(NerfstudioDataParserConfig):
    """A nerfstudio-format capture (by default the bundled one); points read without open3d."""

    _target: Type = field(default_factory=lambda: BundleDataParser)
    data: Path = BUNDLED_SCENE
    downscale_factor: Optional[int] = 1
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "interval"
    eval_interval: int = 8
    load_3D_points: bool = True


class BundleDataParser(Nerfstudio):
    """nerfstudio's parser; ``_load_3D_points`` uses :func:`read_points_ply`."""

    config: BundleDataParserConfig

    def _load_3D_points(self, ply_file_path: Path, transform_matrix: torch.Tensor, scale_factor: float):
        xyz, rgb = read_points_ply(ply_file_path)
        if len(xyz) == 0:
            return None
        pts = torch.from_numpy(xyz)
        pts = torch.cat([pts, torch.ones_like(pts[:, :1])], -1) @ transform_matrix.T.to(pts)
        return {"points3D_xyz": pts * scale_factor, "points3D_rgb": torch.from_numpy(rgb)}
