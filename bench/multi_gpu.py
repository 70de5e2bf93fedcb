"""Benchmark (GPUs): ``ns-train virgi`` on N GPUs against one, as a person runs it.

For each seed, the recipe with ``--steps`` geometry + ``--colour-steps`` colour steps on one GPU,
then on each N of ``--worlds`` with the default 'scale' batch: each process draws a one-GPU batch,
so a step sees N times the views and the run takes 1/N of the steps (the same views seen).

Every run is a fresh interpreter started as ``ns-train`` starts one (nerfstudio's ``launch``, one
process per GPU), with the recipe's own evaluations and checkpoints, so the whole run's wall time
(``whole_run_s``: from starting the interpreter to the final checkpoint written) is what a person
waits for. Columns: steps/s of each stage (geometry steps after the first 20; colour steps but
the first, which holds the warm start, and the last, which measures the specular gate), each
stage's speed-up in views (pixels) per second over one GPU (N x the ratio of steps/s, same
per-process batch), the whole run's speed-up, held-out PSNR / SSIM (every 8th view), Gaussians.
A summary per N over the seeds: mean speed-ups and the PSNR against one GPU's spread over the
seeds. Writes ``results.json``.

    python bench/multi_gpu.py --data .data --out /tmp/runs/multi --worlds 1 2 4 --seeds 42 43

On a CPU (``--device cpu``) the processes join over gloo: a check that the script runs, with
``--settings`` making the recipe tiny (as tests/test_multi_gpu_bench.py runs it).
"""

from __future__ import annotations

import json
import os
import pickle
import random
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Dict, List, Literal

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.table import Table

from common.settings import apply_settings
from common.training import dataparser_for, evaluate, train
from virgi_ns.errors import InputError, atomic_path, cli_entry

# NVLink multicast stays off (the GPU machines' rule: it can take the host's GPUs out of service)
for _name, _value in (("NCCL_NVLS_ENABLE", "0"), ("TORCH_SYMM_MEM_DISABLE_MULTICAST", "1"),
                      ("NVSHMEM_DISABLE_NVLS", "1")):
    os.environ.setdefault(_name, _value)

console = Console()
RESULT = "bench_rank0.json"
CHILD_FLAG = "--one-run"


@dataclass
class Args:
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    """Folder holding the scene folders (COLMAP, LLFF or nerfstudio's transforms.json)."""
    out: Path = Path("bench_out/multi_gpu")
    scene: str = "beercan"
    steps: int = 7000
    """Geometry steps on one GPU (N GPUs: steps / N)."""
    colour_steps: int = 1000
    """Colour steps on one GPU (N GPUs: colour_steps / N)."""
    worlds: List[int] = field(default_factory=lambda: [1, 2])
    """Process counts to train with (1 is the reference)."""
    seeds: List[int] = field(default_factory=lambda: [42])
    device: Literal["cuda", "cpu"] = "cuda"
    settings: str = ""
    """More config settings, 'a.b.c=value,...' (dotted TrainerConfig paths, as bench/train.py's)."""
    warmup: bool = True
    """First an untimed short run on one process: the first run of a fresh machine pays for reading the
    libraries and the images from a cold disk (measured: 10-15 s more), which no row should carry."""
    merge: List[Path] = field(default_factory=list)
    """Train nothing: read the rows of these results.json files (seeds split over calls on one
    machine), print the tables and write them all to --out/results.json."""


def run_config(args: Args, world: int, seed: int):
    """The recipe as ``ns-train virgi --machine.num-devices world`` runs it (its evaluations and
    checkpoints kept), writing under ``args.out`` without a viewer."""
    from method_configs.virgi import virgi_trainer_config

    cfg = virgi_trainer_config("virgi", geometry_steps=args.steps, colour_steps=args.colour_steps)
    cfg.pipeline.datamanager.dataparser = dataparser_for(args.scene, args.data)
    cfg.machine.seed = seed
    cfg.machine.num_devices = world
    cfg.machine.device_type = args.device
    cfg.vis = "tensorboard"
    cfg.output_dir = args.out / "runs"
    cfg.experiment_name = f"{args.scene}-n{world}-s{seed}"
    cfg.timestamp = "run"
    cfg.viewer.quit_on_train_completion = True
    if args.settings:
        apply_settings(cfg, args.settings, "--settings")
    return cfg


def steps_per_s(ms) -> float:
    """Steps per second from the mean step in milliseconds (NaN where no step was timed)."""
    return 1e3 / ms if ms is not None and ms > 0 else float("nan")


def worker(local_rank: int, world_size: int, config, global_rank: int = 0) -> None:
    """One process of a run, as nerfstudio's ``train_loop`` (seeded by rank), timed as
    bench/train.py times it; rank 0 notes when the final checkpoint was written, evaluates, and
    writes its figures beside the run."""
    started = time.time()
    seed = config.machine.seed + global_rank
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    trainer, secs, _, parts = train(config, local_rank, world_size)
    if global_rank == 0:
        done = time.time()  # train() returns once the final checkpoint is on disk
        res = evaluate(trainer.pipeline, 0, None)
        cfg = trainer.config  # as the processes trained it (the batch rule applied)
        row = {"world": world_size, "seed": config.machine.seed, "train_s": secs, "checkpoint_time": done,
               "worker_start_time": started,
               "geometry_steps": cfg.pipeline.model.geometry_steps,
               "colour_steps": cfg.max_num_iterations - cfg.pipeline.model.geometry_steps,
               "views_per_geometry_step": cfg.pipeline.model.geometry_views_per_step,
               "pixels_per_colour_step": cfg.pipeline.datamanager.pixel_budget,
               "geometry_steps_per_s": steps_per_s(parts.get("geometry_step_ms")),
               "colour_steps_per_s": steps_per_s(parts.get("colour_step_ms")),
               **res, "train_breakdown": parts}
        with atomic_path(Path(config.get_base_dir()) / RESULT) as tmp:
            tmp.write_text(json.dumps(row, indent=2))


def _cpu_worker(rank: int, world: int, config) -> None:
    worker(rank, world, config, rank)


def _child(config_file: Path) -> None:
    """The body of one run's interpreter: what ``ns-train`` does after parsing its arguments."""
    config = pickle.loads(config_file.read_bytes())
    world = config.machine.num_devices
    if config.machine.device_type == "cuda":
        from nerfstudio.scripts.train import launch

        launch(worker, num_devices_per_machine=world, device_type="cuda", config=config)
    elif world == 1:
        worker(0, 1, config)
    else:
        from virgi_ns.nerfstudio.distributed import run_processes

        run_processes(_cpu_worker, world, config)


def run(args: Args, world: int, seed: int, name_suffix: str = "") -> Dict[str, object]:
    """Train one run in a fresh interpreter; its row, with ``whole_run_s`` from the interpreter's
    start to the final checkpoint (``launch_s`` of it before rank 0's process starts its work)."""
    cfg = run_config(args, world, seed)
    cfg.experiment_name += name_suffix
    path = Path(cfg.get_base_dir()) / RESULT
    path.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        config_file = Path(tmp) / "config.pkl"
        config_file.write_bytes(pickle.dumps(cfg))
        start = time.time()
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), CHILD_FLAG, str(config_file)])
    if proc.returncode != 0 or not path.is_file():
        raise InputError(f"the run with {world} processes failed (exit {proc.returncode}; {path})")
    row = json.loads(path.read_text())
    row["whole_run_s"] = row.pop("checkpoint_time") - start
    row["launch_s"] = row.pop("worker_start_time") - start  # interpreter, imports, process spawn
    return row


def speedups(rows: List[Dict[str, object]]) -> None:
    """Each row's speed-up over the one-process row of its seed: per stage in views (pixels) per
    second, and for the whole run in wall time (both runs see the same views)."""
    ref = {r["seed"]: r for r in rows if r["world"] == 1}
    for r in rows:
        one = ref.get(r["seed"])
        for stage in ("geometry", "colour"):
            key = f"{stage}_steps_per_s"
            r[f"{stage}_speedup"] = (r["world"] * r[key] / one[key]) if one else float("nan")
        r["whole_run_speedup"] = one["whole_run_s"] / r["whole_run_s"] if one else float("nan")
        r["psnr_minus_one_gpu"] = r["psnr"] - one["psnr"] if one else float("nan")


def summary(rows: List[Dict[str, object]]) -> List[Dict[str, object]]:
    """Per N: the mean speed-ups over the seeds, and whether every run's PSNR lies within one GPU's
    spread over the seeds (its lowest to its highest run)."""
    one = [r["psnr"] for r in rows if r["world"] == 1]
    lo, hi = (min(one), max(one)) if one else (float("nan"), float("nan"))
    out = []
    for world in sorted({r["world"] for r in rows}):
        rs = [r for r in rows if r["world"] == world]
        psnr = [r["psnr"] for r in rs]
        diff = [r["psnr_minus_one_gpu"] for r in rs]
        out.append({"world": world, "runs": len(rs), "psnr_mean": statistics.fmean(psnr),
                    "psnr_std": statistics.stdev(psnr) if len(psnr) > 1 else float("nan"),
                    "psnr_range": [min(psnr), max(psnr)],
                    "psnr_within_one_gpu_spread": all(lo <= p <= hi for p in psnr),
                    "psnr_minus_one_gpu_mean": statistics.fmean(diff),
                    "psnr_minus_one_gpu_range": [min(diff), max(diff)],
                    "whole_run_s_mean": statistics.fmean(r["whole_run_s"] for r in rs),
                    "geometry_speedup": statistics.fmean(r["geometry_speedup"] for r in rs),
                    "colour_speedup": statistics.fmean(r["colour_speedup"] for r in rs),
                    "whole_run_speedup": statistics.fmean(r["whole_run_speedup"] for r in rs)})
    return out


def print_tables(rows: List[Dict[str, object]], summ: List[Dict[str, object]], device: str) -> None:
    t = Table(title=f"virgi on N processes vs one ({device}; speed-up: views or pixels per second, whole run: wall)")
    cols = [("world", "N"), ("seed", "seed"), ("geometry_steps", "geo steps"), ("colour_steps", "colour steps"),
            ("geometry_steps_per_s", "geo steps/s"), ("colour_steps_per_s", "colour steps/s"),
            ("geometry_speedup", "geo speed-up"), ("colour_speedup", "colour speed-up"),
            ("whole_run_s", "whole run s"), ("whole_run_speedup", "whole speed-up"), ("psnr", "PSNR"),
            ("ssim", "SSIM"), ("gaussians", "Gaussians")]
    for _, name in cols:
        t.add_column(name, justify="right")
    for r in rows:
        t.add_row(*(f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k, _ in cols))
    console.print(t)
    s = Table(title="per N over the seeds")
    for name in ("N", "runs", "PSNR", "within 1-GPU spread", "PSNR - 1 GPU (range)", "geo speed-up",
                 "colour speed-up", "whole run s", "whole speed-up"):
        s.add_column(name, justify="right")
    for r in summ:
        lo, hi = r["psnr_minus_one_gpu_range"]
        s.add_row(str(r["world"]), str(r["runs"]), f"{r['psnr_mean']:.2f} +- {r['psnr_std']:.2f}",
                  "yes" if r["psnr_within_one_gpu_spread"] else "no",
                  f"{r['psnr_minus_one_gpu_mean']:+.2f} ({lo:+.2f}..{hi:+.2f})", f"{r['geometry_speedup']:.2f}x",
                  f"{r['colour_speedup']:.2f}x", f"{r['whole_run_s_mean']:.1f}", f"{r['whole_run_speedup']:.2f}x")
    console.print(s)


def _build_cuda() -> None:
    """Compile (or load) gsplat's and virgi's CUDA code before anything is timed."""
    from gsplat.cuda._backend import _C  # noqa: F401

    from virgi_ns.raster import cuda

    cuda.available()


def merged_rows(files: List[Path]) -> tuple[str, List[Dict[str, object]]]:
    """The rows of several results.json files of one device; refuses files of different devices."""
    rows, devices = [], set()
    for f in files:
        if not f.is_file():
            raise InputError(f"--merge: no such file: {f}")
        res = json.loads(f.read_text())
        devices.add(res["device"])
        rows += res["rows"]
    if len(devices) != 1:
        raise InputError(f"--merge: the files were measured on different devices ({sorted(devices)})")
    return devices.pop(), rows


def report(args: Args, device: str, rows: List[Dict[str, object]]) -> None:
    speedups(rows)
    summ = summary(rows)
    print_tables(rows, summ, device)
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out / "results.json") as tmp:
        tmp.write_text(json.dumps({"device": device, "args": str(args), "rows": rows, "summary": summ}, indent=2))


def main(args: Args) -> None:
    if args.merge:
        report(args, *merged_rows(args.merge))
        return
    if 1 not in args.worlds:
        raise InputError("--worlds must hold 1: the other runs are measured against it")
    for world in args.worlds:
        run_config(args, world, args.seeds[0])  # a missing scene or a bad setting: before any run
    if args.device == "cuda":
        if torch.cuda.device_count() < max(args.worlds):
            raise InputError(f"--worlds {max(args.worlds)} needs that many GPUs; {torch.cuda.device_count()} visible")
        _build_cuda()
        device = f"{torch.cuda.device_count()} x {torch.cuda.get_device_name(0)}"
    else:
        device = "CPU (gloo)"
    args.out.mkdir(parents=True, exist_ok=True)
    if args.warmup:
        short = replace(args, steps=min(args.steps, 100), colour_steps=min(args.colour_steps, 20))
        console.log(f"warm-up run (not timed): {short.steps} + {short.colour_steps} steps on one process")
        run(short, 1, args.seeds[0], name_suffix="-warmup")
    rows: List[Dict[str, object]] = []
    for seed in args.seeds:
        for world in sorted(args.worlds):
            rows.append(run(args, world, seed))
            console.log({k: v for k, v in rows[-1].items() if k != "train_breakdown"})
            with atomic_path(args.out / "results.json") as tmp:  # after every run: a cut-off call keeps them
                tmp.write_text(json.dumps({"device": device, "args": str(args), "rows": rows}, indent=2))
    report(args, device, rows)


def entrypoint() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == CHILD_FLAG:
        _child(Path(sys.argv[2]))
        return
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
