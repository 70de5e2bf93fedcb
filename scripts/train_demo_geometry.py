"""(GPU) Train the demo's geometry: splatfacto on the bundle's views, pruned, as a splat file.

    python scripts/train_demo_geometry.py     # how the bundled virgi_ns/assets/beercan_small/geometry.spz was made

The demo imports ``geometry.spz`` (or ``geometry.ply``) from the bundle when it is there (``virgi_ns.demo``), which
spares a CPU the geometry stage. This script trains nerfstudio's splatfacto (gsplat, CUDA) on the
bundle's *training* views only (the same every-8th hold-out as the demo, so the demo's held-out
views stay unseen), on the same views rebuilt at ``--downscale`` from the COLMAP beercan when
``--source`` is present (sharper geometry), else on the bundled images. With
``--all-views`` (the default when ``--source`` is there) it trains on every photo of the capture
except the bundle's held-out ones (67 of 71 for beercan: far fewer floaters in views between the
training photos); the held-out photos are never seen either way. It then

- keeps the ``--cap`` Gaussians with the largest ``opacity * size`` (geometric mean of the three
  scales), after dropping those below ``--min-opacity``;
- trains the kept Gaussians for ``--finetune-steps`` more steps without densification (pruning
  leaves holes that a few thousand steps close again);
- moves them from the run's frame back into the capture frame (COLMAP's; the inverse of the
  dataparser's orient/centre/scale), and writes SH degree 0 (the colour field replaces colours) as
  ``.spz`` by default: its quantisation is far below what the demo can see, at a quarter of a
  ``.ply``'s size;
- prints the held-out PSNR of the splatfacto render before pruning, after it, and after fine-tuning.

Nothing is downloaded: splatfacto's LPIPS metric (which fetches AlexNet) is replaced by a NaN
stand-in when its weights are not cached.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro
from rich.console import Console

from virgi_ns.data.bundle import BUNDLED_SCENE, BundleDataParserConfig
from virgi_ns.data.make_bundle import DEFAULT_SOURCE
from virgi_ns.errors import InputError, cli_entry
from virgi_ns.metrics import offline_splatfacto_lpips

console = Console()
HOLDOUT_INTERVAL = BundleDataParserConfig.eval_interval  # the demo holds out every 8th frame of the bundle


@dataclass
class Args:
    scene: Path = BUNDLED_SCENE
    """The bundle whose views (and hold-out) define the training set."""
    source: Path = DEFAULT_SOURCE
    """COLMAP beercan; when present the bundle's views are rebuilt from it at --downscale."""
    downscale: int = 2
    """Downscale of the rebuilt views (1: 720x1280). Ignored without --source."""
    all_views: bool = True
    """With --source: train on every photo of the capture but the bundle's held-out ones."""
    out: Path = BUNDLED_SCENE / "geometry.spz"
    """The written file: .spz or .ply (by its suffix; the demo reads a bundle's geometry.spz, else geometry.ply)."""
    steps: int = 15000
    cap: int = 150000
    """Most Gaussians kept."""
    min_opacity: float = 0.02
    finetune_steps: int = 3000
    """Steps of training the kept Gaussians after pruning (splatfacto's loss, no densification)."""
    sh_degree: int = 3
    """splatfacto's SH degree while training (the file keeps degree 0)."""
    seed: int = 42


@torch.no_grad()
def heldout_psnr(pipeline) -> float:
    model, dm = pipeline.model, pipeline.datamanager
    model.eval()
    vals = []
    for i in range(len(dm.eval_dataset)):
        gt = dm.cached_eval[i]["image"].to(model.device)
        gt = (gt.float() / 255.0 if gt.dtype == torch.uint8 else gt)[..., :3]
        cam = dm.eval_dataset.cameras[i : i + 1].to(model.device)
        out = model.get_outputs_for_camera(cam)
        pred = out["rgb"].clamp(0, 1)
        vals.append(-10 * math.log10(max(float(((pred - gt) ** 2).mean()), 1e-10)))
    model.train()
    return sum(vals) / max(len(vals), 1)


def prune_scores(opacity_logits: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """``sigmoid(opacity) * geometric mean of the scales`` per Gaussian."""
    return torch.sigmoid(opacity_logits.reshape(-1)) * torch.exp(log_scales.mean(-1))


def to_capture_frame(params: dict, transform: torch.Tensor, scale: float):
    """splatfacto parameters (run frame, ``x_run = scale (R x + t)``, ``transform`` = [R|t]) ->
    :class:`Gaussians` in the capture frame, SH degree 0."""
    from virgi_ns.gaussians import Gaussians
    from virgi_ns.nerfstudio.frames import transform_gaussians

    T = torch.as_tensor(transform).float().cpu()[:3]
    R, t = T[:, :3], T[:, 3]
    inverse = torch.cat([R.T, (-R.T @ t)[:, None]], 1)  # x = R^T (x_run / scale) - R^T t
    means = params["means"].float().cpu() / scale
    log_scales = params["scales"].float().cpu() - math.log(scale)
    means, log_scales, quats = transform_gaussians(means, log_scales, params["quats"].float().cpu(), inverse, 1.0)
    return Gaussians(means=means, scales=log_scales, quats=torch.nn.functional.normalize(quats, dim=-1),
                     opacities=params["opacities"].float().cpu().reshape(-1),
                     sh=params["features_dc"].float().cpu()[:, None, :])


def main(args: Args) -> None:
    if not torch.cuda.is_available():
        raise InputError("train_demo_geometry.py trains splatfacto with gsplat: it needs a CUDA GPU")
    tmp = Path(tempfile.mkdtemp(prefix="virgi_geometry_"))
    try:
        _train_and_write(args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _train_and_write(args: Args, tmp: Path) -> None:
    from nerfstudio.configs.method_configs import method_configs

    from virgi_ns.io import save_splat

    scene = args.scene
    if args.source.is_dir() and (args.source / "sparse" / "0").is_dir():
        from virgi_ns.data.make_bundle import Args as BundleArgs
        from virgi_ns.data.make_bundle import make_bundle

        frames = json.loads((scene / "transforms.json").read_text())["frames"]
        # nerfstudio sorts the frames by file name before taking every 8th as held out
        names_sorted = sorted(f["file_path"] for f in frames)
        held_out = [n for i, n in enumerate(names_sorted) if i % HOLDOUT_INTERVAL == 0]
        n_views = len(frames)
        if args.all_views:
            from nerfstudio.data.utils.colmap_parsing_utils import read_images_binary

            n_views = len(read_images_binary(args.source / "sparse" / "0" / "images.bin"))
        meta = make_bundle(BundleArgs(source=args.source, out=tmp / "scene", views=n_views, downscale=args.downscale))
        names = [f["file_path"] for f in meta["frames"]]
        missing = sorted(set(held_out) - set(names))
        if missing:
            raise InputError(f"the rebuilt views lack the bundle's held-out photos {missing}")
        # nerfstudio's explicit split: the bundle's held-out photos are the eval views
        meta["train_filenames"] = [n for n in names if n not in held_out]
        meta["val_filenames"] = meta["test_filenames"] = held_out
        (tmp / "scene" / "transforms.json").write_text(json.dumps(meta, indent=1) + "\n")
        scene = tmp / "scene"
        console.log(f"training on {len(meta['train_filenames'])} views rebuilt at 1/{args.downscale} from "
                    f"{args.source}; held out: {', '.join(held_out)}")
    else:
        console.log(f"training on the bundled images in {scene}")
    offline_splatfacto_lpips()
    torch.manual_seed(args.seed)
    cfg = copy.deepcopy(method_configs["splatfacto"])
    cfg.pipeline.datamanager.dataparser = BundleDataParserConfig(data=scene)
    cfg.pipeline.datamanager.data = scene
    cfg.pipeline.model.sh_degree = args.sh_degree
    cfg.max_num_iterations = args.steps
    for group in cfg.optimizers.values():
        sch = group.get("scheduler")
        if sch is not None and hasattr(sch, "max_steps"):
            sch.max_steps = args.steps
    cfg.vis = "tensorboard"
    cfg.output_dir = tmp / "runs"
    cfg.experiment_name = "demo-geometry"
    cfg.timestamp = "run"
    cfg.steps_per_eval_image = cfg.steps_per_eval_batch = cfg.steps_per_eval_all_images = 10**9
    cfg.steps_per_save = 10**9
    cfg.viewer.quit_on_train_completion = True
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    t0 = time.perf_counter()
    trainer.train()
    console.log(f"splatfacto: {args.steps} steps in {time.perf_counter() - t0:.0f} s")
    pipeline = trainer.pipeline
    model = pipeline.model
    psnr_full = heldout_psnr(pipeline)
    n_all = model.num_points

    p = {k: v.detach() for k, v in model.gauss_params.items()}
    score = prune_scores(p["opacities"], p["scales"])
    score[torch.sigmoid(p["opacities"].reshape(-1)) < args.min_opacity] = -1.0
    keep = torch.argsort(score, descending=True)[: min(args.cap, int((score >= 0).sum()))]
    keep = keep.sort().values
    for k in list(model.gauss_params.keys()):
        model.gauss_params[k] = torch.nn.Parameter(p[k][keep])
    psnr_pruned = heldout_psnr(pipeline)
    console.log(f"kept {len(keep):,} of {n_all:,} Gaussians: held-out PSNR {psnr_full:.2f} -> {psnr_pruned:.2f} dB")
    psnr_tuned = psnr_pruned
    if args.finetune_steps > 0:
        finetune(pipeline, args.finetune_steps, start_step=args.steps)
        psnr_tuned = heldout_psnr(pipeline)
        console.log(f"fine-tuned {args.finetune_steps} steps: held-out PSNR {psnr_tuned:.2f} dB")

    out = pipeline.datamanager.train_dataparser_outputs
    tuned = {k: v.detach() for k, v in model.gauss_params.items()}
    g = to_capture_frame(tuned, out.dataparser_transform, float(out.dataparser_scale))
    save_splat(g, args.out)
    console.log(f"wrote {args.out}: {len(g):,} of {n_all:,} Gaussians "
                f"({args.out.stat().st_size / 1e6:.1f} MB); held-out PSNR {psnr_full:.2f} dB before pruning, "
                f"{psnr_pruned:.2f} dB after, {psnr_tuned:.2f} dB after fine-tuning")


# learning rates of the fine-tuning (splatfacto's, the means' at its schedule's end x10, decaying 10x)
FINETUNE_LRS = {"means": 1.6e-5, "features_dc": 0.0025, "features_rest": 0.0025 / 20, "opacities": 0.05,
                "scales": 0.005, "quats": 0.001}


def finetune(pipeline, steps: int, start_step: int) -> None:
    """Train the model's Gaussians ``steps`` steps with splatfacto's loss, no densification or
    pruning (the trainer's callbacks are not run), Adam from fresh state."""
    from rich.progress import track

    model = pipeline.model
    model.train()
    groups = [{"params": [model.gauss_params[k]], "lr": lr, "initial_lr": lr}
              for k, lr in FINETUNE_LRS.items() if k in model.gauss_params]
    for g in groups:
        g["params"][0].requires_grad_(True)
    opt = torch.optim.Adam(groups, eps=1e-15)
    decay = 0.1 ** (1.0 / max(steps, 1))
    for i in track(range(steps), description="fine-tuning after pruning", console=console):
        model.step = start_step + i
        _, losses, _ = pipeline.get_train_loss_dict(start_step + i)
        opt.zero_grad(set_to_none=True)
        sum(losses.values()).backward()
        opt.step()
        for g in groups:
            g["lr"] *= decay
    model.eval()


if __name__ == "__main__":
    cli_entry(lambda: main(tyro.cli(Args)))
