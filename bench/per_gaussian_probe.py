"""Probe (measured once, no decision): how far a per-Gaussian colour correction carries an edit past what its
heads can fit.

For each named row of the evaluation set (trained fresh with ``SEED`` under ``TRAIN_OUT``), the engine's default
fit, then its edit view's residual against the engine's own target spread onto the Gaussians that make each pixel,
a damped Jacobi step: ``delta_i = sum_p w_pi r_p / (sum_p w_pi + lam)``, added to each Gaussian's final colour in
every view. Prints one JSON line per setting: held-out propagation / miss / leak (and truth on a synthetic row)
against the rule on the render, and the edit view against the rule and against the target. Written before the
run: ``lam = 1`` (a Gaussian seen through less than one pixel's worth of weight keeps under half of its pixels'
residual) with one step is the candidate form; ``lam = 0.1`` and three steps show the mechanism.

    python bench/per_gaussian_probe.py DATA TRAIN_OUT SEED fox syn_toy_on_white syn_duck_beak beercan
"""
import json
import math
import sys
from pathlib import Path

import torch

from common.evalset import find
from edit import Args, scene_bench
from virgi_ns.bench.recolor import psnr
from virgi_ns.edit.recolor import recolor
from virgi_ns.edit.scene import render_view
from virgi_ns.edit.stack import EditStack


def main() -> None:
    args = Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]))
    for name in sys.argv[4:]:
        scene = find([name])[0]
        b, _, _ = scene_bench(args, scene, {})
        edited, original = b.edited_image(scene.rule, "photo"), b.original("photo")
        edit, _ = b.fit(edited, None, None, 1, original)
        target = b.fitted_target.image.reshape(edited.shape).to(b.scene.device)
        stack = EditStack(b.fingerprint)
        stack.to(b.scene.device)
        stack.add(edit)
        with torch.no_grad():
            probe_scene(b, scene, stack, target, name)
        del b
        torch.cuda.empty_cache()


def probe_scene(b, scene, stack, target, name: str) -> None:
    def render(cams, delta):
        g = b.scene.view(cams.index(0).to(b.scene.device, torch.float32)).gaussians
        cmap = None if delta is None else (lambda c: (c + delta[g]).clamp(0.0, 1.0))
        return render_view(b.scene, cams, 0, stack, colour_map=cmap)["rgb"].clamp(0, 1)

    def figures(delta):
        rows = []
        for i, (cams, base) in enumerate(zip(b.views, b.base)):
            after = render(cams, delta)
            rule_r, mask = recolor(base, scene.rule)
            r = {"prop": psnr(after, rule_r), "miss": psnr(after, rule_r, mask), "leak": psnr(after, rule_r, ~mask)}
            if b.truths is not None:
                r["truth"] = psnr(after, b.truths[i])
            rows.append(r)
        out = {k: sum(r[k] for r in rows if not math.isnan(r[k])) / max(1, sum(not math.isnan(r[k]) for r in rows))
               for k in rows[0]}
        ev = render(b.edit_camera, delta)
        rule_e, _ = recolor(b.edit_base, scene.rule)
        out["edit_view_prop"], out["edit_view_target"] = psnr(ev, rule_e), psnr(ev, target)
        return {k: round(v, 2) for k, v in out.items()}

    seen = b.scene.view(b.edit_camera.index(0).to(b.scene.device, torch.float32))
    c = seen.contrib
    w = c.weight.float()
    wsum = torch.zeros(seen.gaussians.shape[0], device=w.device).index_add_(0, c.pair, w)
    print(json.dumps({"scene": name, "k": 0, **figures(None)}), flush=True)
    for lam in (1.0, 0.1):
        delta = torch.zeros(b.scene.means.shape[0], 3, device=b.scene.device)
        for k in (1, 2, 3):
            r = (target - render(b.edit_camera, delta)).reshape(-1, 3)
            num = torch.zeros(seen.gaussians.shape[0], 3, device=w.device).index_add_(0, c.pair, w[:, None] * r[c.pixel])
            delta[seen.gaussians] += num / (wsum[:, None] + lam)
            if k in (1, 3):
                print(json.dumps({"scene": name, "lam": lam, "k": k, **figures(delta)}), flush=True)


if __name__ == "__main__":
    main()
