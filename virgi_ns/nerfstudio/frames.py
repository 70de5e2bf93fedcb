"""The capture's frame and the run's: nerfstudio's dataparser moves a capture into the run's frame,
``x_run = scale (R x_capture + t)`` (``dataparser_transforms.json``; for COLMAP captures nerfstudio
1.x folds its world-axis swap into that transform).

Splats imported in the capture's frame are moved into the run's (:func:`transform_gaussians`);
exports and saved views go back (:class:`CaptureFrame`, :func:`camera_spec`), so files line up
with the source data.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

import torch
from jaxtyping import Float
from torch import Tensor

from virgi_ns.errors import InputError
from virgi_ns.io.camera_json import CameraSpec
from virgi_ns.nerfstudio.cameras import raster_cameras, viewmats_from_c2w
from virgi_ns.raster import Cameras

if TYPE_CHECKING:  # the frames themselves need no nerfstudio (the command-line tools import this module)
    from nerfstudio.cameras.cameras import Cameras as NSCameras


# ---------------------------------------------------------------------------- rigid maps
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


# -------------------------------------------------------------------------- capture frame
@dataclass
class CaptureFrame:
    """The run's frame relative to the capture's: ``x_run = scale * (R x_capture + t)``
    (``transform`` = [R | t], 3x4, R a rotation)."""

    transform: Float[Tensor, "3 4"]
    scale: float

    @staticmethod
    def identity() -> "CaptureFrame":
        return CaptureFrame(torch.cat([torch.eye(3), torch.zeros(3, 1)], dim=1).double(), 1.0)

    @staticmethod
    def from_dataparser(transform: Tensor, scale: float) -> "CaptureFrame":
        """From a dataparser's ``transform`` (3x4 or 4x4) and ``scale``. nerfstudio 1.x's COLMAP
        parser folds its world-axis swap into that transform, so it alone maps the capture's world
        to the run's (checked on beercan against COLMAP's images.bin to 5e-7)."""
        T = torch.as_tensor(transform, dtype=torch.float64)[:3, :4]
        return CaptureFrame(T.clone(), float(scale))

    @staticmethod
    def from_transforms_json(path: str | Path) -> "CaptureFrame":
        """From a run's ``dataparser_transforms.json`` (``transform``, ``scale``)."""
        path = Path(path)
        try:
            d = json.loads(path.read_text())
            T = torch.tensor(d["transform"], dtype=torch.float64)
            s = float(d["scale"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(f"{path}: not a readable dataparser_transforms.json ({type(e).__name__})") from None
        if T.shape not in ((3, 4), (4, 4)) or not torch.isfinite(T).all() or not (s > 0 and math.isfinite(s)):
            raise InputError(f"{path}: transform must be 3x4 and scale a positive number")
        return CaptureFrame.from_dataparser(T, s)

    @staticmethod
    def from_pipeline(pipeline) -> "CaptureFrame":
        """The frame a VIRGi datamanager recorded for imports (``virgi_capture_transform``), or
        else its dataparser's transform."""
        dm = pipeline.datamanager
        meta = getattr(getattr(dm, "train_dataset", None), "metadata", None) or {}
        if meta.get("virgi_capture_transform") is not None:
            return CaptureFrame(torch.as_tensor(meta["virgi_capture_transform"], dtype=torch.float64)[:3, :4],
                                float(meta.get("virgi_capture_scale", 1.0)))
        out = dm.train_dataparser_outputs
        return CaptureFrame.from_dataparser(out.dataparser_transform, float(out.dataparser_scale))

    # ---- maps run -> capture
    @property
    def rotation(self) -> Tensor:
        """R of ``x_run = scale (R x + t)`` (float64)."""
        return self.transform[:, :3].double()

    def inverse_transform(self) -> tuple[Tensor, float]:
        """([R' | t'], scale') with ``x_capture = scale' (R' x_run + t')``."""
        R = self.rotation
        t = self.transform[:, 3].double()
        Rt = R.T
        return torch.cat([Rt, (-self.scale * (Rt @ t))[:, None]], dim=1), 1.0 / self.scale

    def points_to_capture(self, x: Tensor) -> Tensor:
        T, s = self.inverse_transform()
        return (s * (x.double() @ T[:, :3].T + T[:, 3])).to(x.dtype)

    def directions_to_capture(self, d: Tensor) -> Tensor:
        """Directions (any length) of the run's frame in the capture's (rotation only)."""
        return d @ self.rotation.to(d)

    def directions_to_run(self, d: Tensor) -> Tensor:
        return d @ self.rotation.T.to(d)

    def gaussians_to_capture(self, means: Tensor, log_scales: Tensor, quats: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Means, log-scales, wxyz quaternions of the run's frame in the capture's (float64 inside)."""
        T, s = self.inverse_transform()
        m, sc, q = transform_gaussians(means.double(), log_scales.double(), quats.double(), T, s)
        return m.to(means.dtype), sc.to(log_scales.dtype), q.to(quats.dtype)

    def viewmats_to_capture(self, viewmats: Tensor) -> Tensor:
        """OpenCV world-to-camera [V,4,4] of the run's frame -> the same cameras in the capture's
        frame (``p_cam`` divided by ``scale``, which no pinhole projection sees)."""
        R = self.rotation.to(viewmats)
        t = self.transform[:, 3].to(viewmats)
        out = viewmats.clone()
        out[:, :3, :3] = viewmats[:, :3, :3] @ R
        out[:, :3, 3] = (viewmats[:, :3, :3] @ t) + viewmats[:, :3, 3] / self.scale
        return out


def frame_of_model(model) -> CaptureFrame:
    """The capture frame a VIRGi datamanager recorded in the model's metadata (identity if none)."""
    meta = (getattr(model, "kwargs", None) or {}).get("metadata") or {}
    T = meta.get("virgi_capture_transform")
    if T is None:
        return CaptureFrame.identity()
    return CaptureFrame(torch.as_tensor(T, dtype=torch.float64)[:3, :4], float(meta.get("virgi_capture_scale", 1.0)))


# ------------------------------------------------------------------ cameras of saved views
def capture_frame(model) -> tuple[torch.Tensor, float]:
    """The dataparser transform ``x_dp = s (R x + t)`` from the capture's frame (``[R|t]`` 3x4, ``s``);
    identity when the run does not record it."""
    meta = (getattr(model, "kwargs", None) or {}).get("metadata") or {}
    T = meta.get("virgi_capture_transform")
    s = float(meta.get("virgi_capture_scale", 1.0))
    if T is None:
        return torch.eye(4)[:3].double(), 1.0
    return torch.as_tensor(T).double().cpu()[:3], s


def camera_spec(camera: NSCameras, transform: torch.Tensor, scale: float) -> CameraSpec:
    """CAM.json of a one-view nerfstudio camera, in the frame ``transform``/``scale`` map from.

    With ``x_dp = s (R x + t)`` and the dataparser-frame viewmat ``[Rv|tv]``, the capture-frame
    camera is ``[Rv R | Rv t + tv / s]`` (camera coordinates shrink by ``s``; pixels are equal)."""
    rc = raster_cameras(camera)
    vm = rc.viewmats[0].double().cpu()
    K = rc.Ks[0].double().cpu()
    R, t = transform[:3, :3].double(), transform[:3, 3].double()
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] = vm[:3, :3] @ R
    M[:3, 3] = vm[:3, :3] @ t + vm[:3, 3] / scale
    return CameraSpec(int(rc.widths[0]), int(rc.heights[0]), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                      float(K[1, 2]), M.numpy())


def _c2w_of_spec(spec: CameraSpec, transform: torch.Tensor, scale: float) -> Tensor:
    """The OpenGL camera-to-world [3,4] (float64, dataparser frame) of a capture-frame CAM.json."""
    M = torch.as_tensor(spec.world_to_camera, dtype=torch.float64)
    R, t = transform[:3, :3].double(), transform[:3, 3].double()
    Rv = M[:3, :3] @ R.T
    tv = scale * (M[:3, 3] - Rv @ t)
    c2w = torch.eye(4, dtype=torch.float64)[:3]
    c2w[:3, :3] = Rv.T
    c2w[:3, 3] = -Rv.T @ tv
    c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
    return c2w


def camera_from_spec(spec: CameraSpec, transform: torch.Tensor, scale: float) -> "NSCameras":
    """The nerfstudio camera (dataparser frame) of a capture-frame CAM.json; inverse of :func:`camera_spec`."""
    from nerfstudio.cameras.cameras import Cameras as NSCameras

    return NSCameras(camera_to_worlds=_c2w_of_spec(spec, transform, scale)[None].float(), fx=spec.fx, fy=spec.fy,
                     cx=spec.cx, cy=spec.cy, width=spec.width, height=spec.height)


def raster_camera_from_spec(spec: CameraSpec, transform: torch.Tensor, scale: float) -> Cameras:
    """``raster_cameras(camera_from_spec(...))`` without nerfstudio: the same float32 numbers."""
    c2w = _c2w_of_spec(spec, transform, scale)[None].float()
    K = torch.tensor([[[spec.fx, 0.0, spec.cx], [0.0, spec.fy, spec.cy], [0.0, 0.0, 1.0]]], dtype=torch.float32)
    return Cameras(K, viewmats_from_c2w(c2w), spec.width, spec.height)


__all__ = ["CaptureFrame", "camera_from_spec", "camera_spec", "capture_frame", "frame_of_model", "quat_multiply",
           "raster_camera_from_spec", "rotmat_to_quat", "transform_gaussians"]
