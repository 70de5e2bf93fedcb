"""Study (run once, then removed): the pick's two boundary rules measured apart on trained captures (issue 41, the rug's click): for each
scene, the bench's click with the rules as they are, without the depth cut, without the chroma band, and
without both; the selection's share, its IoU with the rule's mask, the pick's miss and leak."""
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, "bench")
import torch  # noqa: E402

import edit as bench_edit  # noqa: E402
from common.clicks import measure_pick  # noqa: E402
from common.evalset import find  # noqa: E402
from virgi_ns.edit import pick  # noqa: E402

out = {}
args = bench_edit.Args(data=Path(sys.argv[1]), train_out=Path(sys.argv[2]), seed=int(sys.argv[3]),
                       out=Path(sys.argv[2]) / "probe")
args.out.mkdir(parents=True, exist_ok=True)
jump0, band0 = pick.connected_to.__defaults__, pick.CHROMA_BAND
for name in sys.argv[4:]:
    scene = find([name])[0]
    b, view, cfg = bench_edit.scene_bench(args, scene, {})
    rows = {}
    for setting in ("as is", "no depth cut", "no chroma band", "neither"):
        d = list(jump0)
        d[-1] = math.inf if setting in ("no depth cut", "neither") else jump0[-1]
        pick.connected_to.__defaults__ = tuple(d)
        pick.CHROMA_BAND = 1e9 if setting in ("no chroma band", "neither") else band0
        p, _, _ = measure_pick(b, scene.rule, math.nan, click=scene.click)
        rows[setting] = {k: p[k] for k in ("selected", "iou", "propagation_psnr", "miss_psnr", "leak_psnr", "class")}
        print(name, setting, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in rows[setting].items()},
              flush=True)
    pick.connected_to.__defaults__, pick.CHROMA_BAND = jump0, band0
    out[name] = rows
    del b
    torch.cuda.empty_cache()
json.dump(out, open(Path(sys.argv[2]) / "pick_suspects.json", "w"), indent=1)
