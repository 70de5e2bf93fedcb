"""Probe (to run once on a GPU, no decision): which of an edit's two heads limits it on a row.

For each named row of the evaluation set (trained fresh with ``SEED`` under ``TRAIN_OUT``, or a run given as
``CAPTURE=config.yml``), the engine's default fit (``SOURCE=render+original`` in the environment: fitted to the
exact target, the rule on the edit view's render), then each head refitted alone with the other replaced by an
oracle, on the engine's own target in the edit view (changed and unchanged pixels half the loss each, as the
engine's default share; Adam, :data:`STEPS` steps). Each pair's colour is ``sigmoid(alpha c_d' + (1 - alpha) c_d +
c_s)``:

- ``fitted``: the engine's edit (its figures are the bench's own);
- ``oracle segmentation``: alpha fixed to 1 on every Gaussian whose colour the rule takes and 0 elsewhere, the copied
  layer ``c_d'`` refitted from the engine's: how far the layer carries given a perfect segmentation;
- ``oracle layer``: ``c_d'`` fixed to the rule applied to each Gaussian's diffuse colour, the segmentation head
  refitted from the engine's: how far the segmentation carries given a perfect colour;
- ``both``: the two oracles, nothing fitted (close to the bench's diffuse ceiling).

The heads of a joint fit compensate each other (a soft segmentation, a layer past the target colour), so each
oracle's partner is refitted, not kept. One JSON line per row and way: held-out propagation / miss / leak against
the rule on the render, the mean alpha over the rule's mask, and the edit view's changed pixels against the target.

    PYTHONPATH=bench python bench/heads_oracle_probe.py DATA TRAIN_OUT SEED fox cup [CAPTURE=config.yml ...]
"""
import copy
import json
import math
import os
import sys
from pathlib import Path

import torch

from common.evalset import find
from edit import Args, scene_bench
from virgi_ns.bench.recolor import _mean, psnr
from virgi_ns.edit.recolor import recolor, rule_mask
from virgi_ns.raster import composite

STEPS = 300
LR = 1e-2


def oracle_alpha(view, rule) -> torch.Tensor:
    return rule_mask(torch.sigmoid(view.c_d.float() + view.c_s.float()), rule).float()[:, None]


def oracle_layer(view, rule) -> torch.Tensor:
    return torch.logit(recolor(torch.sigmoid(view.c_d.float()), rule)[0].clamp(1e-6, 1.0 - 1e-6))


def render(b, view, alpha: torch.Tensor, layer: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The view's image [H, W, 3] and segmentation [H, W] for per-pair ``alpha`` [U, 1] and ``layer`` [U, 3]."""
    c_d, c_s = view.c_d.float(), view.c_s.float()
    colours = torch.sigmoid(alpha * layer + (1.0 - alpha) * c_d + c_s)
    bg = b.scene.background.to(b.scene.device, torch.float32)
    return composite(colours, view.contrib, bg)[0], composite(alpha, view.contrib)[0][..., 0]


def heads(way: str, rule, seg, weight, bias):
    """(alpha of a view, c_d' of a view) for ``way`` with the heads ``seg`` and ``(weight, bias)``."""
    alpha = (lambda v: oracle_alpha(v, rule)) if way in ("oracle segmentation", "both") else \
        (lambda v: seg(v.feats, v.h_diff.float()).float())
    layer = (lambda v: oracle_layer(v, rule)) if way in ("oracle layer", "both") else \
        (lambda v: torch.nn.functional.linear(v.h_diff.float(), weight, bias))
    return alpha, layer


def refit(b, way: str, rule, edit, target: torch.Tensor, changed: torch.Tensor):
    """The heads of ``way``: the engine's (``fitted``), or one of them refitted against the other's oracle."""
    seg = copy.deepcopy(edit.seg).float()
    weight = edit.head_weight.detach().float().clone()
    bias = edit.head_bias.detach().float().clone()
    params = {"oracle segmentation": [weight, bias], "oracle layer": list(seg.parameters())}.get(way, [])
    if params:
        view = b.scene.view(b.edit_camera.index(0).to(b.scene.device, torch.float32))
        n_c = changed.sum().clamp_min(1)
        w = torch.where(changed, 0.5 / n_c, 0.5 / (~changed).sum().clamp_min(1)).float()
        for p in params:
            p.requires_grad_(True)
        opt = torch.optim.Adam(params, lr=LR)
        alpha_of, layer_of = heads(way, rule, seg, weight, bias)
        for _ in range(STEPS):
            opt.zero_grad()
            image, _ = render(b, view, alpha_of(view), layer_of(view))
            loss = ((image - target).abs().sum(-1) * w).sum()
            loss.backward()
            opt.step()
        for p in params:
            p.requires_grad_(False)
    return heads(way, rule, seg, weight, bias)


@torch.no_grad()
def figures(b, rule, alpha_of, layer_of, target: torch.Tensor, changed: torch.Tensor) -> dict:
    rows = []
    for cams, base in zip(b.views, b.base):
        view = b.scene.view(cams.index(0).to(b.scene.device, torch.float32))
        after, seg = render(b, view, alpha_of(view), layer_of(view))
        after = after.clamp(0, 1)
        truth, mask = recolor(base, rule)
        rows.append({"propagation": psnr(after, truth), "miss": psnr(after, truth, mask), "leak": psnr(after, truth, ~mask),
                     "alpha_in_mask": float(seg[mask].mean()) if bool(mask.any()) else math.nan})
    out = {k: round(_mean([r[k] for r in rows]), 3) for k in rows[0]}
    view = b.scene.view(b.edit_camera.index(0).to(b.scene.device, torch.float32))
    image, _ = render(b, view, alpha_of(view), layer_of(view))
    out["edit_view_changed_vs_target"] = round(psnr(image.clamp(0, 1), target, changed), 3)
    return out


def main() -> None:
    args = Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]))
    names = [a for a in sys.argv[4:] if "=" not in a]
    args.runs = {k: Path(v) for k, v in (a.split("=", 1) for a in sys.argv[4:] if "=" in a)}
    source = os.environ.get("SOURCE", "photo")
    for name in names:
        scene = find([name])[0]
        b, _, _ = scene_bench(args, scene, {})
        edit, _ = b.fit(b.edited_image(scene.rule, source), None, None, 1, b.original(source))
        target = b.fitted_target.image.reshape(b.edit_base.shape).to(b.scene.device).float()
        changed = b.fitted_target.changed.reshape(b.edit_base.shape[:2]).to(b.scene.device)
        for way in ("fitted", "oracle segmentation", "oracle layer", "both"):
            alpha_of, layer_of = refit(b, way, scene.rule, edit, target, changed)
            print(json.dumps({"scene": name, "source": source, "way": way,
                              **figures(b, scene.rule, alpha_of, layer_of, target, changed)}), flush=True)
        del b
        torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
