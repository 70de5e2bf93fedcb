"""Conversions between nerfstudio's cameras and frames and the rasterizer's.

nerfstudio cameras are camera-to-world with OpenGL axes (x right, y up, z back); the rasterizer
contract wants world-to-camera with OpenCV axes (x right, y down, z forward).
"""

from __future__ import annotations

import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from torch import Tensor

from virgi_ns.raster import Cameras


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


# ---------------------------------------------------------------------------- rigid frames
def rotmat_to_quat(R: Tensor) -> Tensor:
    """[...,3,3] rotation matrices -> [...,4] unit quaternions (w x y z), w >= 0."""
    m = R.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = torch.stack(
        [
            torch.stack([1 + tr, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
            torch.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                         m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
            torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0],
                         1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
            torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                         1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
        ],
        dim=1,
    )  # [B,4 candidates,4]; candidate k is 4 * q_k * q, numerically best where |q_k| is largest
    diag = torch.stack([1 + tr, 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                        1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1)
    best = diag.argmax(-1)
    q = cand[torch.arange(m.shape[0]), best]
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(*R.shape[:-2], 4)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of wxyz quaternions (rotation ``a`` after ``b``)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )



def transform_gaussians(means: Tensor, log_scales: Tensor, quats: Tensor, transform: Tensor, scale: float
                        ) -> tuple[Tensor, Tensor, Tensor]:
    """Apply ``x -> scale * (R x + t)`` (``transform`` = [R|t], 3x4, R a rotation) to Gaussians:
    means move, log-scales shift by log(scale), orientations rotate by R."""
    T = transform.to(means)
    R, t = T[:3, :3], T[:3, 3]
    new_means = scale * (means @ R.T + t)
    new_scales = log_scales + torch.log(torch.tensor(float(scale), dtype=log_scales.dtype))
    qR = rotmat_to_quat(R).to(quats)
    q = torch.nn.functional.normalize(quats, dim=-1)
    new_quats = quat_multiply(qR.expand_as(q), q)
    return new_means, new_scales, new_quats
