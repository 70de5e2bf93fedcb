"""The VIRGi pipeline: nerfstudio's pipeline with the two training stages wired in.

Geometry stage: whole images, ``geometry_views_per_step`` per step (one by default, as
splatfacto). Colour stage: the model freezes its geometry (once), the datamanager samples tile
batches around the frozen Gaussians, the model renders only those tiles. :func:`training_state`,
:func:`train_step` and :func:`save_run` train and save a run in process (the demo, tests).

With several processes (:mod:`virgi_ns.nerfstudio.distributed`) each draws its share of every
step's batch and the model is not wrapped in DDP: virgi's trainer averages the gradients.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Dict, List, Literal, Optional, Type

import torch
import yaml
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import profiler

from virgi_ns.errors import InputError, atomic_path
from virgi_ns.nerfstudio import distributed
from virgi_ns.nerfstudio.datamanager import VirgiDataManager
from virgi_ns.nerfstudio.geometry_stage import mean_over_views
from virgi_ns.nerfstudio.model import VirgiModel


@dataclass
class VirgiPipelineConfig(VanillaPipelineConfig):
    _target: Type = field(default_factory=lambda: VirgiPipeline)
    multi_gpu_batch: Literal["scale", "keep"] = "scale"
    """With ``--machine.num-devices N`` above 1: 'scale' gives each process a one-GPU batch (N times
    the views per step) and shortens and re-tunes the run by the batch rule (see the README);
    'keep' splits the one-GPU batch over the processes, with the same steps and learning rates
    (the one-GPU run up to float rounding; needs ``geometry_views_per_step`` a multiple of N)."""


class VirgiPipeline(VanillaPipeline):
    """Switches batches between whole images (geometry) and tiles (colour)."""

    config: VirgiPipelineConfig

    def __init__(self, config: VirgiPipelineConfig, device: str, test_mode: Literal["test", "val", "inference"] = "val",
                 world_size: int = 1, local_rank: int = 0, grad_scaler: Optional[torch.cuda.amp.GradScaler] = None):
        if world_size > 1:
            distributed.prepare_cuda(device)
        # one process's set-up (no DDP wrapper), then the processes' shares
        super().__init__(config, device, test_mode, world_size=1, local_rank=local_rank, grad_scaler=grad_scaler)
        self.world_size = world_size
        if world_size > 1:
            if isinstance(self.datamanager, VirgiDataManager):
                self.datamanager.split_over_processes(distributed.rank(), world_size,
                                                      shared_tiles=config.multi_gpu_batch == "keep")
            distributed.broadcast_state(self.model)  # nerfstudio seeds each process differently

    def get_training_callbacks(self, training_callback_attributes):
        if self.world_size > 1 and not isinstance(training_callback_attributes.optimizers,
                                                  distributed.DistributedOptimizers):
            raise InputError("training on several processes needs virgi's trainer "
                             "(method_configs.virgi's configs; nerfstudio's would not average the gradients)")
        return super().get_training_callbacks(training_callback_attributes)

    @profiler.time_function
    def get_train_loss_dict(self, step: int):
        model = self.model
        dm = self.datamanager
        if not (isinstance(model, VirgiModel) and isinstance(dm, VirgiDataManager)):
            return super().get_train_loss_dict(step)
        if not model.in_colour_stage(step):
            if model.config.geometry_views_per_step == 1 and self.world_size == 1:
                return super().get_train_loss_dict(step)
            return self._geometry_views_step(step)
        if not model.geometry_frozen:
            model.freeze_geometry()
        means, opac = model.sampling_geometry()
        tiles, batch = dm.next_tile_batch(step, means, opac)
        outputs = self._model(tiles) if len(tiles.request) or self.world_size == 1 else None
        if self.world_size > 1:  # the losses are means over every process's pixels and pairs
            counts = torch.zeros(2, dtype=torch.float64, device=model.device)
            if outputs is not None:
                counts[0] = batch["valid"].sum()
                counts[1] = outputs["c_s"].shape[0]
            batch["loss_norm"] = distributed.all_sum(counts).clamp_min(1) / self.world_size
        if outputs is None:  # a share without tiles: nothing to learn from, but a loss to step with
            zero = torch.zeros((), device=model.device, requires_grad=True)
            return {}, {"rgb_l1": zero, "spec_reg": zero}, {}
        metrics = model.get_metrics_dict(outputs, batch)
        losses = model.get_loss_dict(outputs, batch, metrics)
        return outputs, losses, metrics

    def _geometry_views_step(self, step: int):
        """A geometry step over this process's views of the step: the losses and metrics are the
        means over those views (the processes' gradients are averaged in turn)."""
        model = self.model
        losses: List[Dict] = []
        metrics: List[Dict] = []
        outputs = {}
        for camera, batch in self.datamanager.next_train_views(step, model.config.geometry_views_per_step):
            outputs = self._model(camera)
            metrics.append(model.get_metrics_dict(outputs, batch))
            losses.append(model.get_loss_dict(outputs, batch, metrics[-1]))
        return outputs, mean_over_views(losses), mean_over_views(metrics)


def training_state(trainer_config, pipeline) -> tuple:
    """(optimizers, callbacks) for training ``pipeline`` in process as nerfstudio's Trainer would
    set them up from ``trainer_config`` (the model's callbacks read the trainer's config)."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    class _Trainer:  # what the callbacks read from nerfstudio's Trainer
        config = trainer_config

    pipeline.train()
    optimizers = distributed.make_optimizers(trainer_config.optimizers, pipeline.get_param_groups())
    callbacks = pipeline.get_training_callbacks(TrainingCallbackAttributes(optimizers, None, pipeline, _Trainer()))
    return optimizers, callbacks


def train_step(pipeline, optimizers, callbacks, step: int) -> tuple[dict, dict]:
    """One training step as nerfstudio's Trainer takes it (callbacks before, loss, backward,
    optimizer and scheduler steps, callbacks after), without its logging and checkpoints; for
    in-process training (the demo, tests). Returns the step's (loss dict, metrics dict)."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    for cb in callbacks:
        cb.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    optimizers.zero_grad_all()
    _, losses, metrics = pipeline.get_train_loss_dict(step)
    sum(losses.values()).backward()
    optimizers.optimizer_step_all()
    optimizers.scheduler_step_all(step)
    for cb in callbacks:
        cb.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return losses, metrics


@dataclass
class RunDirConfig(TrainerConfig):
    """A trainer config whose run directory is ``output_dir`` itself (``config.yml``,
    ``nerfstudio_models/``, ``edits/`` directly in it) instead of nerfstudio's
    ``output_dir/experiment/method/timestamp``: a run saved in process at a path of its choosing
    (:func:`save_run`), which ``ns-viewer --load-config`` and the virgi commands open as any run."""

    def get_base_dir(self) -> Path:
        return Path(self.output_dir)


def save_run(trainer_config, pipeline, optimizers, step: int, directory=None) -> Path:
    """Save an in-process run as nerfstudio's trainer would (``config.yml`` and
    ``nerfstudio_models/step-NNNNNNNNN.ckpt``, without a grad scaler, with virgi's trainer's
    ``virgi_run.json`` beside ``config.yml``); with ``directory`` the run
    sits there (a :class:`RunDirConfig` with the model class :class:`VirgiModel` and the method
    ``virgi``, whatever trained it), else where ``trainer_config`` puts it. Returns the path of ``config.yml``."""
    cfg = copy.deepcopy(trainer_config)
    if directory is not None:
        cfg = RunDirConfig(**{f.name: getattr(cfg, f.name) for f in fields(TrainerConfig)})
        cfg.output_dir = Path(directory).resolve()
        cfg.pipeline.model._target = VirgiModel
        cfg.method_name = "virgi"  # loaders look the datamanager up by a registered method's name
    base = cfg.get_base_dir()
    ckpt_dir = cfg.get_checkpoint_dir()
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(ckpt_dir / f"step-{step:09d}.ckpt") as tmp:
        torch.save({"step": step, "pipeline": pipeline.state_dict(),
                    "optimizers": {k: v.state_dict() for k, v in optimizers.optimizers.items()},
                    "schedulers": {k: v.state_dict() for k, v in optimizers.schedulers.items()},
                    "scalers": {}}, tmp)
    with atomic_path(base / "config.yml") as tmp:
        tmp.write_text(yaml.dump(cfg), "utf8")
    from virgi_ns.nerfstudio.run_info import training_run_info, write_run_info

    write_run_info(training_run_info(cfg, pipeline.model), base / "config.yml")
    return base / "config.yml"
