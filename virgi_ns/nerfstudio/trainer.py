"""virgi's trainer: nerfstudio's, sizing each process's CPU thread pool
(:func:`~virgi_ns.nerfstudio.distributed.share_cpu_threads`: its share of the host, bounded where it
drives a GPU), made to train on several processes
(``ns-train virgi --machine.num-devices N``), and the batch rule it applies there.

In one process it is nerfstudio's trainer. With N processes it averages the gradients before
every optimizer step (:class:`~virgi_ns.nerfstudio.distributed.DistributedOptimizers`), evaluates
and prints on rank 0 only (nerfstudio already writes checkpoints, logs and the viewer there), ends
when training ends (rank 0 would otherwise wait on the viewer while the others time out), and,
with ``--pipeline.multi-gpu-batch scale`` (the default), trains by :func:`scale_batch`.
"""

from __future__ import annotations

import copy
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple, Type

from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from virgi_ns.errors import InputError
from virgi_ns.nerfstudio import distributed

MODEL_STEPS = ("geometry_steps", "colour_steps", "warmup_length", "refine_every", "resolution_schedule",
               "sh_degree_interval", "stop_screen_size_at", "stop_split_at")
"""The model's settings counted in steps (gsplat's refinement pause counts an epoch of views
itself, from ``geometry_views_per_step``)."""
TRAINER_STEPS = ("steps_per_save", "steps_per_eval_image", "steps_per_eval_batch", "steps_per_eval_all_images")


@dataclass
class AdamConfig(AdamOptimizerConfig):
    """Adam with its betas in the config (the batch rule sets them), updating with torch's multi-tensor
    kernels on any device (``foreach``): on a GPU torch's own default, and on a CPU, where torch would loop
    over the tensors one at a time, the same numbers in about a third of the time."""

    betas: Tuple[float, float] = (0.9, 0.999)
    foreach: Optional[bool] = True


def _steps(n: int, world: int) -> int:
    return -(-int(n) // world)  # ceil: never fewer views than asked for


def scale_batch(config: TrainerConfig, world: int) -> TrainerConfig:
    """The batch rule: ``config`` (a one-GPU recipe) for ``world`` processes each taking a one-GPU
    batch, so that the run sees the same views in 1/N of the steps (N = ``world``).

    Global batch x N (``geometry_views_per_step`` and ``pixel_budget``); every count of steps / N
    (rounded up: the two stages' lengths, the model's schedules, the learning-rate schedules,
    saves and evaluations); Adam by the square-root rule (Malladi et al. 2022, as gsplat's own
    trainer scales it): learning rates x sqrt(N), eps / sqrt(N), each beta to 1 - N (1 - beta)
    (at least 0), so the moment estimates average over the same number of views. Returns a copy."""
    cfg = copy.deepcopy(config)
    model, dm = cfg.pipeline.model, cfg.pipeline.datamanager
    geometry = 0 if getattr(model, "geometry_from", None) is not None else int(model.geometry_steps)
    geometry = min(geometry, cfg.max_num_iterations)
    cfg.max_num_iterations = _steps(geometry, world) + _steps(cfg.max_num_iterations - geometry, world)
    for name in MODEL_STEPS:
        setattr(model, name, _steps(getattr(model, name), world))
    model.geometry_views_per_step *= world
    dm.pixel_budget *= world
    for name in TRAINER_STEPS:
        setattr(cfg, name, _steps(getattr(cfg, name), world))
    root = math.sqrt(world)
    for name, group in cfg.optimizers.items():
        opt = group["optimizer"]
        if not isinstance(opt, AdamOptimizerConfig):
            raise InputError(f"the 'scale' batch rule knows Adam only ({name}: {type(opt).__name__}); "
                             "use --pipeline.multi-gpu-batch keep")
        betas = tuple(max(0.0, 1.0 - world * (1.0 - b)) for b in getattr(opt, "betas", (0.9, 0.999)))
        group["optimizer"] = AdamConfig(lr=opt.lr * root, eps=opt.eps / root, max_norm=opt.max_norm,
                                        weight_decay=opt.weight_decay, betas=betas,  # type: ignore[arg-type]
                                        foreach=getattr(opt, "foreach", True))
        sch = group.get("scheduler")
        if sch is None:
            continue
        if not isinstance(sch, ExponentialDecaySchedulerConfig):
            raise InputError(f"the 'scale' batch rule knows exponential-decay schedules only ({name}: "
                             f"{type(sch).__name__}); use --pipeline.multi-gpu-batch keep")
        sch.max_steps = _steps(sch.max_steps, world)
        sch.warmup_steps = _steps(sch.warmup_steps, world)
        sch.lr_pre_warmup *= root
        if sch.lr_final is not None:
            sch.lr_final *= root
    return cfg


def check_split(config: TrainerConfig, world: int) -> None:
    """Refuse a 'keep' batch that cannot be split evenly over ``world`` processes."""
    model = config.pipeline.model
    trains_geometry = getattr(model, "geometry_from", None) is None and getattr(model, "geometry_steps", 0) > 0
    views = getattr(model, "geometry_views_per_step", 1)
    if trains_geometry and views % world:
        raise InputError(f"--pipeline.multi-gpu-batch keep splits each geometry step's views over the {world} "
                         f"processes: --pipeline.model.geometry-views-per-step ({views}) must be a multiple of "
                         f"{world} (the one-GPU run to compare with takes that many views per step)")


def for_processes(config: TrainerConfig, world: int) -> TrainerConfig:
    """``config`` as each of ``world`` processes trains it (a copy): the batch rule with 'scale',
    and the run ends with training."""
    scale = getattr(config.pipeline, "multi_gpu_batch", "keep") == "scale"
    if not scale:
        check_split(config, world)
    cfg = scale_batch(config, world) if scale else copy.deepcopy(config)
    cfg.viewer.quit_on_train_completion = True
    return cfg


def _describe(cfg: TrainerConfig, world: int) -> str:
    model, dm = cfg.pipeline.model, cfg.pipeline.datamanager
    how = getattr(cfg.pipeline, "multi_gpu_batch", "keep")
    text = (f"virgi: {world} processes ('{how}' batch): {model.geometry_views_per_step} views per geometry step, "
            f"{dm.pixel_budget:,} pixels per colour step, {cfg.max_num_iterations} steps")
    if how == "scale":
        opt = next(iter(cfg.optimizers.values()))["optimizer"]
        text += f"; Adam lr x {math.sqrt(world):.3f}, eps / {math.sqrt(world):.3f}, betas {tuple(opt.betas)}"
    return text


@dataclass
class VirgiTrainerConfig(TrainerConfig):
    _target: Type = field(default_factory=lambda: VirgiTrainer)

    def _prepare(self) -> None:
        """A run on a splat file made one (:func:`virgi_ns.data.splat.prepare_splat_run`); bad input is
        one line on stderr and exit 2. ``ns-train`` prints the config and then saves it before anything
        else: both come after this, so nothing is printed or written for bad input."""
        from virgi_ns.data.splat import prepare_splat_run
        from virgi_ns.errors import EXIT_USER_ERROR, VirgiError

        try:
            prepare_splat_run(self)
        except VirgiError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(EXIT_USER_ERROR)

    def print_to_terminal(self) -> None:
        self._prepare()
        super().print_to_terminal()

    def save_config(self) -> None:
        self._prepare()
        super().save_config()


class VirgiTrainer(Trainer):
    """nerfstudio's trainer; on several processes as the module doc says."""

    def __init__(self, config: TrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        from virgi_ns.data.splat import prepare_splat_run

        prepare_splat_run(config)  # (already done where ns-train saved the config)
        threads = distributed.share_cpu_threads(world_size, config.machine.device_type)
        if world_size > 1:
            config = for_processes(config, world_size)
            if not distributed.is_main():
                CONSOLE.quiet = True  # one console: rank 0's
            CONSOLE.log(f"{_describe(config, world_size)}; {threads} CPU threads each")
        super().__init__(config, local_rank, world_size)

    def train(self) -> None:
        """nerfstudio's training, with the run's folder made first: every process saves the dataparser
        transform there, and nerfstudio makes the folder by a check and then a create that fails in
        the process that loses the race."""
        Path(self.base_dir).mkdir(parents=True, exist_ok=True)
        super().train()

    def setup_optimizers(self):
        return distributed.make_optimizers(self.config.optimizers.copy(), self.pipeline.get_param_groups())

    def save_checkpoint(self, step: int) -> None:
        """nerfstudio's checkpoint, then (once per training, on the main process) ``virgi_run.json``
        beside ``config.yml``: what the virgi commands load instead of nerfstudio's dataparser. A failure to write
        it never stops training (the commands then load the run through nerfstudio)."""
        super().save_checkpoint(step)
        if not distributed.is_main() or getattr(self, "_run_info_written", False):
            return
        self._run_info_written = True
        try:
            from virgi_ns.nerfstudio.run_info import training_run_info, write_run_info

            write_run_info(training_run_info(self.config, self.pipeline.model),
                           Path(self.config.get_base_dir()) / "config.yml")
        except Exception as e:  # noqa: BLE001 - a convenience file; training goes on
            CONSOLE.log(f"virgi: virgi_run.json not written ({type(e).__name__}: {e}); the virgi commands will "
                        "load this run through nerfstudio")

    def eval_iteration(self, step: int) -> None:
        if self.world_size == 1 or distributed.is_main():
            super().eval_iteration(step)


__all__ = ["AdamConfig", "VirgiTrainer", "VirgiTrainerConfig", "check_split", "for_processes", "scale_batch"]
