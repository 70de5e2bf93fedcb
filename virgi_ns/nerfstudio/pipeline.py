"""The VIRGi pipeline: nerfstudio's pipeline with the two training stages wired in.

Geometry stage: one whole image per step, as splatfacto. Colour stage: the model freezes its
geometry (once), the datamanager samples tile batches around the frozen Gaussians, the model
renders only those tiles.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import profiler

from virgi_ns.nerfstudio.datamanager import VirgiDataManager
from virgi_ns.nerfstudio.model import VirgiModel


@dataclass
class VirgiPipelineConfig(VanillaPipelineConfig):
    _target: Type = field(default_factory=lambda: VirgiPipeline)


class VirgiPipeline(VanillaPipeline):
    """Switches batches between whole images (geometry) and tiles (colour)."""

    @profiler.time_function
    def get_train_loss_dict(self, step: int):
        model = self.model
        dm = self.datamanager
        if not (isinstance(model, VirgiModel) and isinstance(dm, VirgiDataManager)) or not model.in_colour_stage(step):
            return super().get_train_loss_dict(step)
        if not model.geometry_frozen:
            model.freeze_geometry()
        means, opac = model.sampling_geometry()
        tiles, batch = dm.next_tile_batch(step, means, opac)
        outputs = self._model(tiles)
        metrics = model.get_metrics_dict(outputs, batch)
        losses = model.get_loss_dict(outputs, batch, metrics)
        return outputs, losses, metrics


def training_state(trainer_config, pipeline) -> tuple:
    """(optimizers, callbacks) for training ``pipeline`` in process as nerfstudio's Trainer would
    set them up from ``trainer_config`` (the model's callbacks read the trainer's config)."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes
    from nerfstudio.engine.optimizers import Optimizers

    class _Trainer:  # what the callbacks read from nerfstudio's Trainer
        config = trainer_config

    pipeline.train()
    optimizers = Optimizers(trainer_config.optimizers, pipeline.get_param_groups())
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
