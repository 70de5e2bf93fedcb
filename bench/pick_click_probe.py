"""Probe (to run once on a GPU, no decision): why a click's selection stops at a few pixels (fern, run set 91).

For each seed, the fern row is trained fresh (``SEED`` under ``TRAIN_OUT``), its bench click made as
``common/clicks.py`` ``measure_pick`` makes it, and the selection grown with each of ``select``'s chroma-steps tests
switched off in turn: the hue angle, the chroma band of the pixel, the chroma band of its median contributor
(``surface``), and the chroma steps between neighbours. One JSON line per seed with each selection's share of the view,
and the view maps (render, diffuse, accumulation, surface, depth) saved to ``OUT/fern_sSEED_maps.pt`` with the click.

    PYTHONPATH=bench python bench/pick_click_probe.py DATA TRAIN_OUT OUT 91 93
"""
import json
import math
import os
import sys
from pathlib import Path

import torch

from common.clicks import click_pixel, coverage, mask_class
from common.evalset import find
from edit import Args, scene_bench
from virgi_ns.edit import pick
from virgi_ns.edit.recolor import rule_mask


def grown(maps, x, y, tol, hue=True, band=True, surface=True, steps=True) -> float:
    ch = pick.chromaticity(maps.diffuse)
    chroma = ch.norm(dim=-1)
    at = float(chroma[y, x])
    b = 1.0 + pick.CHROMA_BAND * tol
    allowed = maps.accumulation >= pick.MIN_COVER
    if hue:
        allowed &= pick._angle(ch, ch[y, x]) <= 90.0 * tol
    if band:
        allowed &= pick._in_band(chroma, at, b)
    if surface and maps.surface is not None:
        allowed &= pick._in_band(pick.chromaticity(maps.surface).norm(dim=-1), at, b)
    allowed[y, x] = True
    value = torch.log(chroma.clamp_min(1e-6)) if steps else None
    sel = pick.connected_to(allowed, x, y, value, math.log(1.0 + 4.0 * tol) if steps else 0.0)
    return float(sel.float().mean())


def main() -> None:
    data, train_out, out = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    out.mkdir(parents=True, exist_ok=True)
    scene = find([os.environ.get("SCENE", "fern")])[0]
    runs = {k: Path(v) for k, v in (a.split("=", 1) for a in sys.argv[4:] if "=" in a)}
    for seed in (int(s) for s in sys.argv[4:] if "=" not in s):
        args = Args(data=data, train_out=train_out, seed=seed)
        args.runs = runs
        b, _, _ = scene_bench(args, scene, {})
        render = b.edit_base
        mask = rule_mask(render, scene.rule)
        clickable = mask & (coverage(b.scene, b.edit_camera) >= pick.MIN_COVER)
        klass, share = mask_class(clickable, scene.click)
        x, y, depth = click_pixel(clickable)
        session = pick.PickSession(b.scene, b.edit_camera, x, y, None, pick.pick_config(b.scene.device))
        maps, tol = session.maps, 0.2
        ch = pick.chromaticity(maps.diffuse)
        row = {"seed": seed, "pixel": [x, y], "depth": depth, "class": klass, "rule_share": float(mask.float().mean()),
               "click_chroma": float(ch[y, x].norm()), "click_surface_chroma":
               float(pick.chromaticity(maps.surface)[y, x].norm()), "click_accumulation": float(maps.accumulation[y, x]),
               "selected": float(pick.select(maps, x, y, tol).float().mean())}
        for name, kw in (("all tests", {}), ("no hue", {"hue": False}), ("no band", {"band": False}),
                         ("no surface band", {"surface": False}), ("no chroma steps", {"steps": False}),
                         ("only hue", {"band": False, "surface": False, "steps": False})):
            row[name] = grown(maps, x, y, tol, **kw)
        print(json.dumps(row), flush=True)
        torch.save({"x": x, "y": y, **{k: getattr(maps, k).detach().cpu() for k in
                                      ("rgb", "diffuse", "accumulation", "depth", "surface")},
                    "rule_mask": mask.cpu()}, out / f"{scene.name}_s{seed}_maps.pt")
        del b, session
        torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
