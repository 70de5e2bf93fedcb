"""Benchmark: how far a pick's recolour is from the rule's, before any fit, for each recolour mode.

A pick and the rule edit of the evaluation set differ in what they select, in how they recolour it, and
in their fits. This script measures the recolour alone: on the training photo the rule recolours most
(the bench's edit view), the rule's own pixels are recoloured as a pick would recolour them (the click
the bench's pick makes, the rule's colour at that pixel, :func:`virgi_ns.edit.pick.recolour` in each
mode) and compared with the rule's recolour of the same photo, over the whole view (the scale of the
propagation PSNR) and over the rule's pixels. On a synthetic scene both are also compared with the
truth: the photo of the really recoloured scene, whose shading the rule does not always follow.
Nothing is trained or fitted (CPU; a synthetic scene's photos take about a minute to render).

    python bench/pick_recolour.py --out bench_out/pick_recolour.json
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Tuple

import torch
import tyro
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from virgi_ns.errors import InputError, atomic_path, cli_entry

@dataclass
class Args:
    scenes: List[str] = field(default_factory=list)
    """Rows of the evaluation set (:data:`virgi_ns.bench.evalset.EVAL_SET`; default all)."""
    modes: List[str] = field(default_factory=lambda: ["hue", "shift"])
    """Recolour modes to measure (:data:`virgi_ns.edit.pick.MODES`)."""
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    """The real captures; a row whose capture is missing is skipped with a line."""
    out: Path = Path("bench_out/pick_recolour.json")
    size: Tuple[int, int, int, float] = (0, 0, 0, 0.0)
    """Views, width, height and Gaussian spacing of the synthetic captures (zeros: the evaluation set's)."""


def psnr(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor) -> float:
    """PSNR of ``a`` against ``b`` [H,W,3] over the pixels ``where`` [H,W] (inf when equal)."""
    mse = float(((a - b) ** 2)[where].double().mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def finite_or_none(value):
    """``value`` with every infinite float (two equal images) as None: JSON has no infinity."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    return None if isinstance(value, float) and math.isinf(value) else value


def real_photos(folder: Path) -> List[torch.Tensor]:
    """A real capture's photos [H,W,3] in [0, 1], in file order, from the folder its parser reads."""
    import numpy as np
    from PIL import Image

    from virgi_ns.bench.evalset import capture_images

    images = folder / capture_images(folder)
    files = sorted(p for p in images.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise InputError(f"no photos in {images}")
    return [torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), dtype=np.float32) / 255.0) for p in files]


def synthetic_photos(name: str, size: tuple, progress=None) -> tuple[List[torch.Tensor], List[torch.Tensor]]:
    """A synthetic scene's photos and truth (the recoloured scene), rendered from its known Gaussians."""
    from virgi_ns.bench.evalset import SYNTHETIC_SIZE
    from virgi_ns.bench.synthetic import SCENES, gaussians_of, render_scene, scene_cameras, surface_points

    spec = SCENES[name]
    views, width, height, spacing = size if size[0] else SYNTHETIC_SIZE
    pts = surface_points(spec, spacing)
    r = render_scene(spec, pts, gaussians_of(pts, spacing), scene_cameras(spec, views, width, height),
                     backend="reference", progress=progress)
    return list(r.images), list(r.truth)


def measure(photo: torch.Tensor, rule, modes: List[str], truth=None) -> dict:
    """The pick's recolour in each mode against the rule's on ``photo`` (and both against ``truth``)."""
    from virgi_ns.bench.pick import click_pixel, rule_colour
    from virgi_ns.edit.pick import recolour
    from virgi_ns.edit.recolor import recolor, rule_mask

    mask = rule_mask(photo, rule)
    x, y, _ = click_pixel(mask)
    colour = rule_colour(photo, x, y, rule)
    ruled = recolor(photo, rule)[0]
    everywhere = torch.ones_like(mask)
    out = {"pixel": [x, y], "colour": colour, "mask_fraction": float(mask.float().mean()), "modes": {}}
    for mode in modes:
        picked = recolour(photo, mask, colour, mode, at=(x, y))
        out["modes"][mode] = {"view_psnr": psnr(picked, ruled, everywhere), "mask_psnr": psnr(picked, ruled, mask)}
        if truth is not None:
            out["modes"][mode]["truth_view_psnr"] = psnr(picked, truth, everywhere)
    if truth is not None:
        out["rule_truth_view_psnr"] = psnr(ruled, truth, everywhere)
    return out


def main(args: Args) -> dict:
    from virgi_ns.bench.evalset import edit_view_of_capture, find
    from virgi_ns.edit.pick import check_mode

    for m in args.modes:
        check_mode(m)
    console = Console(width=160)
    rows = {}
    with Progress(console=console, transient=True) as bar:
        for scene in find(args.scenes):
            if scene.synthetic:
                task = bar.add_task(f"{scene.name}: rendering the photos", total=None)
                photos, truths = synthetic_photos(scene.synthetic, args.size,
                                                  lambda d, n, t=task: bar.update(t, completed=d, total=n))
                bar.remove_task(task)
            else:
                folder = args.data / scene.capture
                if not folder.is_dir():
                    console.print(f"{scene.name}: skipped, no capture at {folder}")
                    continue
                photos, truths = real_photos(folder), None
            view = edit_view_of_capture(photos, scene.rule)
            truth = truths[view] if truths is not None else None
            rows[scene.name] = {"view": view, **measure(photos[view], scene.rule, args.modes, truth)}
    t = Table(title="the pick's recolour of the rule's pixels against the rule's recolour, before any fit (PSNR, dB)")
    t.add_column("scene")
    t.add_column("rule's pixels")
    for m in args.modes:
        t.add_column(f"{m}: view / its pixels")
    t.add_column("against the truth: rule, " + ", ".join(args.modes))
    fmt = lambda v: "inf" if math.isinf(v) else f"{v:.2f}"  # noqa: E731
    for name, r in rows.items():
        modes = [r["modes"][m] for m in args.modes]
        truth = ("-" if "rule_truth_view_psnr" not in r else
                 ", ".join(fmt(v) for v in [r["rule_truth_view_psnr"]] + [m["truth_view_psnr"] for m in modes]))
        t.add_row(name, f"{100 * r['mask_fraction']:.1f}%",
                  *(f"{fmt(m['view_psnr'])} / {fmt(m['mask_psnr'])}" for m in modes), truth)
    console.print(t)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        tmp.write_text(json.dumps(finite_or_none({"size": list(args.size), "modes": args.modes, "scenes": rows}),
                                  indent=1, allow_nan=False))
    console.print(f"wrote {args.out}")
    return rows


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
