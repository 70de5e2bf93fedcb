"""Probe (GPU machine of two GPUs): why a colour step took 10x longer in two processes than in one.

Times, in one process and then in two NCCL processes (one per GPU) side by side, an all-reduce of
12.6M floats (about the colour field's gradient) and a miniature of the colour batch's CPU work
(random scores, top-k, an index gather of 160 tiles of 32x32 from a uint8 image stack), with
torch's default thread pool (the whole host), half of it, and one thread per process. It ran as
``NCCL_NVLS_ENABLE=0 python3 bench/thread_probe.py``; ``bench/process_threads.py`` measures the
real batch drawing the same way.
"""
import os
import time

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

N_GRAD = 12_600_000  # about the hash grid's parameters


def cpu_ops(stack, n=60, reps=50):
    t0 = time.perf_counter()
    for _ in range(reps):
        score = torch.rand((72, n)) + (torch.rand((72, n)) > 0.5).float()
        top = score.topk(5, dim=1)
        ok = (score > 1).any(1).nonzero().flatten()[:32]
        idx = top.indices[ok]
        views = idx.reshape(-1)[:160]
        x0 = torch.randint(0, 470, (len(views),)); y0 = torch.randint(0, 340, (len(views),))
        ys = (y0[:, None] + torch.arange(32)); xs = (x0[:, None] + torch.arange(32))
        out = stack[views[:, None, None], ys[:, :, None], xs[:, None, :]]
        out = out.float() / 255.0
    return (time.perf_counter() - t0) / reps * 1e3


def worker(rank, world, threads):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT="29533")
    torch.cuda.set_device(rank)
    dist.init_process_group("nccl", rank=rank, world_size=world)
    if threads:
        torch.set_num_threads(threads)
    g = torch.randn(N_GRAD, device="cuda")
    for _ in range(3):
        dist.all_reduce(g)
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(20):
        dist.all_reduce(g)
    torch.cuda.synchronize()
    ar = (time.perf_counter() - t0) / 20 * 1e3
    stack = torch.randint(0, 255, (60, 378, 504, 3), dtype=torch.uint8)
    dist.barrier()
    c = cpu_ops(stack)
    dist.barrier()
    print(f"rank {rank} threads {torch.get_num_threads()}: all_reduce {N_GRAD/1e6:.1f}M floats {ar:.2f} ms; cpu ops {c:.2f} ms/step", flush=True)
    dist.destroy_process_group()


if __name__ == "__main__":
    print("cores", os.cpu_count(), "torch threads", torch.get_num_threads(), flush=True)
    stack = torch.randint(0, 255, (60, 378, 504, 3), dtype=torch.uint8)
    print(f"one process: cpu ops {cpu_ops(stack):.2f} ms/step", flush=True)
    for threads in (0, max(1, torch.get_num_threads() // 2), 1):
        mp.spawn(worker, args=(2, threads), nprocs=2, join=True)
