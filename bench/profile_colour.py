"""Profile (GPU): where a colour-stage training step's time goes.

Trains ``virgi`` on a capture through nerfstudio's Trainer (a short geometry stage, then the colour
stage) and runs torch's profiler over ``--profile-steps`` colour steps after ``--skip`` warm-up
steps. Prints the synchronised wall time per step and the top operators by GPU and by CPU time,
and writes ``profile.json`` (the tables as text and the step times).

    python bench/profile_colour.py --data .data --scene beercan --geometry-steps 3000
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

from virgi_ns.errors import InputError, atomic_path, cli_entry


@dataclass
class Args:
    data: Path = Path(".data")
    scene: str = "beercan"
    out: Path = Path("bench_out/profile")
    geometry_steps: int = 3000
    skip: int = 40
    """Colour steps run before profiling (allocator and caches settle)."""
    profile_steps: int = 20
    row_limit: int = 30


def main(args: Args) -> None:
    if not torch.cuda.is_available():
        raise InputError("bench/profile_colour.py needs a CUDA GPU")
    warnings.filterwarnings("ignore", category=FutureWarning)
    from torch.profiler import ProfilerActivity, profile

    from bench.train import dataparser_for, quiet
    from method_configs.virgi import virgi_trainer_config
    from virgi_ns.metrics import offline_splatfacto_lpips

    offline_splatfacto_lpips()
    colour = args.skip + args.profile_steps + 1
    cfg = virgi_trainer_config("virgi", geometry_steps=args.geometry_steps, colour_steps=colour)
    cfg.pipeline.datamanager.dataparser = dataparser_for(args.scene, args.data)
    quiet(cfg, args.out, f"{args.scene}-profile")
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    first = args.geometry_steps + args.skip
    last = first + args.profile_steps
    inner = trainer.train_iteration
    step_ms: list[float] = []
    prof = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA])
    callback_ms: list[float] = []
    run_cb = type(trainer.callbacks[0]).run_callback_at_location

    def timed(step: int):
        if step == first:
            torch.cuda.synchronize()
            prof.__enter__()
        torch.cuda.synchronize()
        t = time.perf_counter()
        out = inner(step)
        torch.cuda.synchronize()
        if first <= step < last:
            step_ms.append(1e3 * (time.perf_counter() - t))
        if step == last - 1:
            prof.__exit__(None, None, None)
        return out

    def timed_cb(self, step, location):
        if not first <= step < last:
            return run_cb(self, step, location)
        torch.cuda.synchronize()
        t = time.perf_counter()
        run_cb(self, step, location)
        torch.cuda.synchronize()
        callback_ms.append(1e3 * (time.perf_counter() - t))

    trainer.train_iteration = timed  # type: ignore[method-assign]
    type(trainer.callbacks[0]).run_callback_at_location = timed_cb
    trainer.train()
    n = max(len(step_ms), 1)
    by_gpu = prof.key_averages().table(sort_by="cuda_time_total", row_limit=args.row_limit)
    by_cpu = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.row_limit)
    print(by_gpu)
    print(by_cpu)
    summary = {"device": torch.cuda.get_device_name(0), "gaussians": int(trainer.pipeline.model.num_points),
               "step_ms_mean": sum(step_ms) / n, "step_ms": step_ms,
               "callbacks_ms_per_step": sum(callback_ms) / n}
    print(json.dumps({k: v for k, v in summary.items() if k != "step_ms"}, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out / "profile.json") as tmp:
        tmp.write_text(json.dumps({**summary, "by_gpu": by_gpu, "by_cpu": by_cpu}, indent=1))


if __name__ == "__main__":
    cli_entry(lambda: main(tyro.cli(Args)))
