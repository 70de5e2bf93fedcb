"""The demo's figures, per held-out view and averaged: how well the model reproduces the photo, and
what the click's edit did there. The clicked object is marked in each view by its colour
(``DemoConfig.object_rule``: the can's blue) in the unedited render; the edit should turn those
pixels to the asked colour and leave everything else as it was. ``DEFINITIONS`` goes into
``metrics.json`` beside the figures."""

from __future__ import annotations

import math
from typing import Dict, List, Optional

import torch
from torch import Tensor

from virgi_ns.edit.recolor import RecolorRule, rgb_to_hsv, rule_mask

HUE_MATCH_DEG = 30.0
"""An object pixel counts as recoloured when its hue lies within this many degrees of the colour's."""
NEAR_PX = 2
"""The object's mask grown by this many pixels: its blended edge belongs to neither side of the leak."""

HELD_OUT_FIGURES = ("reconstruction_psnr", "leak_psnr", "recoloured_share", "hue_error_deg", "unedited_hue_error_deg")

DEFINITIONS = {
    "reconstruction_psnr": "unedited render vs held-out photo",
    "leak_psnr": "edited vs unedited render away from the object (outside its mask grown by 2 px): what the edit "
                 "changed elsewhere (higher is less)",
    "recoloured_share": "share of the object's pixels whose hue in the edited render lies within 30 degrees of the "
                        "asked colour's",
    "hue_error_deg": "mean angle between the asked colour's hue and the edited render's over the object's pixels",
    "unedited_hue_error_deg": "the same angle for the unedited render (no edit)",
    "object_pixels": "per view: the object's pixels (its colour in the unedited render, where the Gaussians cover it)",
    "click_view": "the same figures in the clicked training view, with the pick's selection as the object",
    "edit_fit_psnr": "clicked view's edited render vs the pick's edited image, on the selected pixels",
}


def psnr(a: Tensor, b: Tensor, mask: Optional[Tensor] = None) -> float:
    """PSNR (data range 1) over all pixels, or over ``mask`` [H,W] (NaN when it is empty)."""
    err = (a.float() - b.float()) ** 2
    if mask is not None:
        if not bool(mask.any()):
            return float("nan")
        err = err[mask]
    return -10.0 * math.log10(max(float(err.mean()), 1e-10))


def mean_finite(xs: List[float]) -> float:
    """The mean of the values that are not NaN (NaN when none is)."""
    xs = [x for x in xs if not math.isnan(x)]
    return float(sum(xs) / len(xs)) if xs else float("nan")


def as_float(img: Tensor) -> Tensor:
    """RGB of an image as float in [0, 1] (uint8 images are scaled)."""
    img = img[..., :3]
    return img.float() / 255.0 if img.dtype == torch.uint8 else img.float()


def grow(mask: Tensor, pixels: int) -> Tensor:
    """``mask`` [H,W] grown by ``pixels`` (a square neighbourhood)."""
    if pixels <= 0:
        return mask
    k = 2 * pixels + 1
    return torch.nn.functional.max_pool2d(mask[None, None].float(), k, 1, pixels)[0, 0] > 0


def hue_angle(rgb: Tensor, hue_deg: float) -> Tensor:
    """Per pixel, the angle in degrees [0, 180] between its hue and ``hue_deg``."""
    d = torch.remainder(rgb_to_hsv(rgb.clamp(0, 1))[..., 0] - hue_deg, 360.0)
    return torch.minimum(d, 360.0 - d)


def object_mask(base_rgb: Tensor, accumulation: Tensor, rule: RecolorRule, min_cover: float) -> Tensor:
    """[H,W] bool: the object's pixels in an unedited render, those of the object's colour (``rule``)
    that the Gaussians cover (``accumulation`` [H,W] at least ``min_cover``)."""
    return rule_mask(base_rgb.clamp(0, 1).cpu(), rule).to(base_rgb.device) & (accumulation.to(base_rgb.device) >= min_cover)


def view_metrics(name: str, base_rgb: Tensor, edited_rgb: Tensor, photo: Tensor, obj: Tensor,
                 colour: tuple[float, float, float]) -> Dict[str, object]:
    """The figures of one view (see :data:`DEFINITIONS`): ``base_rgb`` and ``edited_rgb`` [H,W,3]
    are its renders before and after the edit, ``photo`` its photo, ``obj`` [H,W] the object's
    pixels (:func:`object_mask`, or a pick's selection), ``colour`` the asked colour (RGB in [0, 1])."""
    base, edited = base_rgb.clamp(0, 1), edited_rgb.clamp(0, 1)
    obj = obj.to(base.device)
    target_hue = float(rgb_to_hsv(torch.tensor(colour))[0])
    angle = hue_angle(edited, target_hue)
    unedited_angle = hue_angle(base, target_hue)
    has = bool(obj.any())
    return {
        "view": name,
        "reconstruction_psnr": psnr(base, photo),
        "leak_psnr": psnr(edited, base, ~grow(obj, NEAR_PX)),
        "recoloured_share": float((angle[obj] <= HUE_MATCH_DEG).float().mean()) if has else float("nan"),
        "hue_error_deg": float(angle[obj].mean()) if has else float("nan"),
        "unedited_hue_error_deg": float(unedited_angle[obj].mean()) if has else float("nan"),
        "object_pixels": int(obj.sum()),
    }


def held_out_means(per_view: List[Dict[str, object]]) -> Dict[str, float]:
    """Each of :data:`HELD_OUT_FIGURES` averaged over the held-out views (those without the object
    leave out its figures)."""
    return {key: mean_finite([v[key] for v in per_view]) for key in HELD_OUT_FIGURES}


def summary_table(metrics: Dict[str, object]):
    """The figures of ``metrics.json`` as a table for the console."""
    from rich.table import Table

    t = Table(title="virgi demo")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("reconstruction psnr", f"{metrics['reconstruction_psnr']:.2f} dB")
    t.add_row("leak psnr (away from the object)", f"{metrics['leak_psnr']:.2f} dB")
    t.add_row("object pixels recoloured", f"{metrics['recoloured_share']:.0%}")
    t.add_row("object hue error", f"{metrics['hue_error_deg']:.1f} deg (unedited {metrics['unedited_hue_error_deg']:.1f})")
    cv = metrics["click_view"]
    t.add_row("clicked view: selection recoloured / leak", f"{cv['recoloured_share']:.0%} / {cv['leak_psnr']:.2f} dB")
    t.add_row("edit fit psnr (clicked view, selection)", f"{metrics['edit_fit_psnr']:.2f} dB")
    et = metrics["edit_time_s"]
    t.add_row("pick time", f"{et['total']:.2f} s")
    t.add_row("total time", f"{metrics['times_s']['total_s']:.0f} s")
    return t


__all__ = ["DEFINITIONS", "as_float", "grow", "held_out_means", "hue_angle", "object_mask", "psnr", "summary_table",
           "view_metrics"]
