"""Benchmark: what share of an edit's loss each object of a synthetic scene carries, on the view the
evaluation set edits, for each ``near_share``.

The edit engine fits the pixels the rule changed in one photo to their new colour and keeps every other
pixel at the current render; the changed pixels carry ``changed_share`` of the loss and, with
``near_share``, the unchanged pixels next to the change a part of the rest
(:func:`virgi_ns.edit.pixels.pixel_batches`). A part of another colour inside the recoloured object (the
toy's red spots, the duck's beak) is told to keep its colour only by its own unchanged pixels, and told
to change by its rim, blended with the object, among the changed pixels. Per object label this script
gives both: the sum over the unchanged (``keep``) or changed (``turn``) pixels of each pixel's loss weight
times the label's share of that pixel's colour, on the training photo the rule recolours most (the
evaluation set's edit view, :func:`virgi_ns.bench.evalset.edit_view_of_capture`), rendered from the scene's known
Gaussians. Nothing is fitted, nothing is trained: CPU is enough (the reference rasterizer, about a minute
a scene at the evaluation set's size).

    python bench/edit_loss_shares.py --scenes toy_on_white duck_beak --out bench_out/edit_loss_shares.json
"""

from __future__ import annotations

import json
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
    scenes: List[str] = field(default_factory=lambda: ["toy_on_white", "duck_beak"])
    """Synthetic scenes of the evaluation set (:data:`virgi_ns.bench.synthetic.SCENES`)."""
    near_shares: List[float] = field(default_factory=lambda: [0.0, 0.25, 0.5])
    """``EditConfig.near_share`` values to weigh the pixels by (0: the default)."""
    out: Path = Path("bench_out/edit_loss_shares.json")
    size: Tuple[int, int, int, float] = (0, 0, 0, 0.0)
    """Views, width, height and Gaussian spacing of the captures (zeros: the evaluation set's)."""


@torch.no_grad()
def loss_shares(name: str, near_shares: List[float], size: tuple, progress=None) -> dict:
    """Per object label of scene ``name`` and per ``near_share``: its ``keep`` and ``turn`` shares of the
    edit's loss on the evaluation set's edit view (module docstring); with the view and its pixel counts."""
    from virgi_ns.bench.evalset import SYNTHETIC_SIZE, edit_view_of_capture
    from virgi_ns.bench.synthetic import BACKDROP, FLOOR, SCENES, gaussians_of, render_scene, scene_cameras
    from virgi_ns.bench.synthetic import surface_points
    from virgi_ns.edit.engine import EditConfig
    from virgi_ns.edit.pixels import _group_weights, near_changed
    from virgi_ns.edit.recolor import recolor
    from virgi_ns.raster import Request, composite, rasterize

    if name not in SCENES:
        raise InputError(f"unknown synthetic scene {name!r}: one of {', '.join(SCENES)}")
    spec = SCENES[name]
    views, width, height, spacing = size if size[0] else SYNTHETIC_SIZE
    pts = surface_points(spec, spacing)
    g = gaussians_of(pts, spacing)
    cams = scene_cameras(spec, views, width, height)
    names = sorted(set(pts.labels) - {FLOOR, BACKDROP})
    label_of = {lab: i for i, lab in enumerate(names)}
    one_hot = torch.zeros(len(pts.labels), len(names))
    for k, lab in enumerate(pts.labels):
        if lab in label_of:
            one_hot[k, label_of[lab]] = 1.0
    photos = render_scene(spec, pts, g, cams, backend="reference", progress=progress).images
    view = edit_view_of_capture(photos, spec.rule)
    photo, cam = photos[view], cams.index(view)
    c = rasterize(g.means, g.quats, torch.exp(g.scales), torch.sigmoid(g.opacities), cam, Request.whole_images(cam),
                  backend="reference")
    cfg = EditConfig()
    changed = (recolor(photo, spec.rule)[0] - photo).abs().amax(-1) > cfg.unchanged_tol  # as the engine finds them
    share = composite(one_hot[c.pair_gaussian.long()], c, 0.0)[0].reshape(-1, len(names))  # [P, labels]
    flat = changed.reshape(-1)
    near = near_changed(changed, cfg.near_radius).reshape(-1)
    rows = {}
    for ns in near_shares:
        weight = _group_weights(flat, cfg.changed_share, None, near, ns)
        keep = ((weight * ~flat)[:, None] * share).sum(0)
        turn = ((weight * flat)[:, None] * share).sum(0)
        rows[str(ns)] = {lab: {"keep": float(keep[j]), "turn": float(turn[j])} for j, lab in enumerate(names)}
    dominated = share >= 0.5
    return {"edit_view": view, "target": spec.target, "pixels": int(flat.numel()), "changed": int(flat.sum()),
            "near_unchanged": int((near & ~flat).sum()),
            "dominated_pixels": {lab: int(dominated[:, j].sum()) for j, lab in enumerate(names)},
            "dominated_changed": {lab: int((dominated[:, j] & flat).sum()) for j, lab in enumerate(names)},
            "near_shares": rows}


def main(args: Args) -> dict:
    if not args.near_shares or any(not 0.0 <= s < 1.0 for s in args.near_shares):
        raise InputError("--near-shares must be values in [0, 1)")
    console = Console(width=160)
    res = {}
    with Progress(console=console, transient=True) as bar:
        for name in args.scenes:
            task = bar.add_task(f"{name}: rendering the photos", total=None)
            res[name] = loss_shares(name, args.near_shares, args.size,
                                    lambda d, n, t=task: bar.update(t, completed=d, total=n))
            bar.remove_task(task)
    t = Table(title="each object's share of the edit's loss on the edit view: keep (its unchanged pixels) / "
                    "turn (its weight on changed pixels), % of the whole loss")
    for col in ("scene", "label", "pixels it dominates (changed)", *(f"near_share {s}" for s in args.near_shares)):
        t.add_column(col)
    for name, r in res.items():
        for lab in r["dominated_pixels"]:
            cells = [f"{100 * r['near_shares'][str(s)][lab]['keep']:.2f} / {100 * r['near_shares'][str(s)][lab]['turn']:.2f}"
                     for s in args.near_shares]
            t.add_row(name, lab + (" (target)" if lab == r["target"] else ""),
                      f"{r['dominated_pixels'][lab]} ({r['dominated_changed'][lab]})", *cells)
    console.print(t)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        tmp.write_text(json.dumps({"size": list(args.size), "scenes": res}, indent=1))
    console.print(f"wrote {args.out}")
    return res


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
