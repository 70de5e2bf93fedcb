"""Views saved from the viewer: ``<run>/views/view_NNN.png`` (the render the user paints over) and
``view_NNN.json`` (its camera, a CAM.json in the capture's frame)."""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from nerfstudio.cameras.cameras import Cameras as NSCameras

VIEW_RE = re.compile(r"view_(\d+)")
"""A saved view's number in a file name (an uploaded image keeps it: ``view_003_red.png``)."""


@dataclass
class SavedView:
    """A view saved from the viewer: its number, files, the render [H,W,3] in [0,1] and camera
    (dataparser frame, the model's)."""

    number: int
    png: Path
    json: Path
    camera: NSCameras
    image: np.ndarray

    @property
    def name(self) -> str:
        return f"view_{self.number:03d}"


def png_bytes(image: np.ndarray) -> bytes:
    """8-bit PNG of an [H,W,3] image in [0,1]."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray((np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


__all__ = ["SavedView", "VIEW_RE", "png_bytes"]
