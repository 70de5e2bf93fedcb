"""Study (CPU): how many sphere directions the export's SH fit needs, at equal fidelity.

For a trained run, bake with ``BakeConfig(directions=D)`` for each D (the training cameras' directions,
at most 64, always join them) and compare, for every Gaussian the specular gate keeps (the view-dependent
ones; the others bake exactly), its baked SH colour with the model's own colour
``sigmoid(c_d + c_s(d))`` along the direction from each held-out camera: PSNR over those (Gaussian,
view) colours, the bake's seconds, and off the cameras: the colours seen from 32 random directions
against the first D's bake (PSNR) and the share clipped at 1. Run dataparser frame (no frame change), no edits.

    python bench/bake_directions.py --load-config demo_out/run/config.yml
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

import torch
import tyro

from virgi_ns.colour.sh import view_colours
from virgi_ns.nerfstudio.export import BakeConfig, bake
from virgi_ns.nerfstudio.frames import CaptureFrame
from virgi_ns.nerfstudio.runs import open_run


@dataclass
class Args:
    load_config: Path
    directions: List[int] = field(default_factory=lambda: [128, 96, 64, 48, 32, 16])
    repeats: int = 2
    out: Path = Path("/tmp/bake_directions.json")


@torch.no_grad()
def main(args: Args) -> None:
    opened = open_run(args.load_config)
    model = opened.model
    fld = model.field
    means = model.means.detach()
    gate = model.spec_gate
    idx = gate.nonzero().flatten()
    m = means[idx]
    f = fld.encode(m)
    h1, h2 = fld.diffuse_hidden(f)
    c_d = fld.diffuse(h2)
    held = opened.eval.cameras() if opened.eval is not None else opened.train.cameras()
    centres = held.camera_centers().to(means.dtype)
    truth = [torch.sigmoid(c_d + fld.specular(f, torch.nn.functional.normalize(m - c, dim=-1), h1, h2))
             for c in centres]
    gen = torch.Generator().manual_seed(0)
    anywhere = torch.nn.functional.normalize(torch.randn(32, 3, generator=gen), dim=-1).to(means)
    reference = None
    rows = []
    for d in args.directions:
        secs = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            g = bake(model, None, 1.0, CaptureFrame.identity(), opened.train.cameras(), BakeConfig(directions=d))
            secs.append(time.perf_counter() - t)
        sh = g.sh[idx]
        se = sum(float(((view_colours(sh, m, c) - t_) ** 2).mean()) for c, t_ in zip(centres, truth)) / len(truth)
        worst = max(float(((view_colours(sh, m, c) - t_) ** 2).mean(-1).max()) for c, t_ in zip(centres, truth))
        # off the cameras: 32 directions uniform on the sphere, against the first D's bake
        off = torch.stack([view_colours(sh, m, m[0] * 0 - a * 1e3 + m.mean(0)) for a in anywhere])
        if reference is None:
            reference = off
        se_off = float(((off - reference) ** 2).mean())
        rows.append({"directions": d, "psnr": -10 * torch.log10(torch.tensor(se)).item(),
                     "worst_gaussian_mse": worst, "bake_s": min(secs),
                     "psnr_off_cameras_vs_first": -10 * torch.log10(torch.tensor(max(se_off, 1e-20))).item(),
                     "off_cameras_clipped_share": float((off >= 1.0).float().mean())})
        print(rows[-1], flush=True)
    args.out.write_text(json.dumps({"run": str(args.load_config), "gaussians": int(means.shape[0]),
                                    "view_dependent": int(idx.numel()), "held_out_views": len(centres),
                                    "rows": rows}, indent=2))


if __name__ == "__main__":
    main(tyro.cli(Args))
