"""The VIRGi model: frozen Gaussian geometry, a decoupled diffuse/specular colour field.

Two stages in one nerfstudio run, each its own module:

1. **Geometry** (:mod:`virgi_ns.nerfstudio.geometry_stage`): splatfacto's recipe, or a splat
   imported with ``geometry_from``; then the Gaussians are frozen.
2. **Colour** (:mod:`virgi_ns.nerfstudio.colour_stage`): a warm start from the Gaussians' own
   colours, then the colour field trained on multi-view tile batches.

Rendering (:mod:`virgi_ns.nerfstudio.render_path`) goes through the edit stack and, after
training, the specular gate. :class:`VirgiModel` assembles the three with splatfacto's model, so
that nerfstudio's viewer and exporters treat it as a splat; it replaces the pieces that assume
a GPU.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils.colors import get_color
from pytorch_msssim import SSIM
from torch import Tensor
from torch.nn import Parameter

from virgi_ns.colour.field import ColorFieldConfig, DecoupledColorField
from virgi_ns.errors import InputError
from virgi_ns.nerfstudio import distributed
from virgi_ns.nerfstudio.colour_stage import ColourStage
from virgi_ns.nerfstudio.datamanager import TileBatch
from virgi_ns.nerfstudio.geometry_stage import GeometryStage
from virgi_ns.nerfstudio.render_cache import RenderCache
from virgi_ns.nerfstudio.render_path import RenderPath
from virgi_ns.raster import Cameras, Contributions, Request, rasterize


@dataclass
class VirgiModelConfig(SplatfactoModelConfig):
    """VIRGi: splatfacto geometry (trained or imported, then frozen) + decoupled colour field."""

    _target: Type = field(default_factory=lambda: VirgiModel)
    geometry_from: Optional[Path] = None
    """Import the geometry from a splat (.ply, .compressed.ply, .spz, .sog, splatfacto .ckpt/config.yml)
    instead of training it."""
    geometry_frame: Literal["auto", "capture", "dataparser"] = "auto"
    """Frame of the imported splat: 'capture' (the capture's original frame: the dataparser's
    transform is applied), 'dataparser' (already in this run's frame), or 'auto' (splatfacto
    checkpoints are 'dataparser', files are 'capture')."""
    geometry_steps: int = 30000
    """Geometry training steps (ignored with geometry_from)."""
    colour_steps: int = 10000
    """Colour-stage length used for the lambda_spec schedule when the trainer's is unknown."""
    color_field: ColorFieldConfig = field(default_factory=ColorFieldConfig)
    """Hash grid and MLP sizes; ``decoupled=False`` is the single-MLP baseline."""
    lambda_spec_start: float = 0.25
    lambda_spec_end: float = 0.05
    raster_backend: Literal["auto", "reference", "cuda"] = "auto"
    """Rasterizer for the colour stage and rendering."""
    whole_view_renderer: Literal["gsplat", "contributions"] = "gsplat"
    """Whole-view renders on a GPU (viewer, evaluation): gsplat's forward rasterizer with one colour
    per Gaussian, or our contribution lists (``raster_backend``). CPU renders always take the lists."""
    specular_gating: bool = True
    """Render MLP_spec only for Gaussians whose measured specular effect exceeds gate_threshold."""
    gate_threshold: float = 1.0 / 255.0
    """Largest |sigmoid(c_d + c_s) - sigmoid(c_d)| over the training views below which a Gaussian
    is treated as matte."""
    render_cache_half: bool = False
    """Keep the render cache's two per-Gaussian hidden-layer parts of MLP_spec in float16: half the
    cache's memory, colours no longer equal to the field's to float32 precision."""
    render_cache_graphs: bool = True
    """On a GPU, replay the gated colours of a view as a CUDA graph recorded once per render-cache state
    (after its first frame), instead of launching their dozen small kernels every frame."""
    box_quantile: float = 0.01
    """The hash grid's box spans these quantiles of the frozen means (expanded by 10%)."""
    colour_init: Literal["geometry", "geometry_sh", "none"] = "geometry_sh"
    """Start of the colour stage: 'geometry' first fits the colour field to each Gaussian's own
    degree-0 colour (a warm start, no rendering); 'geometry_sh' also fits ``c_d + c_s`` to the
    Gaussian's full SH colour seen from training cameras that see it (the diffuse branch still to
    the degree-0 colour, so the specular branch starts as the geometry's view-dependent residual;
    the single-MLP baseline fits its view-dependent colour to the same SH colours); 'none' starts
    from the random field."""
    colour_init_steps: int = 300
    """Adam steps of the warm start (the field's own learning rates)."""
    colour_init_batch: int = 16384
    """Gaussians per warm-start step (drawn uniformly, weighted by opacity in the loss)."""
    geometry_views_per_step: int = 1
    """Training views per geometry step, over all processes: the loss is their mean, and gsplat's
    densification statistics count each of them as one view."""


class VirgiModel(GeometryStage, ColourStage, RenderPath, SplatfactoModel):
    """Splatfacto's model with VIRGi's stages: :class:`GeometryStage`, :class:`ColourStage` and
    :class:`RenderPath` hold the methods of each; this class sets them up, dispatches outputs by
    what it is given (tiles or a camera, before or after freezing) and keeps the parameters."""

    config: VirgiModelConfig

    # ---------------------------------------------------------------- set-up
    def populate_modules(self) -> None:
        cfg = self.config
        self.imported = cfg.geometry_from is not None
        # the rotation taking directions of the imported file's frame into this run's (the SH
        # coefficients stay in the file's frame; the SH warm start evaluates them there)
        self._sh_rotation: Optional[Tensor] = None
        params = self._initial_gaussians()
        self.gauss_params = torch.nn.ParameterDict({k: Parameter(v) for k, v in params.items()})
        self.camera_optimizer = cfg.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        from torchmetrics.image import PeakSignalNoiseRatio

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self.step = 0
        self.crop_box = None
        if cfg.background_color == "random":
            self.background_color = torch.tensor([0.1490, 0.1647, 0.2157])
        else:
            self.background_color = get_color(cfg.background_color)
        if cfg.use_bilateral_grid:
            raise InputError("virgi does not support --pipeline.model.use-bilateral-grid")
        from gsplat.strategy import DefaultStrategy

        views = max(1, cfg.geometry_views_per_step)
        strategy = distributed.ReducedDefaultStrategy if distributed.world_size() > 1 else DefaultStrategy
        self.strategy = strategy(
            prune_opa=cfg.cull_alpha_thresh,
            grow_grad2d=cfg.densify_grad_thresh,
            grow_scale3d=cfg.densify_size_thresh,
            grow_scale2d=cfg.split_screen_size,
            prune_scale3d=cfg.cull_scale_thresh,
            prune_scale2d=cfg.cull_screen_size,
            refine_scale2d_stop_iter=cfg.stop_screen_size_at,
            refine_start_iter=cfg.warmup_length,
            refine_stop_iter=cfg.stop_split_at,
            reset_every=cfg.reset_alpha_every * cfg.refine_every,
            refine_every=cfg.refine_every,
            pause_refine_after_reset=math.ceil(self.num_train_data / views) + cfg.refine_every,  # an epoch of views
            absgrad=cfg.use_absgrad,
            revised_opacity=False,
            verbose=distributed.is_main(),
        )
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        # gsplat's outputs of this process's views in the current geometry step (see step_post_backward)
        self._view_infos: deque = deque(maxlen=max(1, views // distributed.world_size()))

        self.field = DecoupledColorField(cfg.color_field, self._scene_aabb())
        self.register_buffer("frozen", torch.tensor(False))  # in checkpoints
        self._frozen = False  # its host copy: the flag is read every step, and reading a GPU buffer syncs
        self.register_load_state_dict_post_hook(VirgiModel._sync_frozen)
        # specular gate (filled by build_specular_gate; sizes follow the Gaussians)
        self.register_buffer("spec_magnitude", torch.zeros(0))
        self.register_buffer("diffuse_cache", torch.zeros(0, 3))
        self.colour_start = 0 if self.imported else cfg.geometry_steps
        self.colour_total = max(cfg.colour_steps, 1)
        self._train_cameras_fn = None
        self._colour_init_done = False  # the warm start runs once per process (see start_colour_stage)
        self.stage_seconds: Dict[str, float] = {}  # wall time of the warm start and the gate, for benchmarks
        self._field_lrs = (1e-2, 1e-3)  # hash grid, MLPs: the trainer's, once its optimizers are known
        # the edit stack applied at render time (see set_edit_stack); not part of the checkpoint
        self.edit_stack = None
        self.live_edit = None  # a pick's uncommitted edit, rendered over the stack (set_live_edit)
        self.segmentation_edit: Optional[int] = None
        # view-independent parts of whole-view renders (see render_cache); keyed on what they are
        # computed from, so nothing here has to be cleared by hand
        self._render_cache = RenderCache()
        self._live_revision = 0  # counts set_live_edit calls (the render cache's key for the live edit)
        self._gate_stamp: Optional[tuple] = None  # the field's parameters (identities, versions) when the gate was built
        if self.imported:
            self.freeze_geometry()
        from virgi_ns.nerfstudio.viewer.panel import VirgiPanel

        self.viewer_panel = VirgiPanel(self)  # a plain attribute: the viewer finds it, checkpoints don't

    def _scene_aabb(self) -> Tensor:
        return self.scene_box.aabb.detach().float().cpu().clone()

    def _raster(self, cams: Cameras, request: Request, geometry_grad: bool = False) -> Contributions:
        means, quats, scales, opac = self.means, self.quats, torch.exp(self.scales), torch.sigmoid(self.opacities)
        with torch.set_grad_enabled(geometry_grad and torch.is_grad_enabled()):
            return rasterize(means, quats, scales, opac.reshape(-1), cams.to(self.device), request,
                             backend=self.config.raster_backend if self.geometry_frozen else "reference")

    # --------------------------------------------------------------- outputs
    def get_outputs(self, camera: Union[NSCameras, TileBatch]) -> Dict[str, Union[Tensor, List]]:
        if isinstance(camera, TileBatch):
            return self._tile_outputs(camera)
        if not isinstance(camera, NSCameras):
            return {}
        if not self.geometry_frozen:
            if self._use_gsplat():
                out = super().get_outputs(camera)
                if self.training:
                    self._view_infos.append(self.info)
                return out
            return self._reference_geometry_outputs(camera)
        return self.render_camera(camera, gated=self.config.specular_gating and not self.training)

    def get_image_metrics_and_images(self, outputs, batch):
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])[..., :3]
        pred = outputs["rgb"]
        metrics = image_metrics_dict(pred, gt)
        images = [gt, pred]
        if "diffuse" in outputs:
            images += [outputs["diffuse"], (outputs["specular"] + 0.5).clamp(0, 1)]
        return metrics, {"img": torch.cat(images, dim=1)}

    # ------------------------------------------------------------ parameters
    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        gps = self.get_gaussian_param_groups()
        self.camera_optimizer.get_param_groups(param_groups=gps)
        gps["field_grid"] = self.field.grid_parameters()
        gps["field_mlp"] = self.field.mlp_parameters()
        return gps

    def load_state_dict(self, state_dict, **kwargs):  # type: ignore[override]
        for name in ("spec_magnitude", "diffuse_cache"):
            key = name if name in state_dict else next((k for k in state_dict if k.endswith("." + name)), None)
            if key is not None:
                setattr(self, name, torch.empty_like(state_dict[key], device=self.device))
        out = super().load_state_dict(state_dict, **kwargs)
        for p in self.gauss_params.values():
            p.requires_grad_(not self.geometry_frozen)
        self._gate_stamp = self._field_stamp()  # a saved gate belongs to the saved field
        self.render_cache.clear()
        return out


def image_metrics_dict(pred: Tensor, gt: Tensor) -> Dict[str, float]:
    """PSNR, SSIM, LPIPS through :mod:`virgi_ns.metrics` (LPIPS NaN offline), or PSNR/SSIM here."""
    try:
        from virgi_ns.metrics import image_metrics
    except ImportError:
        image_metrics = None
    if image_metrics is not None:
        return {k: float(v) for k, v in image_metrics(pred, gt).items()}
    mse = float(((pred - gt) ** 2).mean())
    ssim = SSIM(data_range=1.0, size_average=True, channel=3)
    s = float(ssim(gt.permute(2, 0, 1)[None].float().cpu(), pred.permute(2, 0, 1)[None].float().cpu()))
    return {"psnr": -10 * math.log10(max(mse, 1e-10)), "ssim": s, "lpips": float("nan")}