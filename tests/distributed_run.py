"""Training runs on several CPU processes (gloo) for the multi-process tests: the procedural capture
of :mod:`virgi_scene`, a few steps of each stage, every step's parameters recorded and compared
across the processes; and gsplat's densification step fed with constructed rasterizer outputs."""

from __future__ import annotations

import warnings
from pathlib import Path
from types import SimpleNamespace
from typing import Dict, List

import torch
import torch.distributed as dist

from method_configs.virgi import virgi_trainer_config
from virgi_ns.colour.field import ColourFieldConfig
from virgi_ns.nerfstudio import distributed
from virgi_ns.nerfstudio.geometry_stage import strategy_step
from virgi_ns.nerfstudio.pipeline import train_step, training_state
from virgi_ns.nerfstudio.trainer import for_processes

from virgi_scene import use_scene

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")
SEED = 42


def tiny_config(root: Path, how: str = "keep", geometry_steps: int = 3, colour_steps: int = 3, views: int = 2,
                batch_mode: str = "multiview", imported: Path | None = None, adam_eps: float | None = None):
    """Random-init geometry (150 Gaussians) trained ``geometry_steps`` steps of ``views`` views,
    then ``colour_steps`` colour steps of 2 multi-view mini-batches; or ``imported`` geometry.
    ``adam_eps`` replaces the recipe's 1e-15 in every optimizer (and drops the warm start)."""
    cfg = virgi_trainer_config("virgi-test", batch_mode=batch_mode, geometry_steps=0 if imported else geometry_steps,
                               colour_steps=colour_steps)
    cfg.machine.seed = SEED
    cfg.pipeline.multi_gpu_batch = how  # type: ignore[assignment]
    use_scene(cfg, SimpleNamespace(root=root), pixel_budget=5 * 256 * 2, cache_on_device=False)
    m = cfg.pipeline.model
    m.geometry_from = imported
    m.random_init = True
    m.num_random = 150
    m.random_scale = 1.0
    m.num_downscales = 0
    m.background_color = "black"
    m.color_field = ColourFieldConfig(log2_hashmap_size=12, levels=8, decoupled=batch_mode == "multiview")
    m.raster_backend = "reference"
    m.colour_init_steps = 20
    m.geometry_views_per_step = views
    cfg.optimizers["field_mlp"]["optimizer"].lr = 5e-3
    if adam_eps is not None:
        for group in cfg.optimizers.values():
            group["optimizer"].eps = adam_eps
        m.colour_init = "none"  # the warm start's own Adam keeps eps 1e-15
    return cfg


def state_of(model) -> Dict[str, torch.Tensor]:
    """The model's parameters and the colour field's box (copies)."""
    out = {k: v.detach().clone() for k, v in model.named_parameters()}
    out["field.aabb"] = model.field.aabb.detach().clone()
    return out


def same_on_every_process(tensors: Dict[str, torch.Tensor]) -> bool:
    """Whether every process holds bit-identical ``tensors`` (same sizes, same bits)."""
    sizes = torch.tensor([t.numel() for t in tensors.values()], dtype=torch.int64)
    flat = torch.cat([t.reshape(-1).float() for t in tensors.values()]).view(torch.int32)
    same = True
    for x in (sizes, flat):
        lo, hi = x.clone(), x.clone()
        dist.all_reduce(lo, op=dist.ReduceOp.MIN)
        dist.all_reduce(hi, op=dist.ReduceOp.MAX)
        same = same and torch.equal(lo, hi)
        if not same:
            break
    return same


def train(cfg, rank: int = 0, world: int = 1) -> dict:
    """Train ``cfg`` as process ``rank`` of ``world`` (seeded as nerfstudio's launcher seeds it).
    Returns every step's state and gradients, whether the processes agreed after it, and the
    colour batches' views."""
    torch.manual_seed(cfg.machine.seed + rank)
    if world > 1:
        cfg = for_processes(cfg, world)
    pipeline = cfg.pipeline.setup(device="cpu", test_mode="val", world_size=world, local_rank=rank)
    optimizers, callbacks = training_state(cfg, pipeline)
    model = pipeline.model
    states: List[Dict[str, torch.Tensor]] = []
    agreed: List[bool] = []
    views: List[List[int]] = []
    dm = pipeline.datamanager
    draw = dm.next_tile_batch

    def recording_draw(*args):
        tiles, batch = draw(*args)
        views.append(tiles.request.views.tolist())
        return tiles, batch

    dm.next_tile_batch = recording_draw
    grads: List[Dict[str, torch.Tensor]] = []
    for step in range(cfg.max_num_iterations):
        train_step(pipeline, optimizers, callbacks, step)
        states.append(state_of(model))
        # the gradients the optimizers stepped with (averaged over the processes)
        grads.append({k: p.grad.detach().clone() for k, p in model.named_parameters() if p.grad is not None})
        if world > 1:
            agreed.append(same_on_every_process(states[-1]))
    return {"states": states, "grads": grads, "agreed": agreed, "views": views, "frozen": model.geometry_frozen,
            "pixel_budget": cfg.pipeline.datamanager.pixel_budget, "steps": cfg.max_num_iterations}


# ------------------------------------------------------------------ densification
N_GAUSSIANS = 64
REFINE_EVERY = 2


def strategy_params() -> tuple[dict, dict]:
    """The same Gaussians and Adam optimizers on every process: half small (duplicated when their
    gradient is high), half large (split)."""
    g = torch.Generator().manual_seed(0)
    n = N_GAUSSIANS
    scales = torch.where(torch.arange(n)[:, None] % 2 == 0, torch.full((n, 3), 0.005), torch.full((n, 3), 0.05))
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        "scales": torch.nn.Parameter(torch.log(scales)),
        "quats": torch.nn.Parameter(torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)),
        "opacities": torch.nn.Parameter(torch.logit(torch.rand(n, generator=g) * 0.8 + 0.15)),
        "features_dc": torch.nn.Parameter(torch.rand(n, 3, generator=g)),
    })
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    return params, optimizers


def strategy(cls):
    """virgi's densification settings (the model's), refining every second step from step 0."""
    return cls(prune_opa=0.1, grow_grad2d=0.0008, grow_scale3d=0.01, grow_scale2d=0.05, prune_scale3d=0.5,
               prune_scale2d=0.15, refine_scale2d_stop_iter=4000, refine_start_iter=0, refine_stop_iter=15000,
               reset_every=3000, refine_every=REFINE_EVERY, pause_refine_after_reset=0, absgrad=True, verbose=False)


def view_info(process: int, step: int, scale: float = 1.0) -> dict:
    """What gsplat's rasterization returns for one 100x100 view of process ``process`` at ``step``
    (image-plane gradients, ``scale`` times, as after back-propagating a mean over 1 / scale views;
    screen radii, zero where the Gaussian is not seen): each process sees other Gaussians."""
    g = torch.Generator().manual_seed(1000 * process + step)
    n = N_GAUSSIANS
    seen = torch.rand(n, generator=g) < 0.7
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.absgrad = (torch.rand(1, n, 2, generator=g) * 4e-5 * seen[None, :, None]) * scale  # type: ignore[attr-defined]
    radii = (torch.rand(1, n, generator=g) * 12 * seen[None]).to(torch.int32)
    return {"means2d": means2d, "radii": radii, "width": 100, "height": 100, "n_cameras": 1, "gaussian_ids": None}


def densify(cls, infos_per_step: List[List[dict]]) -> tuple[dict, dict]:
    """Run ``cls``'s step after each step's ``infos`` (the last step refines); the resulting
    Gaussians and their Adam moments."""
    params, optimizers = strategy_params()
    s = strategy(cls)
    state = s.initialize_state(scene_scale=1.0)
    g = torch.Generator().manual_seed(1)
    for step, infos in enumerate(infos_per_step, start=1):
        for p in params.values():  # an optimizer step first, so the Adam moments follow the Gaussians
            p.grad = torch.randn(p.shape, generator=g)
        for o in optimizers.values():
            o.step()
        strategy_step(s, params, optimizers, state, step, infos)
    moments = {k: (o.state[o.param_groups[0]["params"][0]]["exp_avg"].clone()
                   if o.state.get(o.param_groups[0]["params"][0]) else None) for k, o in optimizers.items()}
    return {k: v.detach().clone() for k, v in params.items()}, moments


# ------------------------------------------------------------------ the processes
EXACT_EPS = 1e-6
"""Adam's eps for the runs compared with one process. The recipe's 1e-15 makes Adam's step a
step function of the gradient near 0: entries that are rounding noise around an exact 0 (the
quaternions of isotropic Gaussians, hash entries barely touched) move by +-lr with the sign of the
noise, which follows the order of float sums (one process on 1 and on 2 threads differs so too)."""


def cases(imported: Path) -> Dict[str, dict]:
    """The runs of the tests: tiny_config's arguments by name."""
    return {
        "keep": dict(how="keep", adam_eps=EXACT_EPS),
        "scale": dict(how="scale", geometry_steps=4, colour_steps=4, views=1),
        "singleview_keep": dict(how="keep", colour_steps=2, batch_mode="singleview", imported=imported,
                                adam_eps=EXACT_EPS),
    }


def worker(rank: int, world: int, root: Path, imported: Path, out: Path) -> None:
    """Every multi-process case of the tests, in one pair of processes (their start is the cost)."""
    from virgi_ns.nerfstudio.distributed import ReducedDefaultStrategy

    results = {name: train(tiny_config(root, **kwargs), rank, world) for name, kwargs in cases(imported).items()}
    params, moments = densify(ReducedDefaultStrategy, [[view_info(rank, 1)], [view_info(rank, 2)]])
    results["densified"] = {"params": params, "moments": moments,
                            "agreed": same_on_every_process(params)}
    torch.save(results, out / f"rank{rank}.pt")


def trainer_config(root: Path, out: Path):
    """tiny_config ('scale') as an ``ns-train`` run: a CPU, tensorboard, outputs under ``out``,
    an evaluation image every step."""
    cfg = tiny_config(root, "scale", geometry_steps=4, colour_steps=4, views=1)
    cfg.machine.device_type = "cpu"
    cfg.vis = "tensorboard"
    cfg.output_dir = out
    cfg.experiment_name = "tiny"
    cfg.timestamp = "run"
    cfg.steps_per_eval_image = 1
    cfg.steps_per_eval_all_images = 10**9
    cfg.steps_per_save = 10**9
    return cfg


def trainer_worker(rank: int, world: int, root: Path, out: Path) -> None:
    """nerfstudio's train_loop with virgi's trainer, as one of ``world`` processes."""
    cfg = trainer_config(root, out)
    torch.manual_seed(cfg.machine.seed + rank)
    torch.set_num_threads(distributed.host_threads())  # the trainer itself must share them out
    trainer = cfg.setup(local_rank=rank, world_size=world)
    trainer.setup()
    trainer.train()
    state = state_of(trainer.pipeline.model)
    torch.save({"state": state, "agreed": same_on_every_process(state), "steps": trainer.config.max_num_iterations,
                "optimizers": type(trainer.optimizers).__name__, "threads": torch.get_num_threads(),
                "host_threads": distributed.host_threads()},
               out / f"trainer_rank{rank}.pt")
