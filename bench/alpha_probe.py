"""Probe (measured once, no decision): each Gaussian's alpha corrected from the edit view's residual, after the
heads' fit.

The gate probe (``bench/gate_probe.py``, RESULTS) set alpha to 0 on every Gaussian the photo shows mostly
unchanged: fox's leak fell, but so did every row's miss, because a Gaussian straddling a changed pixel lost its
share of it. Here alpha moves only as far as the edit view's residual asks, along the one direction alpha can move a
Gaussian's colour (from its old colour to the copied layer's), so neither the photo's colour detail (what the per-
Gaussian colour correction fitted) nor a majority vote enters. One damped Jacobi step per Gaussian ``i`` the edit
view sees::

    J_i      = C_i (1 - C_i) (c_d'_i - c_d_i)                 (dC_i / d alpha_i, C_i its colour)
    delta_i  = sum_p w_pi J_i . r_p / (|J_i|^2 (sum_p w_pi + lam))
    alpha_i <- clamp(alpha_i + delta_i, 0, 1)

``r_p`` the edit view's residual against the engine's target (every pixel alike, as the held-out figures weigh
them). Spreading each pixel's residual in proportion to weight cannot overshoot a pixel (its weights sum to at
most 1), and ``lam = 1`` keeps a Gaussian seen through less than one pixel's worth of weight under half of what its
pixels ask (the rule the colour correction used). Written before the run: ``lam = 1``, one step, is the candidate
form; three steps and ``lam = 0.1`` show the mechanism. If the candidate form lifts fox's propagation past 35
while no row's miss falls by more than 1 dB, it is built into the edit (per-Gaussian alpha in the edit file).

    PYTHONPATH=bench python bench/alpha_probe.py DATA TRAIN_OUT SEED OUT fox fruit beercan ...
"""
import json
import sys
from pathlib import Path

import torch

from common.evalset import find
from edit import Args, scene_bench
from virgi_ns.edit.engine import EditEngine
from virgi_ns.edit.scene import FrozenScene, render_view
from virgi_ns.edit.stack import Edit, EditStack

STATE = {"delta": None, "seen": None}  # delta [N] added to every Gaussian's alpha (clamped); the last view's Gaussians
_view, _alpha = FrozenScene.view, Edit.alpha


def view(self, camera, contrib=None):
    seen = _view(self, camera, contrib)
    STATE["seen"] = seen.gaussians
    return seen


def alpha(self, feats, h_diff):
    a, d, g = _alpha(self, feats, h_diff), STATE["delta"], STATE["seen"]
    if d is None or g is None or g.shape[0] != a.shape[0]:
        return a
    return (a + d[g.to(d.device).long()][:, None].to(a)).clamp(0.0, 1.0)


FrozenScene.view, Edit.alpha = view, alpha

KEYS = ("propagation_psnr", "miss_psnr", "leak_psnr", "recolour_psnr", "unedited_psnr", "perfect_edit_recolour_psnr",
        "truth_psnr", "region_hue_error_deg", "region_saturation_error", "region_value_error", "alpha_in_mask",
        "alpha_out_mask", "edit_view_propagation_psnr", "edit_view_miss_psnr", "edit_view_leak_psnr",
        "per_gaussian_rule_miss_psnr", "per_gaussian_rule_propagation_psnr")


def correct(b, eng: EditEngine, stack: EditStack, delta: torch.Tensor, lam: float) -> None:
    """One Jacobi step of every seen Gaussian's alpha (``delta`` [N], in place)."""
    c, dev = eng.contrib, eng.h_diff.device
    g = eng.gaussians.to(dev).long()
    STATE["delta"] = delta
    render = render_view(b.scene, b.edit_camera, 0, stack)["rgb"]
    r = (eng.target.image.reshape(render.shape) - render).reshape(-1, 3)
    c_dp = torch.nn.functional.linear(eng.h_diff, eng.weight.detach(), eng.bias.detach())
    a = (torch.sigmoid(eng.seg.logits_of(eng.seg_input)) + delta[g][:, None]).clamp(0.0, 1.0)
    C = torch.sigmoid(a * c_dp + (1.0 - a) * eng.c_d + eng.k * eng.c_s)
    J = C * (1.0 - C) * (c_dp - eng.c_d)
    pair, w = c.pair.to(dev).long(), c.weight.detach().to(dev).float()
    u = g.numel()
    num = torch.zeros(u, device=dev).index_add_(0, pair, w * (J[pair] * r[c.pixel.to(dev).long()]).sum(-1))
    mass = torch.zeros(u, device=dev).index_add_(0, pair, w)
    step = num / ((J * J).sum(-1) * (mass + lam) + 1e-12)
    new = (a[:, 0] + step).clamp(0.0, 1.0)
    delta[g] += new - a[:, 0]


def main() -> None:
    args = Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]))
    out = Path(sys.argv[4])
    out.mkdir(parents=True, exist_ok=True)
    for name in sys.argv[5:]:
        scene = find([name])[0]
        b, _, _ = scene_bench(args, scene, {})
        edited, original = b.edited_image(scene.rule, "photo"), b.original("photo")
        n = b.scene.means.shape[0]
        STATE["delta"] = None
        eng = EditEngine(b.scene, b.edit_camera, edited, original=original)
        edit, timing = eng.fit()
        stack = EditStack(b.fingerprint)
        stack.to(b.scene.device)
        stack.add(edit)

        def record(label, delta):
            STATE["delta"] = delta
            res, _ = b.measure(edit, scene.rule, lpips=False, edited=edited, target=eng.target)
            STATE["delta"] = None
            m = res["mean"]
            moved = 0 if delta is None else int((delta.abs() > 1e-3).sum())
            print(json.dumps({"scene": name, "variant": label, **{k: m.get(k) for k in KEYS},
                              "gaussians_moved": moved, "view_gaussians": int(eng.gaussians.numel())}), flush=True)

        with torch.no_grad():
            record("heads", None)
            for lam in (1.0, 0.1):
                delta = torch.zeros(n, device=b.scene.device)
                for k in (1, 2, 3):
                    correct(b, eng, stack, delta, lam)
                    if k in (1, 3):
                        record(f"alpha lam {lam:g} steps {k}", delta)
        STATE["delta"] = None
        del b
        torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
