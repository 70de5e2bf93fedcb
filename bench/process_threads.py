"""Benchmark: the colour stage's batch drawing in N processes on one host, by CPU threads per process.

Each process draws colour-stage batches as training does (``sample_tiles`` over random opaque
anchors and 60 ring cameras, the tiles' valid mask, ``_gather_tiles`` from an image stack on the
device, nerfstudio's default cache), while the other processes do the same, and all-reduces a
gradient the size of the colour field's. Rows: one process; N processes with torch's default
thread pool each (the whole host: what nerfstudio's launcher leaves); N with
:func:`~virgi_ns.nerfstudio.distributed.share_cpu_threads` (the trainer's); N with one thread each.
Prints a table and writes ``process_threads.json``.

    PYTHONPATH=. python bench/process_threads.py --out bench_out/process_threads [--world 2]

On a GPU machine of N GPUs the processes join over NCCL, one per GPU; elsewhere over gloo on the CPU.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.distributed as dist
import tyro
from rich.console import Console
from rich.table import Table

# NVLink multicast stays off (the GPU machines' rule, as in bench/multi_gpu.py)
os.environ.setdefault("NCCL_NVLS_ENABLE", "0")
console = Console()
VIEWS, H, W = 60, 378, 504
GAUSSIANS = 150_000
GRAD_FLOATS = 12_600_000
"""About the colour field's parameters (16 hash levels of up to 2^19 x 2 features, and the MLPs)."""


@dataclass
class Args:
    out: Path = Path("bench_out/process_threads")
    world: int = 2
    steps: int = 50
    """Batches drawn (and all-reduces) per row, after 5 of warm-up."""


def ring_cameras(n: int, device: torch.device):
    """``n`` cameras on a ring of radius 4 around the origin, looking at it."""
    from virgi_ns.raster import Cameras

    mats = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = torch.tensor([4 * math.cos(a), 4 * math.sin(a), 1.0])
        fwd = -eye / eye.norm()
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0]))
        right = right / right.norm()
        down = torch.linalg.cross(fwd, right)
        R = torch.stack([right, down, fwd])
        m = torch.eye(4)
        m[:3, :3], m[:3, 3] = R, -R @ eye
        mats.append(m)
    return Cameras.from_params(400.0, 400.0, W / 2, H / 2, torch.stack(mats).to(device), W, H)


def measure(steps: int, device: torch.device) -> dict:
    """Median ms of one batch drawn and of one all-reduce of the field's gradient, in this process."""
    from virgi_ns.nerfstudio.datamanager import _gather_tiles, sample_tiles
    from virgi_ns.nerfstudio.distributed import world_size

    g = torch.Generator().manual_seed(0)
    means = (torch.rand(GAUSSIANS, 3, generator=g) * 2 - 1).to(device)
    pool = torch.arange(GAUSSIANS, device=device)
    cams = ring_cameras(VIEWS, device)
    stack = torch.randint(0, 255, (VIEWS, H, W, 3), dtype=torch.uint8, generator=g).to(device)
    grad = torch.randn(GRAD_FLOATS if device.type == "cuda" else GRAD_FLOATS // 64, device=device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    draw, reduce = [], []
    for i in range(steps + 5):
        sync()
        t0 = time.perf_counter()
        req = sample_tiles(means, pool, cams, 32, 5, 163840, "multiview", g)
        gt = _gather_tiles(stack, req, req.valid_mask(cams)).float() / 255.0
        sync()
        t1 = time.perf_counter()
        if world_size() > 1:
            dist.all_reduce(grad)
        sync()
        t2 = time.perf_counter()
        if i >= 5:
            draw.append((t1 - t0) * 1e3)
            reduce.append((t2 - t1) * 1e3)
        del gt
    return {"draw_ms": statistics.median(draw), "all_reduce_ms": statistics.median(reduce),
            "threads": torch.get_num_threads()}


def _worker(rank: int, world: int, port: int, threads: str, steps: int, out: str) -> None:
    from virgi_ns.nerfstudio.distributed import share_cpu_threads

    cuda = torch.cuda.is_available() and torch.cuda.device_count() >= world
    if cuda:
        torch.cuda.set_device(rank)
    dist.init_process_group("nccl" if cuda else "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank,
                            world_size=world)
    try:
        if threads == "share":
            share_cpu_threads(world)
        elif threads == "one":
            torch.set_num_threads(1)
        res = measure(steps, torch.device("cuda", rank) if cuda else torch.device("cpu"))
        Path(out, f"rank{rank}.json").write_text(json.dumps(res))
    finally:
        dist.destroy_process_group()


def run_row(args: Args, threads: str) -> dict:
    """One row: ``args.world`` processes with ``threads`` ("whole host", "share" or "one")."""
    import tempfile

    import torch.multiprocessing as mp

    from virgi_ns.nerfstudio.distributed import _free_port

    with tempfile.TemporaryDirectory() as tmp:
        mp.spawn(_worker, args=(args.world, _free_port(), threads, args.steps, tmp), nprocs=args.world)
        ranks = [json.loads(Path(tmp, f"rank{r}.json").read_text()) for r in range(args.world)]
    return {"processes": args.world, "threads_rule": threads, "threads": ranks[0]["threads"],
            "draw_ms": max(r["draw_ms"] for r in ranks), "all_reduce_ms": max(r["all_reduce_ms"] for r in ranks)}


def main(args: Args) -> None:
    if "OMP_NUM_THREADS" in os.environ:
        raise SystemExit("unset OMP_NUM_THREADS: the rows set the threads themselves")
    args.out.mkdir(parents=True, exist_ok=True)
    cuda = torch.cuda.is_available() and torch.cuda.device_count() >= args.world
    device = torch.device("cuda", 0) if cuda else torch.device("cpu")
    one = {"processes": 1, "threads_rule": "whole host", **measure(args.steps, device)}
    one.pop("all_reduce_ms")
    rows = [one] + [run_row(args, t) for t in ("whole host", "share", "one")]
    for r in rows:
        r["draw_vs_one_process"] = r["draw_ms"] / one["draw_ms"]
    name = torch.cuda.get_device_name(0) if cuda else "CPU"
    res = {"device": f"{args.world if cuda else 1} x {name}", "cores": len(os.sched_getaffinity(0)),
           "steps": args.steps, "rows": rows}
    t = Table(title=f"colour batch drawing in {args.world} processes ({res['device']}, {res['cores']} cores)")
    for c in ("processes", "threads rule", "threads each", "draw ms", "x one process", "all-reduce ms"):
        t.add_column(c, justify="right")
    for r in rows:
        ar = r.get("all_reduce_ms")
        t.add_row(str(r["processes"]), r["threads_rule"], str(r["threads"]), f"{r['draw_ms']:.2f}",
                  f"{r['draw_vs_one_process']:.2f}x", "-" if ar is None else f"{ar:.2f}")
    console.print(t)
    (args.out / "process_threads.json").write_text(json.dumps(res, indent=2))
    console.print(f"wrote {args.out / 'process_threads.json'}")


if __name__ == "__main__":
    main(tyro.cli(Args))
