"""The colour stage of :class:`~virgi_ns.nerfstudio.model.VirgiModel`: the colour field trained on
multi-view tile batches over frozen geometry.

At the stage's first step (a training callback, once per process) a warm start fits the field
to each Gaussian's own colours, per Gaussian and without rendering (``colour_init``):
``c_d`` to its degree-0 colour and, with ``"geometry_sh"``, ``c_d + c_s`` to its SH colour seen
from training cameras that see it (:meth:`ColourStage.init_colour_field`). Then each step
renders only the tiles of a batch (:mod:`virgi_ns.nerfstudio.datamanager`): the colour field runs
for the (view, Gaussian) pairs the tiles touch. Loss ``L1 + lambda_spec * mean ||c_s||^2``,
``lambda_spec`` decaying linearly from ``lambda_spec_start`` to ``lambda_spec_end`` over the
stage. The field's learning-rate decay starts with the stage, and the last step measures the
specular gate (:mod:`virgi_ns.nerfstudio.render_path`).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Dict, List, Optional, Union

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from virgi_ns.colour.field import view_directions
from virgi_ns.gaussians import SH_C0
from virgi_ns.nerfstudio import distributed
from virgi_ns.nerfstudio.datamanager import TileBatch
from virgi_ns.raster import Cameras, composite


class ColourStage:
    """Mixed into :class:`~virgi_ns.nerfstudio.model.VirgiModel` (reads its config, Gaussians and
    field): the warm start, the tile batches' outputs and loss, and the stage's callbacks."""

    # ---------------------------------------------------------------- warm start
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
            res = self.init_colour_field(self.config.colour_init_steps, cams=cams)
        distributed.broadcast_state(self.field)  # each process drew its own mini-batches and cameras
        return res

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
                                {"params": fld.mlp_parameters(), "lr": mlp_lr}], eps=1e-15, foreach=True)
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
        from virgi_ns.colour.sh import sh_colours

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
            full = torch.logit(sh_colours(sh[idx], file_dirs).clamp(eps, 1.0 - eps))
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

    # -------------------------------------------------------------- the schedule
    def in_colour_stage(self, step: int) -> bool:
        return self.geometry_frozen or step >= self.colour_start

    def lambda_spec(self) -> float:
        t = min(max((self.step - self.colour_start) / self.colour_total, 0.0), 1.0)
        return self.config.lambda_spec_start + (self.config.lambda_spec_end - self.config.lambda_spec_start) * t

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
            if step >= self.colour_start and self.gate_ready():
                self.drop_specular_gate()  # the field is about to change: its cached colours would be stale

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

    # ----------------------------------------------------------- tile batches
    def _tile_outputs(self, batch: TileBatch) -> Dict[str, Union[Tensor, List]]:
        contrib = self.contributions(batch.cameras, batch.request)
        cols = self.pair_colours(contrib, batch.cameras)
        bg = self.background_color.to(self.device)
        rgb = composite(cols["rgb"], contrib, bg)
        return {"rgb": rgb, "c_s": cols["c_s"], "background": bg, "tiles": True}

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
            err = (outputs["rgb"] - gt).abs()[valid]
            c_s = outputs["c_s"]
            share = batch.get("loss_norm")
            if share is None:
                l1 = err.mean()
                spec = (c_s**2).sum(-1).mean() if c_s.numel() else l1.new_zeros(())
            else:  # several processes: this one's part of the means over all of them
                share = share.to(err)
                l1 = err.mean(-1).sum() / share[0]  # share: (valid pixels, pairs) over all / processes
                spec = (c_s**2).sum() / share[1]
            return {"rgb_l1": l1, "spec_reg": self.lambda_spec() * spec}
        return super().get_loss_dict(outputs, batch, metrics_dict)


__all__ = ["ColourStage"]
