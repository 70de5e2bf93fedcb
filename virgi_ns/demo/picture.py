"""``grid.png``: one row per held-out view, the columns below left to right."""

from __future__ import annotations

from typing import Dict, List

import numpy as np
import torch
from torch import Tensor

COLUMNS = ("photo", "render", "recoloured", "segmentation", "highlights")
HIGHLIGHT_QUANTILE = 0.995
"""The highlight layer is scaled so that this quantile of its pixels over the grid reaches white."""
MAX_HIGHLIGHT_GAIN = 64.0


def highlight_gain(rows: List[Dict[str, Tensor]]) -> float:
    """The factor that shows the highlight layer (|specular|) of ``rows``: its
    :data:`HIGHLIGHT_QUANTILE` over every row's pixels becomes 1, at least 1x and at most
    :data:`MAX_HIGHLIGHT_GAIN`, rounded down to a whole number."""
    values = torch.cat([r["highlights"].detach().float().abs().amax(-1).reshape(-1).cpu() for r in rows])
    top = float(torch.quantile(values[:: max(1, values.numel() // 1_000_000)], HIGHLIGHT_QUANTILE))
    return float(max(1.0, min(MAX_HIGHLIGHT_GAIN, np.floor(1.0 / max(top, 1e-6)))))


def grid_image(rows: List[Dict[str, Tensor]], labels: List[str], scale: int = 1) -> np.ndarray:
    """uint8 grid: one row per held-out view, the :data:`COLUMNS` left to right, each cell ``scale``
    times the render's size (nearest neighbour), a title strip naming the columns."""
    from PIL import Image, ImageDraw

    gain = highlight_gain(rows)
    titles = {"highlights": f"highlights x{gain:.0f}"}
    h, w = (s * scale for s in rows[0]["photo"].shape[:2])
    pad, title = 4, 18
    H = title + len(rows) * (h + pad)
    W = len(COLUMNS) * (w + pad) + pad
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for c, name in enumerate(COLUMNS):
        draw.text((pad + c * (w + pad) + 2, 3), titles.get(name, name), fill=(0, 0, 0))
    for r, row in enumerate(rows):
        for c, name in enumerate(COLUMNS):
            img = row[name].detach().float().cpu()
            img = (img.abs() * gain if name == "highlights" else img).clamp(0, 1)
            if img.shape[-1] == 1:
                img = img.expand(*img.shape[:-1], 3)
            arr = (img.numpy() * 255 + 0.5).astype(np.uint8)
            if scale > 1:
                arr = arr.repeat(scale, axis=0).repeat(scale, axis=1)
            canvas.paste(Image.fromarray(arr), (pad + c * (w + pad), title + r * (h + pad)))
        draw.text((pad + 2, title + r * (h + pad) + 2), labels[r], fill=(255, 255, 0))
    return np.asarray(canvas)


def grid_row(photo: Tensor, base: Dict[str, Tensor], edited: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """One row of the grid: the held-out photo, the unedited render (``base``) and the edited one
    with its segmentation and its highlight layer (the view-dependent part, unscaled)."""
    return {"photo": photo, "render": base["rgb"], "recoloured": edited["rgb"].clamp(0, 1),
            "segmentation": edited["segmentation"], "highlights": edited["specular"]}


__all__ = ["COLUMNS", "grid_image", "grid_row", "highlight_gain"]
