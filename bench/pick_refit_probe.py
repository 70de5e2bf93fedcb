"""Probe (measured once, no decision): is a pick that fell far below the rule edit one fit's collapse? The
glossy ball's click of the bench (``common/clicks.py``) on a fresh training of run set ``SEED``, refitted with
``EditConfig.seed`` 0..4; one JSON line per fit.

    python bench/pick_refit_probe.py DATA TRAIN_OUT SEED
"""
import json
import math
import sys
from pathlib import Path

import virgi_ns.edit.pick as pick
from common import clicks
from common.evalset import find
from edit import Args, scene_bench


def main() -> None:
    args = Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]))
    scene = find(["syn_glossy_ball"])[0]
    b, _, _ = scene_bench(args, scene, {})
    default_config = pick.pick_config
    for seed in range(5):
        def seeded(device, _seed=seed):
            cfg = default_config(device)
            cfg.seed = _seed
            return cfg
        pick.pick_config = seeded  # measure_pick imports it at each call
        p, _, _ = clicks.measure_pick(b, scene.rule, math.nan, keep=0, click=scene.click)
        keys = ("propagation_psnr", "miss_psnr", "leak_psnr", "edit_view_propagation_psnr")
        print(json.dumps({"seed": seed, **{k: round(p[k], 2) for k in keys}, "pixel": p["pixel"],
                          "colour": p["colour"], "selected": round(p["selected"], 4)}), flush=True)
    pick.pick_config = default_config


if __name__ == "__main__":
    main()
