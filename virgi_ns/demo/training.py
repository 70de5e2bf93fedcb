"""``ns-train virgi``'s recipe on the demo's capture, trained in process (no checkpoints, no viewer);
on a CPU the colour stage slices its tiles from a cache of whole-view contribution lists."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Dict, Optional

import torch

from virgi_ns.data.bundle import BundleDataParserConfig
from virgi_ns.demo.config import DemoConfig


def _cached_model_class():
    """VirgiModel whose colour-stage rasterization can come from a contribution cache."""
    from virgi_ns.nerfstudio.model import VirgiModel

    class CachedVirgiModel(VirgiModel):
        contrib_cache = None

        def contributions(self, cams, request, geometry_grad: bool = False):
            cache = self.contrib_cache
            if cache is not None and self.geometry_frozen and cache.matches(cams):
                return cache.contributions(request, self.means.detach())
            return super().contributions(cams, request, geometry_grad)

    return CachedVirgiModel


def trainer_config(cfg: DemoConfig, scene: Path, geometry: Optional[Path], use_cache: bool):
    """``ns-train virgi``'s recipe on ``scene``, with the demo's step counts and sizes."""
    from method_configs.virgi import virgi_trainer_config
    from virgi_ns.colour.field import ColourFieldConfig

    g_steps = 0 if geometry is not None else geometry_steps(cfg)
    tc = virgi_trainer_config("virgi-demo", geometry_steps=g_steps, colour_steps=colour_steps(cfg, geometry))
    dm = tc.pipeline.datamanager
    dm.dataparser = BundleDataParserConfig(data=scene)
    dm.data = scene
    dm.cache_images = "gpu"  # keeps images on the manager's device, whichever it is
    dm.tile_size = cfg.tile_size
    dm.views_per_anchor = cfg.views_per_anchor
    dm.pixel_budget = cfg.pixel_budget if cfg.pixel_budget is not None else (
        163840 if torch.cuda.is_available() and cfg.device != "cpu" else 2 * 5 * 32 * 32)
    m = tc.pipeline.model
    m.geometry_from = geometry
    m.colour_init = cfg.colour_init
    if not (torch.cuda.is_available() and cfg.device != "cpu"):  # a CPU: a shorter warm start (~20 s)
        m.colour_init_steps, m.colour_init_batch = 200, 4096
    if cfg.colour_init_steps is not None:
        m.colour_init_steps = cfg.colour_init_steps
    if cfg.colour_init_batch is not None:
        m.colour_init_batch = cfg.colour_init_batch
    m.color_field = ColourFieldConfig(log2_hashmap_size=cfg.hash_log2)
    if g_steps > 0 and (cfg.device == "cpu" or not torch.cuda.is_available()):
        m.num_downscales = 2  # a CPU affords 1/4 resolution for the first half, 1/2 for the second
        m.resolution_schedule = max(1, (g_steps + 1) // 2)
    if use_cache:
        m._target = _cached_model_class()
    return tc


def colour_steps(cfg: DemoConfig, geometry: Optional[Path]) -> int:
    if cfg.colour_steps is not None:
        return cfg.colour_steps
    if torch.cuda.is_available() and cfg.device != "cpu":
        return 5000
    return 1000


def geometry_steps(cfg: DemoConfig) -> int:
    if cfg.geometry_steps is not None:
        return cfg.geometry_steps
    return 15000 if torch.cuda.is_available() and cfg.device != "cpu" else 400


def train(pipeline, tc, steps: int, on_step: Callable[[int, Dict[str, float]], None],
          before_colour: Callable[[], None], after_init: Callable[[], None] = lambda: None):
    """nerfstudio's training loop (callbacks, optimizers, schedulers), without checkpoints or viewer;
    returns the optimizers (for the saved run's checkpoint)."""
    from virgi_ns.nerfstudio.pipeline import train_step, training_state

    opt, cbs = training_state(tc, pipeline)
    model = pipeline.model
    prepared = False
    for step in range(steps):
        if not prepared and model.in_colour_stage(step):
            model.freeze_geometry()
            before_colour()
            model.start_colour_stage()  # the warm start (the model's callback would run it at this step)
            after_init()
            prepared = True
        _, metrics = train_step(pipeline, opt, cbs, step)
        on_step(step, {k: float(torch.as_tensor(v).detach()) for k, v in metrics.items() if k == "psnr"})
    if not prepared:
        model.freeze_geometry()
    return opt


__all__ = ["colour_steps", "geometry_steps", "train", "trainer_config"]
