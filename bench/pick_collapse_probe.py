"""Probe (measured once, no decision): why the blowtorch click of run set 93 changed nothing (its segmentation
ended at alpha 0 over a selection of 80% of the view). On a fresh training of run set ``SEED``, the bench's click
(``common/clicks.py``) refitted: ``EditConfig.seed`` 0..4 (one fit's chance, or the setting's), the changed pixels
at their own share of the loss (``changed_share`` = the selected share: each pixel weighs alike), and the
``staged`` recipe (a classifier of the selected Gaussians first). One JSON line per fit, with the edit view's mean
alpha over the selection.

    python bench/pick_collapse_probe.py DATA TRAIN_OUT SEED [ROW]
"""
import json
import math
import sys
from pathlib import Path

import virgi_ns.edit.pick as pick
from common import clicks
from common.evalset import find
from edit import Args, scene_bench
from virgi_ns.edit.scene import render_view


def main() -> None:
    args = Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]))
    scene = find([sys.argv[4] if len(sys.argv) > 4 else "blowtorch"])[0]
    b, _, _ = scene_bench(args, scene, {})
    default_config, default_commit = pick.pick_config, pick.commit
    seen = {}

    def watched_commit(stack, session, edit, replace=None):
        n = default_commit(stack, session, edit, replace)
        seg = render_view(b.scene, b.edit_camera, 0, stack, seg_index=1)["segmentation"][..., 0]
        sel = session.mask.to(seg.device)
        seen.update(alpha_in_selection=float(seg[sel].mean()), alpha_outside=float(seg[~sel].mean()),
                    selected=float(sel.float().mean()))
        return n

    settings = [("seed", {"seed": s}) for s in range(5)] + [("share", {"changed_share": None}), ("staged", {"recipe": "staged"})]
    for label, change in settings:
        def configured(device, _change=change):
            cfg = default_config(device)
            for k, v in _change.items():
                setattr(cfg, k, seen.get("selected", 0.5) if v is None else v)
            return cfg
        pick.pick_config, pick.commit = configured, watched_commit
        p, _, _ = clicks.measure_pick(b, scene.rule, math.nan, keep=0, click=scene.click)
        keys = ("propagation_psnr", "miss_psnr", "leak_psnr", "edit_view_propagation_psnr", "fit_s")
        print(json.dumps({"probe": label, **change, **{k: round(p[k], 3) for k in keys}, "pixel": p["pixel"],
                          "colour": p["colour"], **{k: round(v, 4) for k, v in seen.items()}}), flush=True)
    pick.pick_config, pick.commit = default_config, default_commit


if __name__ == "__main__":
    main()
