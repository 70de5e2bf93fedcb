"""Study (GPUs): where a step's time goes when ``ns-train virgi`` runs on N processes.

Each variant is one short run in a fresh interpreter, as bench/multi_gpu.py starts it, with every
process timing its own steps (median and 90th percentile per stage), its set-up, its evaluations and
checkpoints, the time its gradient average holds it (``reduce``: the host waits there for the slowest
process) and the colour batch's drawing (``draw``: it reads the GPU's projections, so it waits for the
GPU). Variants, each measuring one suspect apart:

- ``w1``, ``w2``, ``w4``: the recipe on 1, 2, 4 processes;
- ``warm``: a first run, not compared (it fills the disk cache and the loaded libraries');
- ``w2-nohostflags``: the gradient average without its exchange of has-a-gradient flags over gloo
  (each process's own flags taken as everyone's: a host-side barrier less every step);
- ``pair``: two independent one-process runs at once on GPUs 0 and 1 (the host shared, no collective);
- ``w1-gcfreeze``, ``w2-gcfreeze``: Python's garbage collector frozen after set-up (no pause over
  the set-up's objects);
- ``w2-profile``: torch's profiler over 30 steps of each stage, a table per process.

    python bench/multi_gpu_probe.py --data .data --out /tmp/runs/probe --steps 1200 --colour-steps 240
"""

from __future__ import annotations

import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List

import torch
import tyro

import multi_gpu as mg
from common.training import sync

PROFILE_STEPS = 30


@dataclass
class ProbeArgs:
    data: Path = Path(".data")
    out: Path = Path("/tmp/runs/probe")
    steps: int = 1200
    colour_steps: int = 240
    seed: int = 42
    device: str = "cuda"
    """'cpu': a check that the study runs (processes over gloo; figures meaningless)."""
    scene: str = "beercan"
    settings: str = ""
    variants: List[str] = field(default_factory=lambda: ["warm", "w1", "w1-gcfreeze", "pair", "w2", "w2-nohostflags",
                                                         "w2-gcfreeze", "w2-profile"])
    timeout: float = 120.0
    """Seconds a variant may take before it is stopped (a hung collective)."""


def _stats(xs: List[float]) -> Dict[str, float]:
    if not xs:
        return {}
    s = sorted(xs)
    return {"median_ms": 1e3 * statistics.median(s), "p90_ms": 1e3 * s[int(0.9 * (len(s) - 1))],
            "mean_ms": 1e3 * statistics.fmean(s), "n": len(s)}


def probe_worker(local_rank: int, world_size: int, config, global_rank: int = 0) -> None:
    import random

    import numpy as np

    from virgi_ns.nerfstudio import distributed

    variant = os.environ.get("PROBE_VARIANT", "")
    started = time.time()
    seed = config.machine.seed + global_rank
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    timers: Dict[str, float] = {"reduce_s": 0.0, "draw_s": 0.0, "eval_s": 0.0, "save_s": 0.0}
    inner_reduce = distributed.reduce_gradients
    if "nohostflags" in variant:  # every process's own has-a-gradient flags taken as everyone's

        def inner_reduce(params):
            n = distributed.world_size()
            unique = list({id(p): p for p in params}.values())
            grads = [p.grad for p in unique if p.grad is not None]
            if n > 1 and grads:
                def average(t):
                    distributed.dist.all_reduce(t)
                    t.div_(n)
                distributed._collective(grads, average)
    if True:

        def timed_reduce(params):
            t = time.perf_counter()
            inner_reduce(params)
            timers["reduce_s"] += time.perf_counter() - t

        distributed.reduce_gradients = timed_reduce
    if local_rank == 0:
        config.save_config()
    t = time.perf_counter()
    trainer = config.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    setup_s = time.perf_counter() - t
    if "gcfreeze" in variant:
        import gc

        gc.collect()
        gc.freeze()
    model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
    for obj, name, key in ((dm, "next_tile_batch", "draw_s"), (trainer, "eval_iteration", "eval_s"),
                           (trainer, "save_checkpoint", "save_s")):
        fn = getattr(obj, name)

        def timed(*a, _fn=fn, _key=key, **k):
            t0 = time.perf_counter()
            out = _fn(*a, **k)
            timers[_key] += time.perf_counter() - t0
            return out

        setattr(obj, name, timed)
    steps: List[tuple] = []
    inner = trainer.train_iteration
    prof = {"p": None, "windows": []}
    c0 = model.colour_start
    if "profile" in variant:
        g0 = min(200, c0 // 2)
        prof["windows"] = [("geometry", g0, g0 + PROFILE_STEPS), ("colour", c0 + 10, c0 + 10 + PROFILE_STEPS)]
    base = Path(config.get_base_dir())

    def timed_iteration(step: int):
        for name, a, b in prof["windows"]:
            if step == a:
                sync()
                prof["p"] = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                                               torch.profiler.ProfilerActivity.CUDA])
                prof["p"].__enter__()
        t0 = time.perf_counter()
        out = inner(step)
        steps.append((step, time.perf_counter() - t0))
        for name, a, b in prof["windows"]:
            if step == b - 1 and prof["p"] is not None:
                sync()
                p, prof["p"] = prof["p"], None
                p.__exit__(None, None, None)
                ka = p.key_averages()
                text = [f"{name} steps {a}..{b - 1}, rank {global_rank} of {world_size}",
                        ka.table(sort_by="self_cpu_time_total", row_limit=35),
                        ka.table(sort_by="self_device_time_total", row_limit=25)]
                (base / f"profile_{name}_rank{global_rank}.txt").write_text("\n".join(text))
        return out

    trainer.train_iteration = timed_iteration
    sync()
    t0 = time.perf_counter()
    trainer.train()
    sync()
    total = time.perf_counter() - t0
    last = steps[-1][0]
    geo = [s for i, s in steps if 20 <= i < c0 and not any(a <= i < b for _, a, b in prof["windows"])]
    col = [s for i, s in steps if c0 < i < last and not any(a <= i < b for _, a, b in prof["windows"])]
    row = {"variant": variant, "world": world_size, "rank": global_rank, "threads": torch.get_num_threads(),
           "worker_start_time": started, "end_time": time.time(), "setup_s": setup_s, "train_s": total,
           "iterations_s": sum(s for _, s in steps), "geometry": _stats(geo), "colour": _stats(col),
           "steps": len(steps), **timers, **{k: float(v) for k, v in model.stage_seconds.items()}}
    (base / f"probe_rank{global_rank}.json").write_text(json.dumps(row, indent=2))


def _cpu_worker(rank: int, world: int, config) -> None:
    probe_worker(rank, world, config, rank)


def _child(config_file: Path) -> None:
    config = pickle.loads(config_file.read_bytes())
    world = config.machine.num_devices
    if config.machine.device_type == "cuda":
        from nerfstudio.scripts.train import launch

        launch(probe_worker, num_devices_per_machine=world, device_type="cuda", config=config)
    elif world == 1:
        probe_worker(0, 1, config)
    else:
        from virgi_ns.nerfstudio.distributed import run_processes

        run_processes(_cpu_worker, world, config)


def start(args: ProbeArgs, variant: str, world: int, env: Dict[str, str], tag: str, tmp: Path):
    margs = mg.Args(data=args.data, out=args.out, steps=args.steps, colour_steps=args.colour_steps,
                    device=args.device, scene=args.scene, settings=args.settings)
    cfg = mg.run_config(margs, world, args.seed)
    cfg.experiment_name = f"{variant}{tag}"
    cfg_file = tmp / f"{variant}{tag}.pkl"
    cfg_file.write_bytes(pickle.dumps(cfg))
    e = {**os.environ, "PROBE_VARIANT": variant, **env}
    return cfg, subprocess.Popen([sys.executable, str(Path(__file__).resolve()), mg.CHILD_FLAG, str(cfg_file)], env=e,
                                 start_new_session=True)


def main(args: ProbeArgs) -> None:
    if args.device == "cuda":
        mg._build_cuda()
    rows = []
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for variant in args.variants:
            world = 4 if variant.startswith("w4") else 2 if variant.startswith("w2") else 1
            env = {"OMP_NUM_THREADS": "4"} if "threads4" in variant else {}
            t = time.time()
            if variant == "pair":
                procs = [start(args, variant, 1, {**env, "CUDA_VISIBLE_DEVICES": str(g)}, f"-gpu{g}", Path(tmp))
                         for g in (0, 1)]
            else:
                procs = [start(args, variant, world, env, "", Path(tmp))]
            for cfg, p in procs:
                try:
                    p.wait(timeout=max(1.0, args.timeout - (time.time() - t)))
                except subprocess.TimeoutExpired:
                    import signal

                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                    print(f"{cfg.experiment_name}: stopped after {args.timeout:.0f} s", flush=True)
                for f in sorted(Path(cfg.get_base_dir()).glob("probe_rank*.json")):
                    r = json.loads(f.read_text())
                    r["launch_s"] = r.pop("worker_start_time") - t
                    r["whole_s"] = r.pop("end_time") - t
                    r["run"] = cfg.experiment_name
                    rows.append(r)
                    g, c = r["geometry"], r["colour"]
                    print(f"{r['run']:>16} rank {r['rank']} thr {r['threads']:>2}: geo {g.get('median_ms', 0):6.2f} "
                          f"(p90 {g.get('p90_ms', 0):6.2f}) colour {c.get('median_ms', 0):6.2f} (p90 "
                          f"{c.get('p90_ms', 0):6.2f}) ms | reduce {r['reduce_s']:5.2f} draw {r['draw_s']:5.2f} "
                          f"eval {r['eval_s']:5.2f} save {r['save_s']:5.2f} s | launch {r['launch_s']:5.1f} setup "
                          f"{r['setup_s']:5.1f} train {r['train_s']:5.1f} whole {r['whole_s']:5.1f} s", flush=True)
            (args.out / "probe.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == mg.CHILD_FLAG:
        _child(Path(sys.argv[2]))
    else:
        main(tyro.cli(ProbeArgs))
