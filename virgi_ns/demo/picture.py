"""``grid.png``: one row per held-out view, the columns below left to right."""

from __future__ import annotations

from typing import Dict, List

import numpy as np
from torch import Tensor

COLUMNS = ("photo", "render", "recoloured", "segmentation", "diffuse", "specular")
TITLES = {"specular": "|specular| x4"}


def grid_image(rows: List[Dict[str, Tensor]], labels: List[str]) -> np.ndarray:
    """uint8 grid: one row per held-out view, the :data:`COLUMNS` left to right, a title strip."""
    from PIL import Image, ImageDraw

    h, w = rows[0]["photo"].shape[:2]
    pad, title = 4, 18
    H = title + len(rows) * (h + pad)
    W = len(COLUMNS) * (w + pad) + pad
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for c, name in enumerate(COLUMNS):
        draw.text((pad + c * (w + pad) + 2, 3), TITLES.get(name, name), fill=(0, 0, 0))
    for r, row in enumerate(rows):
        for c, name in enumerate(COLUMNS):
            img = row[name].detach().float().cpu().clamp(0, 1)
            if img.shape[-1] == 1:
                img = img.expand(*img.shape[:-1], 3)
            arr = (img.numpy() * 255 + 0.5).astype(np.uint8)
            canvas.paste(Image.fromarray(arr), (pad + c * (w + pad), title + r * (h + pad)))
        draw.text((pad + 2, title + r * (h + pad) + 2), labels[r], fill=(255, 255, 0))
    return np.asarray(canvas)


def grid_row(photo: Tensor, base: Dict[str, Tensor], edited: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """One row of the grid: the held-out photo, the unedited render (``base``) and the edited one."""
    return {"photo": photo, "render": base["rgb"], "recoloured": edited["rgb"].clamp(0, 1),
            "segmentation": edited["segmentation"], "diffuse": edited["diffuse"],
            "specular": (edited["specular"].abs() * 4.0)}


__all__ = ["COLUMNS", "grid_image", "grid_row"]
