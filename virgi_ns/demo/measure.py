"""The demo's figures: PSNR of the held-out views before and after the edit, against the rule
applied to the photos (recolour) and to the unedited renders (propagation), and the summary
printed at the end. ``DEFINITIONS`` goes into ``metrics.json`` beside them."""

from __future__ import annotations

import math
from typing import Dict, List, Optional

import torch
from torch import Tensor

from virgi_ns.edit.recolor import RecolorRule, recolor

HELD_OUT_PSNRS = ("reconstruction_psnr", "recolour_psnr", "recolour_psnr_inside_mask", "unedited_psnr_inside_mask",
                  "propagation_psnr", "propagation_psnr_inside_mask", "propagation_psnr_outside_mask")

DEFINITIONS = {
    "reconstruction_psnr": "unedited render vs held-out photo",
    "recolour_psnr": "edited render vs the rule applied to the held-out photo",
    "recolour_psnr_inside_mask": "the same on the pixels the rule recolours in the photo (the can);"
                                 " unedited_psnr_inside_mask: the unedited render there (no edit)",
    "propagation_psnr": "edited render vs the rule applied to the unedited render (isolates the edit);"
                        " inside_mask: pixels the rule recolours (misses), outside: the rest (leaks)",
    "edit_fit_psnr": "edited view's render vs the edited image (the rule applied to its photo or render), "
                     "on the pixels the rule changed",
    "rule_pixels": "held-out pixels the rule recolours, summed over the held-out views: in the unedited"
                   " renders (what the edit can visibly change) and in the photos",
    "mask_fraction": "per view: share of pixels the rule recolours in the unedited render",
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


def view_metrics(name: str, base_rgb: Tensor, edited_rgb: Tensor, photo: Tensor, rule: RecolorRule
                 ) -> Dict[str, object]:
    """The figures of one held-out view (see :data:`DEFINITIONS`): ``base_rgb`` and ``edited_rgb``
    are its renders before and after the edit, ``photo`` its photo."""
    truth, truth_mask = recolor(photo, rule)
    prop_truth, prop_mask = recolor(base_rgb.clamp(0, 1), rule)
    e_rgb = edited_rgb.clamp(0, 1)
    return {
        "view": name,
        "reconstruction_psnr": psnr(base_rgb.clamp(0, 1), photo),
        "recolour_psnr": psnr(e_rgb, truth),
        "recolour_psnr_inside_mask": psnr(e_rgb, truth, truth_mask),
        "unedited_psnr_inside_mask": psnr(base_rgb.clamp(0, 1), truth, truth_mask),
        "propagation_psnr": psnr(e_rgb, prop_truth),
        "propagation_psnr_inside_mask": psnr(e_rgb, prop_truth, prop_mask),
        "propagation_psnr_outside_mask": psnr(e_rgb, prop_truth, ~prop_mask),
        "mask_fraction": float(prop_mask.float().mean()),
        "rule_pixels_render": int(prop_mask.sum()),
        "rule_pixels_photo": int(truth_mask.sum()),
    }


def held_out_means(per_view: List[Dict[str, object]]) -> Dict[str, float]:
    """Each of :data:`HELD_OUT_PSNRS` averaged over the held-out views."""
    return {key: mean_finite([v[key] for v in per_view]) for key in HELD_OUT_PSNRS}


def rule_pixel_totals(per_view: List[Dict[str, object]]) -> Dict[str, int]:
    """Held-out pixels the rule recolours, summed over the views: in the unedited renders and in the photos."""
    return {"unedited_renders": sum(v["rule_pixels_render"] for v in per_view),
            "photos": sum(v["rule_pixels_photo"] for v in per_view)}


def summary_table(metrics: Dict[str, object]):
    """The figures of ``metrics.json`` as a table for the console."""
    from rich.table import Table

    t = Table(title="virgi demo")
    t.add_column("figure")
    t.add_column("value", justify="right")
    for key in ("reconstruction_psnr", "recolour_psnr", "recolour_psnr_inside_mask", "unedited_psnr_inside_mask",
                "propagation_psnr", "propagation_psnr_inside_mask",
                "propagation_psnr_outside_mask", "edit_fit_psnr"):
        t.add_row(key.replace("_", " "), f"{metrics[key]:.2f} dB")
    et = metrics["edit_time_s"]
    t.add_row("edit time", f"{et['total']:.2f} s (setup {et['setup']:.2f}, {et['steps_count']} steps {et['steps']:.2f})")
    t.add_row("total time", f"{metrics['times_s']['total_s']:.0f} s")
    return t


__all__ = ["DEFINITIONS", "as_float", "held_out_means", "psnr", "rule_pixel_totals", "summary_table", "view_metrics"]
