"""Conversions between nerfstudio's cameras and the rasterizer's.

nerfstudio cameras are camera-to-world with OpenGL axes (x right, y up, z back); the rasterizer
contract wants world-to-camera with OpenCV axes (x right, y down, z forward).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from virgi_ns.raster import Cameras

if TYPE_CHECKING:  # only read here: importing this module (or frames) needs no nerfstudio
    from nerfstudio.cameras.cameras import Cameras as NSCameras


def viewmats_from_c2w(c2w: Tensor) -> Tensor:
    """[V,3,4] (or [V,4,4]) OpenGL camera-to-world -> [V,4,4] OpenCV world-to-camera."""
    R = c2w[:, :3, :3] * torch.tensor([1.0, -1.0, -1.0], dtype=c2w.dtype, device=c2w.device)
    t = c2w[:, :3, 3:4]
    Rt = R.transpose(1, 2)
    out = torch.zeros(c2w.shape[0], 4, 4, dtype=c2w.dtype, device=c2w.device)
    out[:, :3, :3] = Rt
    out[:, :3, 3:4] = -Rt @ t
    out[:, 3, 3] = 1
    return out


def raster_cameras(cameras: NSCameras) -> Cameras:
    """nerfstudio pinhole cameras (any batch shape, flattened) -> rasterizer :class:`Cameras`."""
    cams = cameras.flatten() if len(cameras.shape) != 1 else cameras
    c2w = cams.camera_to_worlds.float()
    K = cams.get_intrinsics_matrices().float().to(c2w.device)
    return Cameras(K, viewmats_from_c2w(c2w), cams.width.reshape(-1), cams.height.reshape(-1))


def ns_cameras(cameras: Cameras) -> NSCameras:
    """Rasterizer :class:`Cameras` -> nerfstudio pinhole cameras (the inverse of :func:`raster_cameras`),
    for code that renders our own cameras through a model's nerfstudio entry points."""
    from nerfstudio.cameras.cameras import Cameras as NSCameras

    c2w = torch.linalg.inv(cameras.viewmats.float())[:, :3, :4]
    c2w = c2w * torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=c2w.dtype, device=c2w.device)  # OpenCV -> OpenGL axes
    K = cameras.Ks.float()
    return NSCameras(camera_to_worlds=c2w, fx=K[:, 0, 0:1], fy=K[:, 1, 1:2], cx=K[:, 0, 2:3], cy=K[:, 1, 2:3],
                     width=cameras.widths.reshape(-1, 1).long(), height=cameras.heights.reshape(-1, 1).long())


__all__ = ["ns_cameras", "raster_cameras", "viewmats_from_c2w"]
