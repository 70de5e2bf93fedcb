"""``CAM.json``: one pinhole camera, as ``virgi-render`` reads it.

    {"width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0,
     "world_to_camera": [[...4 numbers...], x4]}

``world_to_camera`` is a 4x4 matrix with OpenCV axes (x right, y down, z forward), as gsplat's
``viewmats``: its rotation part must be orthonormal and its last row ``0 0 0 1``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from virgi_ns.errors import InputError, atomic_path
from virgi_ns.raster.contract import Cameras

__all__ = ["CameraSpec", "read_camera_json", "write_camera_json", "parse_camera"]

_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "world_to_camera")


@dataclass
class CameraSpec:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray  # [4, 4] float64

    def to_cameras(self, dtype: torch.dtype = torch.float32, device=None) -> Cameras:
        """A one-view :class:`Cameras`."""
        vm = torch.as_tensor(self.world_to_camera, dtype=dtype, device=device)[None]
        return Cameras.from_params(self.fx, self.fy, self.cx, self.cy, vm, self.width, self.height)

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "world_to_camera": [[float(v) for v in row] for row in np.asarray(self.world_to_camera)],
        }


def _number(d: dict, key: str, where: str) -> float:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{where}: '{key}' must be a finite number, got {v!r}")
    return float(v)


def parse_camera(d: object, where: str = "camera") -> CameraSpec:
    """Validate a decoded JSON object; every problem is one clear :class:`InputError`."""
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a JSON object with {', '.join(_KEYS)}")
    missing = [k for k in _KEYS if k not in d]
    if missing:
        raise InputError(f"{where}: missing {', '.join(missing)} (needs {', '.join(_KEYS)})")
    size = {}
    for key in ("width", "height"):
        v = d[key]
        if isinstance(v, float) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= 65536:
            raise InputError(f"{where}: '{key}' must be a whole number of pixels in 1..65536, got {v!r}")
        size[key] = v
    fx, fy, cx, cy = (_number(d, k, where) for k in ("fx", "fy", "cx", "cy"))
    if fx <= 0 or fy <= 0:
        raise InputError(f"{where}: focal lengths must be positive, got fx={fx}, fy={fy}")
    m = d["world_to_camera"]
    ok = isinstance(m, list) and len(m) == 4 and all(isinstance(r, list) and len(r) == 4 for r in m)
    if not ok or any(isinstance(v, bool) or not isinstance(v, (int, float)) for r in m for v in r):
        raise InputError(f"{where}: 'world_to_camera' must be a 4x4 array of numbers (rows of 4)")
    M = np.asarray(m, dtype=np.float64)
    if not np.isfinite(M).all():
        raise InputError(f"{where}: 'world_to_camera' holds NaN or Inf")
    if np.abs(M[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise InputError(f"{where}: 'world_to_camera' last row must be 0 0 0 1, got {M[3].tolist()}")
    R = M[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise InputError(f"{where}: 'world_to_camera' rotation part is not a rotation (orthonormal, det +1)")
    return CameraSpec(size["width"], size["height"], fx, fy, cx, cy, M)


def read_camera_json(path: str | os.PathLike) -> CameraSpec:
    """Read and validate a CAM.json file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such camera file: {path}")
    try:
        text = path.read_text(encoding="utf-8")
        d = json.loads(text)
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read camera file {path}: {e}") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    return parse_camera(d, str(path))


def write_camera_json(path: str | os.PathLike, spec: CameraSpec) -> None:
    """Write a CAM.json file (atomically)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(spec.to_dict(), indent=2) + "\n", encoding="utf-8")
