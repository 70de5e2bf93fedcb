"""Training on several processes (``ns-train virgi --machine.num-devices N``): replicated data
parallelism over ``torch.distributed``, without DDP.

Every process holds all Gaussians and the whole colour field and draws its own share of each
step's batch. Nothing here runs in a one-process run: every function returns at once there.

- The parameters start equal: :func:`broadcast_state` copies rank 0's after the model is built
  (nerfstudio seeds each process differently) and after every step that draws on a process's own
  random numbers (the box of the frozen means, the colour field's warm start).
- :class:`DistributedOptimizers` averages the gradients before each optimizer step. DDP does not
  fit: gsplat's densification replaces the Gaussian parameters, which DDP's reducer would keep
  reducing in their old form.
- :class:`ReducedDefaultStrategy` densifies and prunes from statistics summed over the processes,
  drawing the split offsets from a generator every process seeds alike, so all processes hold the
  same Gaussians after every refinement.
"""

from __future__ import annotations

import os
import socket
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Dict, Iterable, Iterator, List, Sequence

import torch
import torch.distributed as dist
from gsplat.strategy import DefaultStrategy
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.utils import comms
from torch import Tensor

BUCKET_ELEMENTS = 1 << 24
"""Tensors smaller than this are reduced together, flattened into buckets of about this size."""


# ------------------------------------------------------------------ the process group
def world_size() -> int:
    """Processes training together (1 without a process group)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def rank() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def is_main() -> bool:
    """Rank 0: the process that logs, evaluates and writes checkpoints."""
    return rank() == 0


def barrier() -> None:
    if world_size() == 1:
        return
    if dist.get_backend() == "nccl":
        dist.barrier(device_ids=[torch.cuda.current_device()])
    else:
        dist.barrier()


_DEFAULT_THREADS = torch.get_num_threads()
"""torch's thread count when this process started (its physical cores, or ``OMP_NUM_THREADS``)."""


def host_threads() -> int:
    """The CPU threads this process may use on its host before any share: torch's default, at most the
    CPUs it may run on."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(_DEFAULT_THREADS, cpus))


def processes_per_host(world: int) -> int:
    """How many of ``world`` processes share this host: nerfstudio's per-machine process group where
    its launcher (or :func:`run_processes`) made one, else all of them."""
    if dist.is_available() and dist.is_initialized() and comms.LOCAL_PROCESS_GROUP is not None:
        return max(1, comms.get_local_size())
    return max(1, world)


GPU_PROCESS_THREADS = 16
"""At most this many CPU threads in a process that drives a GPU. Its CPU work is small ops between
kernel launches (the colour stage's batch drawing), whose thread pool must not take every core
from the process's own launching thread: with a pool as wide as a large host the drawing runs slower by an
order of magnitude."""


def share_cpu_threads(world: int, device_type: str = "cpu") -> int:
    """Give this process its share of the host's CPU threads (:func:`host_threads` over the processes
    on the host, at most :data:`GPU_PROCESS_THREADS` where it drives a GPU); returns the count it now
    uses.

    Every process otherwise sizes torch's thread pool for the whole host, and the colour stage's
    batch drawing (small CPU ops each step) then waits on threads the other processes, or its own
    launching thread, hold. A CPU-only process alone keeps the whole host (the reference rasterizer
    is its work). ``OMP_NUM_THREADS``, where set, is the user's choice and is kept."""
    if os.environ.get("OMP_NUM_THREADS"):
        return torch.get_num_threads()
    gpu = device_type == "cuda"
    if world <= 1 and not gpu:
        return torch.get_num_threads()
    threads = max(1, host_threads() // processes_per_host(world))
    if gpu:
        threads = min(threads, GPU_PROCESS_THREADS)
    torch.set_num_threads(threads)
    return threads


def prepare_cuda(device) -> None:
    """Pin this process to its GPU (splatfacto puts tensors on the current device) and load
    gsplat's and virgi's CUDA code with rank 0 first: the first use compiles them, and a second
    process starting gsplat's build removes the first one's build folder."""
    dev = torch.device(device)
    if dev.type != "cuda" or world_size() == 1:
        return
    torch.cuda.set_device(dev)

    def load() -> None:
        from gsplat.cuda._backend import _C  # noqa: F401  (compiles on first use)

        from virgi_ns.raster import cuda

        cuda.available()  # builds or loads the rasterizer; a failure is reported where it is used

    if is_main():
        load()
    barrier()
    if not is_main():
        load()


# ------------------------------------------------------------------ collectives
_HOST_GROUP = None


def _host_group():
    """A process group over gloo for host-side collectives (made on first use, which every process
    reaches at the same step): exchanging a few flags over NCCL would make the host wait for the GPU."""
    global _HOST_GROUP
    if _HOST_GROUP is None:
        _HOST_GROUP = dist.group.WORLD if dist.get_backend() == "gloo" else dist.new_group(backend="gloo")
    return _HOST_GROUP


def _buckets(tensors: Sequence[Tensor]) -> Iterator[List[Tensor]]:
    """Groups of tensors of one dtype and device: a large tensor alone, small ones together."""
    group: List[Tensor] = []
    size = 0
    for t in tensors:
        if group and (t.dtype != group[0].dtype or t.device != group[0].device or size + t.numel() > BUCKET_ELEMENTS):
            yield group
            group, size = [], 0
        group.append(t)
        size += t.numel()
    if group:
        yield group


def _collective(tensors: Sequence[Tensor], op: Callable[[Tensor], None]) -> None:
    """Apply ``op`` (an in-place collective) to every bucket of ``tensors``, in place."""
    with torch.no_grad():
        for group in _buckets(tensors):
            if len(group) == 1 and group[0].is_contiguous():
                op(group[0])
                continue
            flat = torch.cat([t.reshape(-1) for t in group])
            op(flat)
            for t, part in zip(group, flat.split([t.numel() for t in group])):
                t.copy_(part.view_as(t))


def broadcast_state(module: torch.nn.Module, src: int = 0) -> None:
    """Give every process rank ``src``'s floating-point parameters and buffers of ``module``."""
    if world_size() == 1:
        return
    tensors = [t.data for t in (*module.parameters(), *module.buffers()) if t.is_floating_point() and t.numel()]
    _collective(tensors, lambda t: dist.broadcast(t, src))


def broadcast_tensor(t: Tensor, src: int = 0) -> None:
    if world_size() > 1:
        dist.broadcast(t, src)


def all_sum(t: Tensor) -> Tensor:
    """The sum of ``t`` over the processes (a new tensor; ``t`` itself in one process)."""
    if world_size() == 1:
        return t
    t = t.clone()
    dist.all_reduce(t)
    return t


def reduce_gradients(params: Iterable[Tensor]) -> None:
    """Average the gradients of ``params`` over the processes, in place.

    A parameter that has no gradient on any process keeps none (the optimizer skips it, as in one
    process); one that has a gradient on some processes only joins with zeros elsewhere."""
    n = world_size()
    seen, unique = set(), []
    for p in params:
        if id(p) not in seen:
            seen.add(id(p))
            unique.append(p)
    if n == 1 or not unique:
        return
    has = torch.tensor([p.grad is not None for p in unique], dtype=torch.int32)  # on the host: no GPU sync
    dist.all_reduce(has, group=_host_group())
    live = [p for p, h in zip(unique, has.tolist()) if h]
    for p in live:
        if p.grad is None:
            p.grad = torch.zeros_like(p)

    def average(t: Tensor) -> None:
        dist.all_reduce(t)
        t.div_(n)

    _collective([p.grad for p in live], average)


# ------------------------------------------------------------------ optimizers
class DistributedOptimizers(Optimizers):
    """nerfstudio's optimizers, averaging the gradients over the processes before they step.

    The parameters are read from the optimizers themselves when they step: gsplat's densification
    replaces the Gaussian parameters inside them, so a list taken at set-up would go stale."""

    def _reduce(self, names: Iterable[str]) -> None:
        reduce_gradients(p for name in names for g in self.optimizers[name].param_groups for p in g["params"])

    def optimizer_step(self, param_group_name: str) -> None:
        self._reduce([param_group_name])
        super().optimizer_step(param_group_name)

    def optimizer_step_all(self) -> None:
        self._reduce(self.optimizers)
        super().optimizer_step_all()

    def optimizer_scaler_step_all(self, grad_scaler) -> None:
        self._reduce(self.optimizers)
        super().optimizer_scaler_step_all(grad_scaler)

    def optimizer_scaler_step_some(self, grad_scaler, param_groups: List[str]) -> None:
        self._reduce(param_groups)
        super().optimizer_scaler_step_some(grad_scaler, param_groups)


def make_optimizers(config: Dict, param_groups: Dict[str, List]) -> Optimizers:
    """nerfstudio's :class:`Optimizers` in one process, :class:`DistributedOptimizers` in several."""
    cls = DistributedOptimizers if world_size() > 1 else Optimizers
    return cls(config, param_groups)


# ------------------------------------------------------------------ densification
@contextmanager
def shared_rng(device: torch.device, seed: int) -> Iterator[None]:
    """Within the block, ``device``'s default generator is seeded with ``seed``; restored after."""
    cuda = device.type == "cuda"
    with torch.random.fork_rng(devices=[device] if cuda else []):
        gen = torch.cuda.default_generators[device.index if device.index is not None else torch.cuda.current_device()] \
            if cuda else torch.default_generator
        gen.manual_seed(seed)
        yield


@dataclass
class ReducedDefaultStrategy(DefaultStrategy):
    """gsplat's :class:`DefaultStrategy` for several processes, each accumulating the statistics of
    its own views: at each refinement the accumulated image-plane gradients and visibility counts
    are summed over the processes and the screen radii maximised (so each decides from every
    view, as one process seeing them all would), and the split offsets come from a generator
    seeded by the step alone."""

    def _grow_gs(self, params, optimizers, state, step):
        if world_size() > 1:
            for key, op in (("grad2d", dist.ReduceOp.SUM), ("count", dist.ReduceOp.SUM),
                            ("radii", dist.ReduceOp.MAX)):
                if state.get(key) is not None:
                    dist.all_reduce(state[key], op=op)
        with shared_rng(params["means"].device, step):
            return super()._grow_gs(params, optimizers, state, step)


# ------------------------------------------------------------------ processes on a CPU
def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gloo_worker(process: int, fn: Callable, world: int, port: int, args: tuple) -> None:
    global _HOST_GROUP
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=process, world_size=world)
    comms.LOCAL_PROCESS_GROUP = dist.new_group(list(range(world)))  # as nerfstudio's launcher sets it
    share_cpu_threads(world)
    try:
        fn(process, world, *args)
        dist.barrier()  # no process closes its connections while another still talks over them
    finally:
        dist.destroy_process_group()
        # drop every reference to the groups while the interpreter is alive: a group that outlives it
        # stops its gloo threads during finalization, which can abort the process after its work is done
        comms.LOCAL_PROCESS_GROUP = None
        _HOST_GROUP = None


def run_processes(fn: Callable, world: int, *args) -> None:
    """Run ``fn(rank, world, *args)`` in ``world`` new processes joined by a gloo process group:
    nerfstudio's launcher on a CPU (that launcher requires CUDA). For tests and the benchmark's
    CPU check; ``fn`` and ``args`` must pickle."""
    import torch.multiprocessing as mp

    mp.spawn(_gloo_worker, args=(fn, world, _free_port(), args), nprocs=world)


__all__ = ["DistributedOptimizers", "ReducedDefaultStrategy", "all_sum", "barrier", "broadcast_state",
           "broadcast_tensor", "is_main", "make_optimizers", "prepare_cuda", "rank", "reduce_gradients",
           "host_threads", "processes_per_host", "run_processes", "share_cpu_threads", "shared_rng", "world_size"]
