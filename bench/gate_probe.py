"""Probe (measured once, no decision): does deciding, per Gaussian, what the edited photo shows free the fit from
the trade between leak and miss?

The trade (RESULTS, "Where each miss comes from"): the segmentation head and the copied layer read hash features
that neighbouring Gaussians share, so the wallpaper between fox's roses and the banana's edge against the apple
are covered with the changed Gaussians, and whatever holds them to their colour pulls the layer off the changed
pixels' colour. The photo itself says which of the Gaussians it shows changed: each Gaussian the edit view sees
with at least one pixel's worth of weight (``mass >= 1``: below that the photo says little about it) is
"unchanged" where under half of its weight lands on changed pixels and "changed" where over half does
(the ``staged`` recipe's labels). Variants, each on the same training of each row:

- ``heads``: the defaults' fit, rendered as it is;
- ``off``: the same edit, alpha set to 0 at render time on the unchanged Gaussians;
- ``off+on``: also alpha set to 1 on the changed Gaussians;
- ``fit off``: the fit itself run with alpha 0 on the unchanged Gaussians (so they pull neither head), and
  rendered so;
- ``fit off+on``: the fit run and rendered with both;
- ``fit off any mass``: as ``fit off`` with every Gaussian the view sees labelled, however little (whether the
  one-pixel floor leaves the leak's Gaussians out).

Written before the run, what each outcome means: if ``fit off`` lifts fox's leak and propagation past 35 while
its miss stays within 1 dB of ``heads`` and fruit's miss stays >= 30, a per-Gaussian gate in the fit is the next
candidate (it needs the edit format to carry per-Gaussian values); if only ``off`` does, a gate applied after the
fit is; if ``off+on`` brings cup's hue error under 5 degrees, the changed Gaussians' partial alpha is item 2's
mechanism. One fit per row (seed 0), so a difference under about 0.5 dB is within one fit's spread.

    PYTHONPATH=bench python bench/gate_probe.py DATA TRAIN_OUT SEED OUT fox beercan ...
"""
import json
import sys
from pathlib import Path

import torch

from common.evalset import find
from edit import Args, scene_bench
from virgi_ns.bench.recolor import _save_png
from virgi_ns.edit.config import EditConfig
from virgi_ns.edit.engine import EditEngine
from virgi_ns.edit.scene import FrozenScene
from virgi_ns.edit.stack import Edit

GATE = {"render": None, "fit": None, "seen": None}  # (off [N] bool, on [N] bool) or None; the last view's Gaussians

_view, _alpha, _colours = FrozenScene.view, Edit.alpha, EditEngine.colours


def _gated(alpha, gaussians, gate):
    if gate is None or gaussians is None or gaussians.shape[0] != alpha.shape[0]:
        return alpha
    off, on = gate
    g = gaussians.to(off.device).long()
    alpha = torch.where(off[g][:, None], torch.zeros_like(alpha), alpha)
    return torch.where(on[g][:, None], torch.ones_like(alpha), alpha)


def view(self, camera, contrib=None):
    seen = _view(self, camera, contrib)
    GATE["seen"] = seen.gaussians
    return seen


def alpha(self, feats, h_diff):
    return _gated(_alpha(self, feats, h_diff), GATE["seen"], GATE["render"])


def colours(self):
    c_dp = torch.nn.functional.linear(self.h_diff, self.weight, self.bias)
    a = _gated(torch.sigmoid(self.seg.logits_of(self.seg_input)), self.gaussians, GATE["fit"])
    return torch.sigmoid(a * c_dp + (1.0 - a) * self.c_d + self.k * self.c_s), a


FrozenScene.view, Edit.alpha, EditEngine.colours = view, alpha, colours


def gate_of(eng: EditEngine, n: int, with_on: bool, min_mass: float = 1.0):
    c = eng.contrib
    dev = eng.h_diff.device
    pair, w = c.pair.to(dev).long(), c.weight.detach().to(dev).float()
    on_changed = eng.target.flat[c.pixel.to(dev).long()].float()
    u = eng.gaussians.numel()
    mass = torch.zeros(u, device=dev).index_add_(0, pair, w)
    share = torch.zeros(u, device=dev).index_add_(0, pair, w * on_changed) / mass.clamp_min(1e-12)
    seen = mass >= min_mass if min_mass > 0 else mass > 0
    off, on = torch.zeros(n, dtype=torch.bool, device=dev), torch.zeros(n, dtype=torch.bool, device=dev)
    g = eng.gaussians.to(dev).long()
    off[g[seen & (share < 0.5)]] = True
    if with_on:
        on[g[seen & (share > 0.5)]] = True
    return (off, on), {"unchanged_gaussians": int(off.sum()), "changed_gaussians": int((seen & (share > 0.5)).sum()),
                       "seen_gaussians": int(seen.sum()), "view_gaussians": u}


KEYS = ("propagation_psnr", "miss_psnr", "leak_psnr", "recolour_psnr", "unedited_psnr", "perfect_edit_recolour_psnr",
        "truth_psnr", "region_hue_error_deg", "region_saturation_error", "region_value_error", "alpha_in_mask",
        "alpha_out_mask", "edit_view_propagation_psnr", "edit_view_miss_psnr", "edit_view_leak_psnr",
        "per_gaussian_rule_propagation_psnr", "per_gaussian_rule_miss_psnr", "per_gaussian_rule_leak_psnr",
        "diffuse_rule_region_hue_error_deg")


def main() -> None:
    args = Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]))
    out = Path(sys.argv[4])
    out.mkdir(parents=True, exist_ok=True)
    for name in sys.argv[5:]:
        scene = find([name])[0]
        b, _, _ = scene_bench(args, scene, {})
        edited, original = b.edited_image(scene.rule, "photo"), b.original("photo")
        n = b.scene.means.shape[0]

        def fit(gate_with_on, min_mass=1.0):
            GATE["render"] = GATE["fit"] = None
            eng = EditEngine(b.scene, b.edit_camera, edited, cfg=EditConfig(fused_heads=gate_with_on is None),
                             original=original)
            gate, counts = gate_of(eng, n, bool(gate_with_on), min_mass)
            if gate_with_on is not None:
                GATE["fit"] = gate
            edit, timing = eng.fit()
            eng.changed_progress()  # measured under the fit's gate (kept until the heads change)
            GATE["fit"] = None
            return edit, eng, gate, counts, timing

        def record(label, edit, eng, render_gate, counts, timing):
            GATE["render"] = render_gate
            res, pics = b.measure(edit, scene.rule, lpips=False, keep=1, edited=edited, target=eng.target)
            GATE["render"] = None
            m = res["mean"]
            row = {"scene": name, "variant": label, **{k: m.get(k) for k in KEYS}, **counts,
                   "changed_progress": eng.changed_progress(), "fit_s": timing.total_s}
            print(json.dumps(row), flush=True)
            for p in pics:
                _save_png(out / f"{name}__{label.replace(' ', '_').replace('+', '_')}.png", p)

        edit, eng, gate, counts, timing = fit(None)
        record("heads", edit, eng, None, counts, timing)
        record("off", edit, eng, (gate[0], torch.zeros_like(gate[1])), counts, timing)
        both, counts_on = gate_of(eng, n, True)
        record("off+on", edit, eng, both, counts_on, timing)
        for with_on, min_mass, label in ((False, 1.0, "fit off"), (True, 1.0, "fit off+on"),
                                         (False, 0.0, "fit off any mass")):
            edit, eng, gate, counts, timing = fit(with_on, min_mass)
            record(label, edit, eng, gate, counts, timing)
        del b
        torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
