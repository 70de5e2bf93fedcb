"""Benchmark (CPU): small parts of another colour packed on a recoloured body, the suspects measured apart.

A yellow box with red and grey studs sunk into its four sides (``common.synthetic.studs``), the colour field
fitted directly to every Gaussian's true diffuse colour (no floor or backdrop: wide views whose pixels are
mostly background stand in for them, so the studs are a small share of the unchanged pixels), its own
render of view 0 recoloured by the toy's rule as the edit. Each row changes one thing from the defaults and
reports, per view (the edited one and held-out ones), the studs' and bolts' inner pixels against the
unedited render (mean absolute difference, pixels off by more than 0.08) and the box's against the rule on
the unedited render, and the edit's mean alpha over each object's Gaussians:

  defaults                 EditConfig()
  changed_share=0.2        the loss share of the unchanged pixels raised (0.5 -> 0.8)
  unchanged_weights=colour the colours shown only unchanged get half of it (the candidate)
  seg_without_f            the segmentation head reads h_diff only (the hash features neighbours share zeroed)
  seg_without_h            the segmentation head reads the hash features only
  map_start                the copied layer starts from the colour map however small the edit
  changed_target=edited    the photo's pixels as the changed pixels' target
  recipe=staged            the segmentation fitted first as a classifier

    python bench/edit_packed_parts.py --out bench_out/packed_parts
"""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

from common.synthetic import Part, SceneSpec, gaussians_of, scene_cameras, studs, surface_points
from virgi_ns.colour.field import ColourFieldConfig, DecoupledColourField
from virgi_ns.edit import engine as engine_module
from virgi_ns.edit.engine import EditConfig, EditEngine
from virgi_ns.edit.heads import SegmentationHead
from virgi_ns.edit.recolor import RecolorRule, recolor
from virgi_ns.edit.scene import FrozenScene, render_view
from virgi_ns.edit.stack import EditStack
from virgi_ns.raster import Request, composite

YELLOW, RED, GREY = (0.88, 0.76, 0.10), (0.80, 0.10, 0.08), (0.50, 0.50, 0.52)
SPEC = SceneSpec(
    name="packed", target="toy",
    parts=(Part("toy", "box", (0.0, 0.0, 0.3), (0.3, 0.3, 0.3), YELLOW),)
    + studs("studs", "bolts", (0.0, 0.0, 0.3), (0.3, 0.3, 0.3), 0.05, 0.15, RED, GREY),
    rule=RecolorRule(35.0, 75.0, 180.0, 0.35, 0.2), why="bench", cam_radius=1.3, look_at=(0.0, 0.0, 0.3),
    fov_deg=108.0)
ROWS = ("defaults", "changed_share=0.2", "unchanged_weights=colour", "seg_without_f", "seg_without_h", "map_start",
        "changed_target=edited", "recipe=staged")


@dataclass
class Args:
    out: Path = Path("bench_out/packed_parts")
    spacing: float = 0.025
    fit_steps: int = 300
    width: int = 384
    height: int = 288
    views: int = 16
    held_out: tuple[int, ...] = (1, 5, 9, 13)


def build(a: Args):
    pts = surface_points(SPEC, a.spacing)
    keep = torch.tensor([lab not in ("floor", "backdrop") for lab in pts.labels])
    labels = [lab for lab, k in zip(pts.labels, keep.tolist()) if k]
    g = gaussians_of(pts, a.spacing).index(keep)
    normals = pts.normals[keep].float()
    light = torch.nn.functional.normalize(torch.tensor(SPEC.light), dim=0)
    diffuse = pts.albedo[keep].float() * (0.45 + 0.55 * (normals @ light).clamp_min(0.0))[:, None]
    lo, hi = g.means.min(0).values - 0.1, g.means.max(0).values + 0.1
    torch.manual_seed(0)
    field = DecoupledColourField(ColourFieldConfig(levels=8, log2_hashmap_size=14, base_res=16, growth=1.6),
                                torch.stack([lo, hi]))
    target = torch.logit(diffuse.clamp(0.02, 0.98))
    opt = torch.optim.Adam(field.parameters(), lr=3e-2)
    for _ in range(a.fit_steps):
        loss = (field.diffuse(field.diffuse_hidden(field.encode(g.means))[1]) - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    for p in field.parameters():
        p.requires_grad_(False)
    scene = FrozenScene(g.means, g.quats, torch.exp(g.scales), torch.sigmoid(g.opacities), field, torch.ones(3),
                        backend="reference")
    return scene, scene_cameras(SPEC, a.views, a.width, a.height), labels


@contextmanager
def row_setting(row: str):
    """The engine changed for one row (restored after)."""
    inputs, share = SegmentationHead.inputs, engine_module.MAP_START_SHARE
    if row == "seg_without_f":
        SegmentationHead.inputs = lambda self, f, h: inputs(self, torch.zeros_like(f), h)
    elif row == "seg_without_h":
        SegmentationHead.inputs = lambda self, f, h: inputs(self, f, torch.zeros_like(h))
    elif row == "map_start":
        engine_module.MAP_START_SHARE = 0.0
    try:
        yield
    finally:
        SegmentationHead.inputs, engine_module.MAP_START_SHARE = inputs, share


def inner(scene, cam, sel: torch.Tensor) -> torch.Tensor:
    c = scene.contributions(cam, Request.whole_images(cam))
    mostly = (composite(sel[c.pair_gaussian.long()][:, None], c, 0.0)[0, ..., 0] > 0.7).float()
    return -torch.nn.functional.max_pool2d(-mostly[None, None], 3, 1, 1)[0, 0] > 0


def main(a: Args) -> None:
    torch.set_num_threads(1)
    scene, cams, labels = build(a)
    photo = render_view(scene, cams, 0)["rgb"].clamp(0, 1)
    edited, _ = recolor(photo, SPEC.rule)
    names = ("studs", "bolts", "toy")
    sel = {n: torch.tensor([lab == n for lab in labels]) for n in names}
    masks = {(v, n): inner(scene, cams.index(v), sel[n].float()) for v in (0, *a.held_out) for n in names}
    f, _, h2 = scene.gaussian_features(torch.arange(scene.means.shape[0]))
    out = {"gaussians": len(labels), "rows": {}}
    for row in ROWS:
        settings = {} if "=" not in row else {row.split("=")[0]: row.split("=")[1]}
        if "changed_share" in settings:
            settings["changed_share"] = float(settings["changed_share"])
        with row_setting(row):
            t0 = time.perf_counter()
            engine = EditEngine(scene, cams.index(0), edited, EditStack(scene.fingerprint()), EditConfig(**settings),
                                original=photo)
            edit, _ = engine.fit()
            fit_s = time.perf_counter() - t0
        stack = EditStack(scene.fingerprint())
        stack.add(edit)
        with torch.no_grad():
            alpha = edit.alpha(f, h2)[:, 0]
        res = {"fit_s": fit_s, "changed_fraction": engine.changed_fraction,
               "alpha": {n: float(alpha[sel[n]].mean()) for n in names}, "views": {}}
        for v in (0, *a.held_out):
            before = render_view(scene, cams, v)["rgb"].clamp(0, 1)
            after = render_view(scene, cams, v, stack)["rgb"].clamp(0, 1)
            truth, _ = recolor(before, SPEC.rule)
            res["views"][v] = {}
            for n in names:
                d = (after - (truth if n == "toy" else before)).abs()[masks[v, n]]
                res["views"][v][n] = {"pixels": int(d.shape[0]), "mean": float(d.mean()),
                                      "off": int((d.amax(-1) > 0.08).sum())}
        out["rows"][row] = res
        studs_txt = " ".join(f"v{v}:{r['studs']['off']}/{r['studs']['pixels']}" for v, r in res["views"].items())
        print(f"{row:26s} alpha studs {res['alpha']['studs']:.3f} bolts {res['alpha']['bolts']:.3f} | studs off "
              f"{studs_txt} | worst mean studs {max(r['studs']['mean'] for r in res['views'].values()):.3f} bolts "
              f"{max(r['bolts']['mean'] for r in res['views'].values()):.3f} toy vs rule "
              f"{max(r['toy']['mean'] for r in res['views'].values()):.3f}", flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "packed_parts.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(tyro.cli(Args))
