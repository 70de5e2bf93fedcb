"""Probe (measured once on a CPU, no decision): the per-Gaussian colour correction of commit ae059cf's
``bench/per_gaussian_probe.py`` on a run trained elsewhere, in two forms, against the engine's fit: ``all`` spreads
the edit view's whole residual against the engine's target onto the Gaussians of each pixel
(``delta_i = sum_p w_pi r_p / (sum_p w_pi + 1)``, one step), ``unchanged`` only the residual of the pixels the edit
left unchanged. ``SOURCE=render+original`` fits the exact target (the rule on the edit view's render) instead of the
edited photo. Held-out figures against the rule on the render, and the recolour against the rule on the photos
minus the unedited render's PSNR.

    PYTHONPATH=bench python bench/per_gaussian_probe_cpu.py ../shared/data OUT 0 beercan demo_out/run/config.yml
"""
import json
import math
import os
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
    if len(sys.argv) > 5 and sys.argv[5].endswith("config.yml"):
        args.runs = {find([sys.argv[4]])[0].capture: Path(sys.argv[5])}
    for name in sys.argv[4:5]:
        scene = find([name])[0]
        b, _, _ = scene_bench(args, scene, {})
        src = os.environ.get("SOURCE", "photo")
        edited, original = b.edited_image(scene.rule, src), b.original(src)
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
            rule_p, _ = recolor(b.photos[i], scene.rule)
            r = {"prop": psnr(after, rule_r), "miss": psnr(after, rule_r, mask), "leak": psnr(after, rule_r, ~mask),
                 "rec": psnr(after, rule_p) - psnr(base, b.photos[i])}
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
    changed = b.fitted_target.changed.reshape(-1).to(w.device)
    for form in ("all", "unchanged"):
        delta = torch.zeros(b.scene.means.shape[0], 3, device=b.scene.device)
        r = (target - render(b.edit_camera, delta)).reshape(-1, 3)
        if form == "unchanged":
            r = torch.where(changed[:, None], torch.zeros_like(r), r)
        num = torch.zeros(seen.gaussians.shape[0], 3, device=w.device).index_add_(0, c.pair, w[:, None] * r[c.pixel])
        delta[seen.gaussians] += num / (wsum[:, None] + 1.0)
        print(json.dumps({"scene": name, "form": form, "lam": 1.0, "k": 1, **figures(delta)}), flush=True)


if __name__ == "__main__":
    main()
