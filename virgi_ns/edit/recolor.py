"""The deterministic recolouring rule of the benchmarks: an HSV hue shift on selected pixels.

A pixel is selected when its hue lies in ``[h0, h1]`` degrees (a range with ``h0 > h1`` wraps
through 0, e.g. ``[330, 30]`` for reds), its saturation is at least ``s_min`` and its value at
least ``v_min``. Selected pixels get their hue shifted by ``shift`` degrees (mod 360) and their
saturation multiplied by ``sat_scale`` (clamped to 1); value is kept. Everything else is
returned unchanged, bit for bit.

Applied to one training view the rule makes an edit; applied to held-out views it makes the
ground truth. Near-white highlights have low saturation, so they fall outside the rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor


@dataclass(frozen=True)
class RecolorRule:
    """Hue range [h0, h1] (degrees), thresholds, and the shift applied to selected pixels."""

    h0: float
    h1: float
    shift: float
    s_min: float = 0.25
    v_min: float = 0.1
    sat_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in ("h0", "h1"):
            v = getattr(self, name)
            if not 0.0 <= v <= 360.0:
                raise ValueError(f"RecolorRule.{name} = {v} is not a hue in [0, 360] degrees")
        if self.sat_scale < 0:
            raise ValueError(f"RecolorRule.sat_scale = {self.sat_scale} must be >= 0")

    def __call__(self, image: Float[Tensor, "*B 3"]) -> tuple[Float[Tensor, "*B 3"], Tensor]:
        return recolor(image, self)

    def to_dict(self) -> dict[str, float]:
        return {"h0": self.h0, "h1": self.h1, "shift": self.shift, "s_min": self.s_min,
                "v_min": self.v_min, "sat_scale": self.sat_scale}


def rgb_to_hsv(rgb: Float[Tensor, "*B 3"]) -> Float[Tensor, "*B 3"]:
    """RGB in [0, 1] -> (hue in degrees [0, 360), saturation, value). Grey pixels get hue 0."""
    r, g, b = rgb.unbind(-1)
    v, imax = rgb.max(dim=-1)
    mn = rgb.min(dim=-1).values
    delta = v - mn
    safe = torch.where(delta > 0, delta, torch.ones_like(delta))
    h = torch.where(imax == 0, (g - b) / safe, torch.where(imax == 1, 2.0 + (b - r) / safe, 4.0 + (r - g) / safe))
    h = torch.where(delta > 0, torch.remainder(h * 60.0, 360.0), torch.zeros_like(h))
    s = torch.where(v > 0, delta / torch.where(v > 0, v, torch.ones_like(v)), torch.zeros_like(v))
    return torch.stack([h, s, v], dim=-1)


def hsv_to_rgb(hsv: Float[Tensor, "*B 3"]) -> Float[Tensor, "*B 3"]:
    """(hue degrees, saturation, value) -> RGB, the inverse of :func:`rgb_to_hsv`."""
    h, s, v = hsv.unbind(-1)
    # the standard closed form: channel n gets v - v s max(0, min(k, 4 - k, 1)), k = (n + h/60) mod 6
    n = torch.tensor([5.0, 3.0, 1.0], dtype=hsv.dtype, device=hsv.device)
    k = torch.remainder(n + (h / 60.0)[..., None], 6.0)
    f = torch.clamp(torch.minimum(k, 4.0 - k), 0.0, 1.0)
    return v[..., None] - (v * s)[..., None] * f


def rule_mask(image: Float[Tensor, "*B 3"], rule: RecolorRule) -> Tensor:
    """Bool [*B]: the pixels the rule recolours."""
    hsv = rgb_to_hsv(image.clamp(0.0, 1.0))
    h, s, v = hsv.unbind(-1)
    if rule.h0 <= rule.h1:
        in_hue = (h >= rule.h0) & (h <= rule.h1)
    else:
        in_hue = (h >= rule.h0) | (h <= rule.h1)
    return in_hue & (s >= rule.s_min) & (v >= rule.v_min)


def recolor(image: Float[Tensor, "*B 3"], rule: RecolorRule) -> tuple[Float[Tensor, "*B 3"], Tensor]:
    """Apply ``rule`` to an RGB image (any leading shape, values in [0, 1]).

    Returns (recoloured image, bool mask of the recoloured pixels). Unselected pixels are copied
    unchanged."""
    if image.shape[-1] != 3:
        raise ValueError(f"recolor: expected RGB in the last dimension, got shape {tuple(image.shape)}")
    hsv = rgb_to_hsv(image.clamp(0.0, 1.0))
    mask = rule_mask(image, rule)
    h = torch.remainder(hsv[..., 0] + rule.shift, 360.0)
    s = (hsv[..., 1] * rule.sat_scale).clamp(0.0, 1.0)
    shifted = hsv_to_rgb(torch.stack([h, s, hsv[..., 2]], dim=-1))
    return torch.where(mask[..., None], shifted, image), mask


__all__ = ["RecolorRule", "recolor", "rgb_to_hsv", "hsv_to_rgb", "rule_mask"]
