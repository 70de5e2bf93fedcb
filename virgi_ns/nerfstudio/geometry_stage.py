"""The geometry stage of :class:`~virgi_ns.nerfstudio.model.VirgiModel`: Gaussians trained with
splatfacto's recipe (or imported from a splat), then frozen.

Steps ``[0, geometry_steps)`` train the Gaussians as splatfacto does (gsplat, densification) on a
GPU; on a CPU the torch reference rasterizer renders them with degree-0 colours and no
densification (tiny scenes only). With ``geometry_from`` the stage is skipped: the splat is
imported, moved from the capture's frame into the run's when it was saved there. Then
:meth:`GeometryStage.freeze_geometry` stops every gradient and strategy callback and fits the
colour field's box to the frozen means.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Union

import torch
from nerfstudio.cameras.cameras import Cameras as NSCameras
from nerfstudio.models.splatfacto import RGB2SH, num_sh_bases
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from virgi_ns.errors import InputError
from virgi_ns.gaussians import SH_C0, Gaussians
from virgi_ns.nerfstudio import distributed
from virgi_ns.nerfstudio.cameras import raster_cameras
from virgi_ns.nerfstudio.frames import transform_gaussians
from virgi_ns.raster import Request, composite, composite_depth


class GeometryStage:
    """Mixed into :class:`~virgi_ns.nerfstudio.model.VirgiModel` (reads its config, Gaussians and
    field): the Gaussians' start, their freezing, and the CPU geometry stage's renders."""

    # ---------------------------------------------------------------- Gaussians
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
            run_dir = path.is_dir() and not (path / "meta.json").is_file()  # a splatfacto run, not a SOG folder
            frame = "dataparser" if path.suffix.lower() in (".ckpt", ".yml", ".yaml", ".pt", ".pth") or run_dir \
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

    # ---------------------------------------------------------------- freezing
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
        distributed.broadcast_tensor(self.field.aabb)  # the subsample above is this process's own draw

    @staticmethod
    def _sync_frozen(module: "GeometryStage", _keys) -> None:
        """After a state dict is loaded: the host copy of the ``frozen`` buffer."""
        module._frozen = bool(module.frozen)

    @property
    def geometry_frozen(self) -> bool:
        return self._frozen

    def sampling_geometry(self) -> tuple[Tensor, Tensor]:
        """(means, sigmoided opacities) for the tile sampler."""
        return self.means.detach(), torch.sigmoid(self.opacities.detach().reshape(-1))

    # ------------------------------------------------------- training the geometry
    def _use_gsplat(self) -> bool:
        return self.device.type == "cuda"

    def _get_downscale_factor(self) -> int:
        if self.geometry_frozen or not self.training:
            return 1
        return super()._get_downscale_factor()

    def step_post_backward(self, step: int) -> None:
        if self.geometry_frozen or not self._use_gsplat() or not hasattr(self, "info"):
            return
        strategy_step(self.strategy, self.gauss_params, self.optimizers, self.strategy_state, step,
                      list(self._view_infos) or [self.info])

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


def strategy_step(strategy, params, optimizers, state: dict, step: int, infos: List[dict]) -> None:
    """gsplat's densification step after a geometry step over ``infos`` (gsplat's outputs of the
    views whose mean loss was back-propagated): each view's image-plane gradients enter the
    statistics scaled back by the number of views, as gsplat scales a batch of cameras; the
    last view's call refines. With one view this is splatfacto's own call."""
    if len(infos) > 1 and step < strategy.refine_stop_iter:
        for info in infos:
            info["n_cameras"] = len(infos)
        for info in infos[:-1]:
            strategy._update_state(params, state, info, packed=False)
    strategy.step_post_backward(params=params, optimizers=optimizers, state=state, step=step, info=infos[-1],
                                packed=False)


def mean_over_views(dicts: List[Dict]) -> Dict:
    """The losses (or metrics) of a geometry step over several views: key by key, the mean of
    numbers and tensors (other values: the first view's)."""
    if len(dicts) == 1:
        return dicts[0]
    out = {}
    for key, value in dicts[0].items():
        if isinstance(value, (Tensor, int, float)) and not isinstance(value, bool):
            out[key] = sum(d[key] for d in dicts) / len(dicts)
        else:
            out[key] = value
    return out


__all__ = ["GeometryStage", "mean_over_views", "strategy_step"]
