"""The VIRGi model: frozen Gaussian geometry, a decoupled diffuse/specular colour field.

Two stages in one nerfstudio run:

1. **Geometry** (steps ``[0, geometry_steps)``): splatfacto's recipe (gsplat, densification) on a
   GPU; on a CPU the torch reference rasterizer, degree-0 colours, no densification (tiny scenes
   only). Skipped when ``geometry_from`` imports a splat. Then the Gaussians are frozen: no
   gradients, no strategy callbacks.
2. **Colour**: first (``colour_init="geometry_sh"``) a warm start fits the colour field to each
   Gaussian's own colours, per Gaussian and without rendering: ``c_d`` to its degree-0 colour,
   ``c_d + c_s`` to its SH colour seen from training cameras that see it
   (:meth:`VirgiModel.init_colour_field`); then batches of tiles (:mod:`virgi_ns.nerfstudio.datamanager`)
   are rasterized once into contribution lists; the colour field runs only for the (view,
   Gaussian) pairs the batch touches: hash features and MLP_diff per Gaussian, MLP_spec per pair
   with that pair's view direction. Loss ``L1 + lambda_spec * mean ||c_s||^2``, ``lambda_spec`` decaying linearly from
   ``lambda_spec_start`` to ``lambda_spec_end`` over the colour stage.

After training the model measures every Gaussian's specular magnitude over the training views
(:meth:`VirgiModel.build_specular_gate`); rendering then runs MLP_spec only for Gaussians above
``gate_threshold`` and cached diffuse colours elsewhere.

The class extends :class:`SplatfactoModel` so that nerfstudio's viewer and exporters treat it as
a splat; it replaces the pieces that assume a GPU.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.splatfacto import RGB2SH, SplatfactoModel, SplatfactoModelConfig, num_sh_bases
from nerfstudio.utils.colors import get_color
from nerfstudio.utils.rich_utils import CONSOLE
from pytorch_msssim import SSIM
from torch import Tensor
from torch.nn import Parameter

from virgi_ns.nerfstudio.datamanager import TileBatch
from virgi_ns.errors import InputError
from virgi_ns.colour.field import ColorFieldConfig, DecoupledColorField, view_directions
from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.nerfstudio.cameras import raster_cameras
from virgi_ns.nerfstudio.frames import transform_gaussians
from virgi_ns.raster import Cameras, Contributions, Request, composite, composite_depth, rasterize


@dataclass
class VirgiModelConfig(SplatfactoModelConfig):
    """VIRGi: splatfacto geometry (trained or imported, then frozen) + decoupled colour field."""

    _target: Type = field(default_factory=lambda: VirgiModel)
    geometry_from: Optional[Path] = None
    """Import the geometry from a splat (.ply, .compressed.ply, .spz, splatfacto .ckpt/config.yml)
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
    specular_gating: bool = True
    """Render MLP_spec only for Gaussians whose measured specular effect exceeds gate_threshold."""
    gate_threshold: float = 1.0 / 255.0
    """Largest |sigmoid(c_d + c_s) - sigmoid(c_d)| over the training views below which a Gaussian
    is treated as matte."""
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


class VirgiModel(SplatfactoModel):
    """See the module docstring."""

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

        self.strategy = DefaultStrategy(
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
            pause_refine_after_reset=self.num_train_data + cfg.refine_every,
            absgrad=cfg.use_absgrad,
            revised_opacity=False,
            verbose=True,
        )
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)

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
        self.segmentation_edit: Optional[int] = None
        self._edited_cache: Optional[tuple] = None
        if self.imported:
            self.freeze_geometry()
        from virgi_ns.nerfstudio.viewer.panel import VirgiPanel

        self.viewer_panel = VirgiPanel(self)  # a plain attribute: the viewer finds it, checkpoints don't

    def _scene_aabb(self) -> Tensor:
        return self.scene_box.aabb.detach().float().cpu().clone()

    def _initial_gaussians(self) -> Dict[str, Tensor]:
        cfg = self.config
        dim_sh = num_sh_bases(cfg.sh_degree)
        if cfg.geometry_from is not None:
            return self._imported_gaussians(Path(cfg.geometry_from), dim_sh)
        if self.seed_points is not None and not cfg.random_init:
            means = self.seed_points[0].float().cpu()
            colors = self.seed_points[1].float().cpu() / 255.0 if self.seed_points[1].shape[0] > 0 else None
        else:
            means = (torch.rand(cfg.num_random, 3) - 0.5) * cfg.random_scale
            colors = None
        n = means.shape[0]
        dist, _ = self.k_nearest_sklearn(means, 3) if n > 3 else (None, None)
        avg = torch.from_numpy(dist).mean(-1, keepdim=True) if dist is not None else torch.full((n, 1), 0.01)
        from nerfstudio.models.splatfacto import random_quat_tensor

        dc = RGB2SH(colors) if colors is not None else torch.rand(n, 3)
        return {
            "means": means,
            "scales": torch.log(avg.clamp_min(1e-7).repeat(1, 3)),
            "quats": random_quat_tensor(n),
            "features_dc": dc,
            "features_rest": torch.zeros(n, dim_sh - 1, 3),
            "opacities": torch.logit(0.1 * torch.ones(n, 1)),
        }

    def _imported_gaussians(self, path: Path, dim_sh: int) -> Dict[str, Tensor]:
        from virgi_ns.io import load_splat

        g: Gaussians = load_splat(path)
        if len(g) == 0:
            raise InputError(f"{path}: the splat holds no Gaussians")
        frame = self.config.geometry_frame
        if frame == "auto":
            frame = "dataparser" if path.suffix.lower() in (".ckpt", ".yml", ".yaml", ".pt", ".pth") or path.is_dir() \
                else "capture"
        means, scales, quats = g.means.float(), g.scales.float(), g.quats.float()
        if frame == "capture":
            meta = self.kwargs.get("metadata") or {}
            T = meta.get("virgi_capture_transform")
            if T is not None:
                means, scales, quats = transform_gaussians(means, scales, quats, T, meta.get("virgi_capture_scale", 1.0))
                self._sh_rotation = torch.as_tensor(T, dtype=torch.float32)[:3, :3].clone()
        sh = g.with_sh_degree(self.config.sh_degree).sh.float()
        CONSOLE.log(f"virgi: imported geometry from {path} ({len(g):,} Gaussians, frame {frame})")
        return {
            "means": means,
            "scales": scales,
            "quats": quats,
            "features_dc": sh[:, 0].clone(),
            "features_rest": sh[:, 1:dim_sh].clone(),
            "opacities": g.opacities.float().reshape(-1, 1),
        }

    # ---------------------------------------------------------------- stages
    def freeze_geometry(self) -> None:
        """Stop geometry training; fit the hash grid's box to the frozen means."""
        for p in self.gauss_params.values():
            p.requires_grad_(False)
        if self._frozen:
            return
        self._frozen = True
        self.frozen.fill_(True)
        m = self.means.detach()
        op = torch.sigmoid(self.opacities.detach().reshape(-1))
        keep = m[op > 0.1] if int((op > 0.1).sum()) >= 8 else m
        if keep.shape[0] > 200_000:
            keep = keep[torch.randperm(keep.shape[0], device=keep.device)[:200_000]]
        q = self.config.box_quantile
        lo = torch.quantile(keep.float(), q, dim=0)
        hi = torch.quantile(keep.float(), 1 - q, dim=0)
        pad = 0.1 * (hi - lo).clamp_min(1e-3)
        self.field.aabb.copy_(torch.stack([lo - pad, hi + pad]).to(self.field.aabb))

    @staticmethod
    def _sync_frozen(module: "VirgiModel", _keys) -> None:
        """After a state dict is loaded: the host copy of the ``frozen`` buffer."""
        module._frozen = bool(module.frozen)

    def start_colour_stage(self) -> Optional[Dict[str, float]]:
        """Freeze the geometry and, once per process, warm-start the colour field
        (``colour_init``). Runs from the training callback at the colour stage's first step, so a
        run resumed later in the colour stage keeps its trained field."""
        self.freeze_geometry()
        if self._colour_init_done:
            return None
        self._colour_init_done = True
        if self.config.colour_init == "none" or self.config.colour_init_steps <= 0:
            return None
        cams = None
        if self.config.colour_init == "geometry_sh" and self._train_cameras_fn is not None:
            cams = self._train_cameras_fn()  # loads the training images, as the first colour step would
        with self._timed("warm_start_s"):
            return self.init_colour_field(self.config.colour_init_steps, cams=cams)

    @contextmanager
    def _timed(self, name: str):
        """Record the block's wall time (GPU work included) in ``stage_seconds[name]``."""
        sync = torch.cuda.synchronize if self.device.type == "cuda" else (lambda: None)
        sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            sync()
            self.stage_seconds[name] = time.perf_counter() - t0

    def geometry_colours(self) -> Tensor:
        """Each Gaussian's own view-independent colour [N,3] in [0,1]: its SH degree-0 term
        (splatfacto trained with ``sh_degree`` 0 stores sigmoid logits instead)."""
        dc = self.features_dc.detach()
        if not self.imported and self.config.sh_degree == 0 and self._use_gsplat():
            return torch.sigmoid(dc)
        return (SH_C0 * dc + 0.5).clamp(0.0, 1.0)

    def init_colour_field(self, steps: int, batch: Optional[int] = None, eps: float = 0.01,
                          cams: Optional[Cameras] = None) -> Dict[str, float]:
        """Warm start: fit the field per Gaussian (no rendering) so that ``sigmoid(c_d)`` is the
        Gaussian's :meth:`geometry_colours` (target ``c_d = logit(colour)``, colours clamped to
        ``(eps, 1 - eps)``). With ``colour_init="geometry_sh"``, training ``cams`` and SH above
        degree 0, each sampled Gaussian also gets one training camera drawn at random: where that
        camera sees it, ``c_d + c_s`` is fitted to the logit of its SH colour along that direction;
        elsewhere (and in the other modes) ``||c_s||^2`` is pushed towards 0. The single-MLP
        baseline (no ``c_s``; its ``c_d`` sees the direction) fits its colour along the drawn
        direction to the SH colour where the camera sees the Gaussian, to the degree-0 one
        elsewhere. L1 in logit space, weighted by opacity, on mini-batches of Gaussians; Adam with
        the field's own learning rates, the trainer's optimizer state untouched. Returns the
        opacity-weighted mean diffuse colour error before and after (and, with SH, the share of
        draws the camera saw; the single MLP's error is along random directions, so after an SH
        start it also counts the view-dependent part it was meant to learn)."""
        fld = self.field
        n = self.num_points
        if n == 0 or steps <= 0:
            return {}
        dev = self.device
        means = self.means.detach()
        target = torch.logit(self.geometry_colours().clamp(eps, 1.0 - eps))
        weight = torch.sigmoid(self.opacities.detach().reshape(-1)).clamp_min(1e-4)
        b = min(int(batch or self.config.colour_init_batch), n)
        views = None
        if self.config.colour_init == "geometry_sh":
            views = self._sh_views(cams, eps)
        seen_draws, seen_total = torch.zeros((), device=dev), 0  # summed on the device: no per-step sync
        grid_lr, mlp_lr = self._field_lrs
        opt = torch.optim.Adam([{"params": fld.grid_parameters(), "lr": grid_lr},
                                {"params": fld.mlp_parameters(), "lr": mlp_lr}], eps=1e-15)
        before = self._colour_init_error(target)
        with torch.enable_grad():
            for _ in range(steps):
                idx = torch.randint(n, (b,), device=dev) if b < n else torch.arange(n, device=dev)
                f = fld.encode(means[idx])
                seen = None
                if views is not None:  # directions from training cameras, and whether they see it
                    dirs, full, seen = views(idx)
                    seen_draws = seen_draws + seen.sum()
                    seen_total += seen.numel()
                else:
                    dirs = torch.nn.functional.normalize(torch.randn(b, 3, device=dev), dim=-1)
                if fld.decoupled:
                    h1, h2 = fld.diffuse_hidden(f)
                    c_d = fld.diffuse(h2)
                    c_s = fld.specular(f, dirs, h1, h2)
                    spec = (c_s**2).sum(-1)
                else:  # the single MLP sees directions throughout; its colour is c_d alone
                    _, h2 = fld.diffuse_hidden(f, dirs)
                    c_d = fld.diffuse(h2)
                    spec = c_d.new_zeros(b)
                w = weight[idx]
                per = (c_d - target[idx]).abs().mean(-1)
                if seen is None:
                    per = per + spec
                elif fld.decoupled:  # seen: c_d + c_s to the SH colour; unseen: c_s towards 0
                    per = per + torch.where(seen, (c_d + c_s - full).abs().mean(-1), spec)
                else:  # the single MLP's colour: the SH colour where seen, the degree-0 one elsewhere
                    per = torch.where(seen, (c_d - full).abs().mean(-1), per)
                loss = (per * w).sum() / w.sum()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
        for p in fld.parameters():
            p.grad = None
        after = self._colour_init_error(target)
        res = {"error_before": before, "error_after": after}
        what = "degree-0 colours"
        if views is not None:
            res["seen_share"] = float(seen_draws) / max(seen_total, 1)
            what = f"SH colours from the training cameras ({res['seen_share']:.0%} of the draws seen)"
        CONSOLE.log(f"virgi: colour field warm-started from the geometry's {what} ({steps} steps of {b:,} "
                    f"Gaussians): mean diffuse colour error {before:.3f} -> {after:.3f}")
        return res

    def _sh_views(self, cams: Optional[Cameras], eps: float = 0.01):
        """For the 'geometry_sh' warm start: a function of Gaussian indices [B] that draws one
        training camera per Gaussian and returns (unit directions camera -> Gaussian [B,3], logit
        of the Gaussian's SH colour along them [B,3], whether the camera sees the Gaussian [B],
        :meth:`Cameras.project_points`). The SH coefficients are evaluated in the frame they were trained in:
        an imported file's directions are rotated back into the file's frame. None without
        training cameras or without SH coefficients above degree 0 (the degree-0 warm start is
        then the same thing)."""
        rest = self.features_rest.detach()
        if cams is None or len(cams) == 0 or rest.shape[1] == 0 or not bool((rest != 0).any()):
            CONSOLE.log("virgi: no training cameras or no SH above degree 0: degree-0 warm start")
            return None
        from virgi_ns.colour.sh import sh_colors

        dtype = self.means.dtype
        cams = cams.to(self.device, dtype)
        centres = cams.camera_centers()
        sh = torch.cat([self.features_dc.detach()[:, None], rest], dim=1)
        means = self.means.detach()
        # d_run = R d_file, so d_file = R^T d_run: row vectors times R
        rot = None if self._sh_rotation is None else self._sh_rotation.to(self.device, dtype)

        def draw(idx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            v = torch.randint(len(cams), idx.shape, device=idx.device)
            m = means[idx]
            seen = cams.project_points(m, v)[1]
            dirs = view_directions(m, centres[v])
            file_dirs = dirs if rot is None else dirs @ rot
            full = torch.logit(sh_colors(sh[idx], file_dirs).clamp(eps, 1.0 - eps))
            return dirs, full, seen

        return draw

    @torch.no_grad()
    def _colour_init_error(self, target_logit: Tensor, chunk: int = 65536) -> float:
        """Opacity-weighted mean |sigmoid(c_d) - colour| over all Gaussians (a random direction per
        Gaussian for the single MLP)."""
        fld = self.field
        means = self.means.detach()
        weight = torch.sigmoid(self.opacities.detach().reshape(-1))
        err = means.new_zeros(())
        for s in range(0, self.num_points, chunk):
            f = fld.encode(means[s : s + chunk])
            if fld.decoupled:
                _, h2 = fld.diffuse_hidden(f)
            else:
                dirs = torch.nn.functional.normalize(torch.randn(f.shape[0], 3, device=f.device), dim=-1)
                _, h2 = fld.diffuse_hidden(f, dirs)
            diff = (torch.sigmoid(fld.diffuse(h2)) - torch.sigmoid(target_logit[s : s + chunk])).abs().mean(-1)
            err = err + (diff * weight[s : s + chunk]).sum()
        return float(err / weight.sum().clamp_min(1e-12))

    @property
    def geometry_frozen(self) -> bool:
        return self._frozen

    def in_colour_stage(self, step: int) -> bool:
        return self.geometry_frozen or step >= self.colour_start

    def lambda_spec(self) -> float:
        t = min(max((self.step - self.colour_start) / self.colour_total, 0.0), 1.0)
        return self.config.lambda_spec_start + (self.config.lambda_spec_end - self.config.lambda_spec_start) * t

    def sampling_geometry(self) -> tuple[Tensor, Tensor]:
        """(means, sigmoided opacities) for the tile sampler."""
        return self.means.detach(), torch.sigmoid(self.opacities.detach().reshape(-1))

    def _use_gsplat(self) -> bool:
        return self.device.type == "cuda"

    def _get_downscale_factor(self) -> int:
        if self.geometry_frozen or not self.training:
            return 1
        return super()._get_downscale_factor()

    # --------------------------------------------------------------- callbacks
    def get_training_callbacks(self, attrs: TrainingCallbackAttributes) -> List[TrainingCallback]:
        cbs = super().get_training_callbacks(attrs)
        trainer = attrs.trainer
        pipeline = attrs.pipeline
        if attrs.optimizers is not None:  # the warm start uses the field's own learning rates
            conf = attrs.optimizers.config
            self._field_lrs = tuple(float(conf[k]["optimizer"].lr) if k in conf else lr
                                    for k, lr in zip(("field_grid", "field_mlp"), self._field_lrs))

        def colour_start(step: int) -> None:
            if step == self.colour_start:
                self.start_colour_stage()

        cbs.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], colour_start))
        if trainer is not None:
            total = int(trainer.config.max_num_iterations)
            self.colour_total = max(total - self.colour_start, 1)
            last = total - 1
            if pipeline is not None and hasattr(pipeline.datamanager, "train_raster_cameras"):
                self._train_cameras_fn = pipeline.datamanager.train_raster_cameras
            if attrs.optimizers is not None:
                self._anchor_field_schedules(attrs.optimizers, total)

            def finish(step: int) -> None:
                if step == last and self.config.specular_gating and self._train_cameras_fn is not None:
                    with self._timed("gate_s"):
                        self.build_specular_gate(self._train_cameras_fn())

            cbs.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], finish))
        return cbs

    def _anchor_field_schedules(self, optimizers, total: int) -> None:
        """Start the colour field's learning-rate decay at the colour stage's first step."""
        from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

        for name in ("field_grid", "field_mlp"):
            old = optimizers.schedulers.get(name)
            conf = optimizers.config.get(name, {}).get("scheduler")
            if old is None or not isinstance(conf, ExponentialDecaySchedulerConfig):
                continue
            opt = optimizers.optimizers[name]
            lr_init = optimizers.config[name]["optimizer"].lr
            new_conf = ExponentialDecaySchedulerConfig(
                lr_pre_warmup=lr_init, lr_final=conf.lr_final, warmup_steps=self.colour_start,
                max_steps=max(total, self.colour_start + 1), ramp="linear")
            state = old.state_dict()
            sched = new_conf.setup().get_scheduler(optimizer=opt, lr_init=lr_init)
            state["lr_lambdas"] = [None] * len(state.get("lr_lambdas", []))
            sched.load_state_dict(state)
            optimizers.schedulers[name] = sched

    def step_post_backward(self, step: int) -> None:
        if self.geometry_frozen or not self._use_gsplat() or not hasattr(self, "info"):
            return
        super().step_post_backward(step)

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
        return out

    # -------------------------------------------------------------- colours
    def _raster(self, cams: Cameras, request: Request, geometry_grad: bool = False) -> Contributions:
        means, quats, scales, opac = self.means, self.quats, torch.exp(self.scales), torch.sigmoid(self.opacities)
        with torch.set_grad_enabled(geometry_grad and torch.is_grad_enabled()):
            return rasterize(means, quats, scales, opac.reshape(-1), cams.to(self.device), request,
                             backend=self.config.raster_backend if self.geometry_frozen else "reference")

    def set_edit_stack(self, stack) -> None:
        """Render through ``stack`` (a :class:`virgi_ns.edit.stack.EditStack`, or None for the base
        colours) from now on: its enabled edits recolour ``c_d``, its ``specular_strength`` scales
        ``c_s``."""
        self.edit_stack = stack.to(self.device) if stack is not None else None
        self._edited_cache = None

    def fingerprint(self) -> str:
        """The base run's fingerprint that every edit of it carries."""
        from virgi_ns.edit.stack import field_fingerprint

        return field_fingerprint(self.means.detach(), self.field,
                                 [self.quats.detach(), torch.exp(self.scales.detach()),
                                  torch.sigmoid(self.opacities.detach()).reshape(-1)])

    def _active_stack(self):
        st = self.edit_stack
        return None if st is None or st.is_identity else st

    def _edited_diffuse_cache(self, stack) -> Tensor:
        """``c_d''`` of every Gaussian through ``stack``, recomputed when its enabled edits change."""
        key = tuple((id(e.edit), e.enabled) for e in stack.entries)
        if self._edited_cache is None or self._edited_cache[0] != key:
            self._edited_cache = (key, stack.diffuse_all(self.field, self.means.detach()))
        return self._edited_cache[1]

    def pair_colours(self, contrib: Contributions, cams: Cameras, gated: bool = False,
                     segmentation: bool = False) -> Dict[str, Tensor]:
        """Per-pair ``rgb``, ``diffuse`` (sigmoid c_d), ``c_s`` (and ``segmentation``) for a
        contribution list, through the edit stack when one is set.

        Hash features and MLP_diff run once per distinct Gaussian, MLP_spec once per pair. With
        ``gated``, MLP_spec runs only for gated Gaussians and cached diffuse colours serve the rest.
        """
        pg = contrib.pair_gaussian.to(self.device)
        pv = contrib.pair_view.to(self.device)
        stack = self._active_stack()
        if pg.numel() == 0:
            z = torch.zeros(0, 3, device=self.device)
            return {"rgb": z, "diffuse": z, "c_s": z, "segmentation": z[:, :1]}
        means = self.means.detach()
        centres = cams.to(self.device).camera_centers().to(means.dtype)
        fld = self.field
        uniq = inv = f = h2 = None
        if gated and self.gate_ready() and fld.decoupled:
            cache = self._edited_diffuse_cache(stack) if stack is not None else self.diffuse_cache
            c_d = cache[pg]
            c_s = torch.zeros_like(c_d)
            sel = self.spec_gate[pg].nonzero().flatten()
            if sel.numel() > 0:
                g_sel = pg[sel]
                u_sel, i_sel = torch.unique(g_sel, return_inverse=True)
                fs = fld.encode(means[u_sel])
                hs1, hs2 = fld.diffuse_hidden(fs)
                d = view_directions(means[g_sel], centres[pv[sel]])
                c_s[sel] = fld.specular(fs[i_sel], d, hs1[i_sel], hs2[i_sel]).to(c_s.dtype)
        else:
            uniq, inv = torch.unique(pg, return_inverse=True)
            f = fld.encode(means[uniq])
            d = view_directions(means[pg], centres[pv])
            if fld.decoupled:
                h1, h2 = fld.diffuse_hidden(f)
                c_d_u = fld.diffuse(h2)
                if stack is not None:
                    c_d_u = stack.diffuse(f, h2, c_d_u)
                c_d = c_d_u[inv]
                c_s = fld.specular(f[inv], d, h1[inv], h2[inv])
            else:
                h1, h2p = fld.diffuse_hidden(f[inv], d)
                c_d = fld.diffuse(h2p)
                if stack is not None:
                    c_d = stack.diffuse(f[inv], h2p, c_d)
                c_s = torch.zeros_like(c_d)
        k = stack.specular_strength if stack is not None else 1.0
        out = {"rgb": torch.sigmoid(c_d + k * c_s), "diffuse": torch.sigmoid(c_d), "c_s": c_s}
        if segmentation:
            out["segmentation"] = self._pair_segmentation(pg, pv, cams, uniq, inv, f, h2)
        return out

    def _pair_segmentation(self, pg, pv, cams, uniq, inv, f, h2) -> Tensor:
        """Per-pair alpha of ``segmentation_edit`` (or of all enabled edits together) [U,1];
        zeros without edits."""
        st = self.edit_stack
        if st is None or len(st) == 0:
            return torch.zeros(pg.shape[0], 1, device=self.device)
        if self.segmentation_edit is not None and not 1 <= self.segmentation_edit <= len(st):
            self.segmentation_edit = None  # the selected edit was undone: show all enabled edits
        fld = self.field
        if f is None:  # the gated path computed no features for these pairs
            uniq, inv = torch.unique(pg, return_inverse=True)
            f = fld.encode(self.means.detach()[uniq])
        if h2 is None:  # gated, or the single MLP (whose hidden layers are per pair)
            if fld.decoupled:
                _, h2 = fld.diffuse_hidden(f)
            else:  # the single MLP's hidden layers need a direction: use each pair's
                centres = cams.to(self.device).camera_centers().to(f.dtype)
                d = view_directions(self.means.detach()[pg], centres[pv])
                _, h2 = fld.diffuse_hidden(f[inv], d)
                return st.segmentation(f[inv], h2, self.segmentation_edit).to(f.dtype)
        return st.segmentation(f, h2, self.segmentation_edit)[inv].to(f.dtype)

    # ----------------------------------------------------------- specular gate
    def gate_ready(self) -> bool:
        return self.spec_magnitude.numel() == self.num_points and self.diffuse_cache.shape[0] == self.num_points

    @property
    def spec_gate(self) -> Tensor:
        return self.spec_magnitude > self.config.gate_threshold

    @torch.no_grad()
    def build_specular_gate(self, cams: Cameras, chunk: int = 65536) -> Dict[str, float]:
        """Measure max over training views of |sigmoid(c_d + c_s) - sigmoid(c_d)| per Gaussian
        (directions from each training camera's centre; visibility is not checked, which only
        keeps more Gaussians) and cache every Gaussian's ``c_d``."""
        fld = self.field
        means = self.means.detach()
        centres = cams.to(self.device).camera_centers().to(means.dtype)
        mag = torch.zeros(self.num_points, device=self.device)
        cache = torch.zeros(self.num_points, 3, device=self.device)
        if fld.decoupled:
            for s in range(0, self.num_points, chunk):
                m = means[s : s + chunk]
                f = fld.encode(m)
                h1, h2 = fld.diffuse_hidden(f)
                c_d = fld.diffuse(h2)
                cache[s : s + chunk] = c_d
                base = torch.sigmoid(c_d)
                for c in centres:
                    d = torch.nn.functional.normalize(m - c, dim=-1)
                    c_s = fld.specular(f, d, h1, h2)
                    eff = (torch.sigmoid(c_d + c_s) - base).abs().amax(-1)
                    mag[s : s + chunk] = torch.maximum(mag[s : s + chunk], eff)
        else:  # the single MLP is view dependent throughout: keep every Gaussian on the full path
            mag.fill_(float("inf"))
        self.spec_magnitude = mag
        self.diffuse_cache = cache
        kept = float(self.spec_gate.float().mean()) if self.num_points else 0.0
        CONSOLE.log(f"virgi: specular gate keeps {kept:.1%} of {self.num_points:,} Gaussians")
        return {"kept_fraction": kept}

    # --------------------------------------------------------------- outputs
    def get_outputs(self, camera: Union[NSCameras, TileBatch]) -> Dict[str, Union[Tensor, List]]:
        if isinstance(camera, TileBatch):
            return self._tile_outputs(camera)
        if not isinstance(camera, NSCameras):
            return {}
        if not self.geometry_frozen:
            if self._use_gsplat():
                return super().get_outputs(camera)
            return self._reference_geometry_outputs(camera)
        return self.render_camera(camera, gated=self.config.specular_gating and not self.training)

    def _tile_outputs(self, batch: TileBatch) -> Dict[str, Union[Tensor, List]]:
        contrib = self._raster(batch.cameras, batch.request)
        cols = self.pair_colours(contrib, batch.cameras)
        bg = self.background_color.to(self.device)
        rgb = composite(cols["rgb"], contrib, bg)
        return {"rgb": rgb, "c_s": cols["c_s"], "background": bg, "tiles": True}

    def _reference_geometry_outputs(self, camera: NSCameras) -> Dict[str, Union[Tensor, List]]:
        """CPU geometry stage: whole image through the differentiable reference, degree-0 colours."""
        d = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / d)
        cams = raster_cameras(camera[0:1] if len(camera.shape) else camera.reshape((1,)))
        camera.rescale_output_resolution(d)
        req = Request.whole_images(cams)
        contrib = self._raster(cams, req, geometry_grad=self.training)
        colours = (SH_C0 * self.features_dc + 0.5).clamp_min(0.0)
        bg = self._get_background_color() if self.training else self.background_color.to(self.device)
        rgb = composite(contrib.gather(colours), contrib, bg)[0].clamp(0, 1)
        acc = contrib.accumulation()[0, ..., None].to(rgb)
        depth = composite_depth(contrib)[0].to(rgb)
        return {"rgb": rgb, "depth": depth, "accumulation": acc, "background": bg}

    @torch.no_grad()
    def render_camera(self, camera: NSCameras, gated: bool = False, max_pixels: int = 1 << 20
                      ) -> Dict[str, Tensor]:
        """Whole-image ``rgb``, ``diffuse``, ``specular`` (rgb - diffuse, no background), ``depth``,
        ``accumulation`` and ``segmentation`` (zeros without edits) for one camera, rendered in bands
        of rows, through the edit stack when one is set."""
        cams = raster_cameras(camera[0:1] if len(camera.shape) else camera.reshape((1,)))
        W, H = int(cams.widths[0]), int(cams.heights[0])
        bg = self.background_color.to(self.device)
        rows = max(1, min(H, max_pixels // max(W, 1)))
        with_seg = self.edit_stack is not None and len(self.edit_stack) > 0
        names = ("rgb", "diffuse", "specular", "depth", "accumulation", "segmentation")
        parts: Dict[str, List[Tensor]] = {k: [] for k in names}
        for y0 in range(0, H, rows):
            h = min(rows, H - y0)
            req = Request(torch.zeros(1, dtype=torch.long), 0, y0, W, h)
            contrib = self._raster(cams, req)
            cols = self.pair_colours(contrib, cams, gated=gated, segmentation=with_seg)
            rgb = composite(cols["rgb"], contrib, bg)[0]
            if with_seg:
                parts["segmentation"].append(composite(cols["segmentation"], contrib)[0])
            else:
                parts["segmentation"].append(rgb.new_zeros(h, W, 1))
            diff = composite(cols["diffuse"], contrib, bg)[0]
            parts["rgb"].append(rgb)
            parts["diffuse"].append(diff)
            parts["specular"].append(rgb - diff)
            parts["depth"].append(composite_depth(contrib)[0].to(rgb))
            parts["accumulation"].append(contrib.accumulation()[0, ..., None].to(rgb))
        out: Dict[str, Tensor] = {k: torch.cat(v, dim=0) for k, v in parts.items()}
        out["rgb"] = out["rgb"].clamp(0, 1)
        out["diffuse"] = out["diffuse"].clamp(0, 1)
        out["background"] = bg
        return out

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: NSCameras, obb_box=None) -> Dict[str, Tensor]:
        if obb_box is not None and self.geometry_frozen and not getattr(self, "_crop_notice", False):
            self._crop_notice = True
            CONSOLE.log("virgi: crop boxes are ignored when rendering the colour field")
        self.set_crop(None if self.geometry_frozen else obb_box)
        return self.get_outputs(camera.to(self.device))  # type: ignore[return-value]

    # ----------------------------------------------------------------- losses
    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        if outputs.get("tiles"):
            valid = batch["valid"]
            gt = batch["image"][..., :3]
            mse = ((outputs["rgb"] - gt) ** 2)[valid].mean()
            return {"psnr": -10 * torch.log10(mse.clamp_min(1e-10)), "gaussian_count": self.num_points,
                    "lambda_spec": torch.tensor(self.lambda_spec())}
        return super().get_metrics_dict(outputs, batch)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        if outputs.get("tiles"):
            valid = batch["valid"]
            gt = batch["image"][..., :3]
            l1 = (outputs["rgb"] - gt).abs()[valid].mean()
            c_s = outputs["c_s"]
            spec = (c_s**2).sum(-1).mean() if c_s.numel() else l1.new_zeros(())
            return {"rgb_l1": l1, "spec_reg": self.lambda_spec() * spec}
        return super().get_loss_dict(outputs, batch, metrics_dict)

    def get_image_metrics_and_images(self, outputs, batch):
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])[..., :3]
        pred = outputs["rgb"]
        metrics = image_metrics_dict(pred, gt)
        images = [gt, pred]
        if "diffuse" in outputs:
            images += [outputs["diffuse"], (outputs["specular"] + 0.5).clamp(0, 1)]
        return metrics, {"img": torch.cat(images, dim=1)}


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
