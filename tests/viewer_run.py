"""A tiny trained VIRGi run for the viewer tests: the procedural capture of :mod:`virgi_scene`,
imported geometry, a few colour steps on the CPU; optionally saved as a nerfstudio run directory
(``config.yml`` + ``nerfstudio_models/step-*.ckpt``) that ``ns-viewer --load-config`` opens."""

from __future__ import annotations

import warnings
from pathlib import Path

import torch

from method_configs.virgi import virgi_trainer_config
from virgi_ns.colour.field import ColourFieldConfig
from virgi_ns.nerfstudio.pipeline import save_run, train_step, training_state

from virgi_scene import Scene, use_scene

warnings.filterwarnings("ignore", message="virgi-ns: no GPU")


def tiny_config(scene: Scene, steps: int, output_dir: Path | None = None):
    cfg = virgi_trainer_config("virgi", geometry_steps=0, colour_steps=steps)
    cfg.max_num_iterations = steps
    use_scene(cfg, scene, pixel_budget=5 * 256 * 2)
    m = cfg.pipeline.model
    m.geometry_from = scene.ply.resolve()
    m.background_color = "black"
    m.color_field = ColourFieldConfig(log2_hashmap_size=12, levels=8)
    m.raster_backend = "reference"
    cfg.optimizers["field_mlp"]["optimizer"].lr = 5e-3
    cfg.machine.device_type = "cpu"
    if output_dir is not None:
        cfg.output_dir = output_dir
        cfg.experiment_name = "tiny"
        cfg.timestamp = "run"
        cfg.relative_model_dir = Path("nerfstudio_models")
    return cfg


def train_tiny(scene: Scene, steps: int = 30, output_dir: Path | None = None, seed: int = 0):
    """(config, pipeline) after ``steps`` colour steps; with ``output_dir`` the run is saved too."""
    torch.manual_seed(seed)
    cfg = tiny_config(scene, steps, output_dir)
    pipeline = cfg.pipeline.setup(device="cpu", test_mode="val")
    optimizers, cbs = training_state(cfg, pipeline)
    for step in range(steps):
        train_step(pipeline, optimizers, cbs, step)
    pipeline.eval()
    if output_dir is not None:
        save_run(cfg, pipeline, optimizers, steps - 1)
    return cfg, pipeline
