"""Where an edit's time goes on a GPU: the torch profiler over one warm edit (set-up, then steps) on
the edit benchmark's 1M-Gaussian 1280x720 scene, the top operations by GPU and by CPU time.

    python bench/profile_edit.py --out bench_out/profile_edit [--steps 100]
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from edit import million_scene  # noqa: E402

from virgi_ns.edit.engine import EditConfig, EditEngine  # noqa: E402


@dataclass
class Args:
    out: Path = Path("bench_out/profile_edit")
    steps: int = 100
    rows: int = 25


def table(prof, key: str, rows: int) -> str:
    return prof.key_averages().table(sort_by=key, row_limit=rows, max_name_column_width=60)


def main(args: Args) -> None:
    from torch.profiler import ProfilerActivity, profile, record_function

    args.out.mkdir(parents=True, exist_ok=True)
    scene, cams = million_scene()
    scene.precompute_features()
    edited = torch.rand(720, 1280, 3, generator=torch.Generator(device="cuda").manual_seed(1), device="cuda")
    cfg = EditConfig(steps=args.steps)
    for _ in range(2):  # warm-up: kernels loaded, graphs recorded, allocator filled
        EditEngine(scene, cams, edited, cfg=cfg).fit()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        with record_function("edit_setup"):
            eng = EditEngine(scene, cams, edited, cfg=cfg)
            torch.cuda.synchronize()
        with record_function("edit_steps"):
            _, timing = eng.fit()
            torch.cuda.synchronize()
    text = (f"setup {timing.setup_s * 1e3:.1f} ms, steps {timing.steps_s * 1e3:.1f} ms ({args.steps} steps)\n\n"
            f"by GPU time\n{table(prof, 'cuda_time_total', args.rows)}\n\nby CPU time\n"
            f"{table(prof, 'cpu_time_total', args.rows)}\n")
    print(text)
    (args.out / "profile.txt").write_text(text)
    (args.out / "timing.json").write_text(json.dumps({"setup_s": timing.setup_s, "steps_s": timing.steps_s}))


if __name__ == "__main__":
    main(tyro.cli(Args))
