"""Training and evaluating a run as the benchmarks do: a dataparser for a capture, a quiet trainer config, one
training timed by stage, the held-out figures, and the evaluation set's runs (trained once, then reused)."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
from rich.console import Console

from common.evalset import EvalScene, dataparser_config
from common.results import safe_name
from common.settings import apply_settings
from virgi_ns.errors import InputError, atomic_path

CONSOLE = Console(width=220)
BRIGHT = 0.95
"""Photo pixels with a channel at or above this count as near-saturated in the error split."""
WARMUP_STEPS = 20
"""Geometry steps left out of ``geometry_step_ms`` (the first ones compile and allocate)."""


def dataparser_for(scene: str, root: Path):
    """The dataparser of capture ``root/scene``: COLMAP (``sparse/0``), nerfstudio's own (``transforms.json``)
    or LLFF, every 8th frame held out."""
    path = root / scene
    if not path.is_dir():
        raise InputError(f"scene folder not found: {path}")
    if (path / "sparse" / "0").is_dir():
        from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

        return ColmapDataParserConfig(data=path, colmap_path=Path("sparse/0"), images_path=Path("images"),
                                      eval_mode="interval", eval_interval=8, load_3D_points=True,
                                      downscale_factor=1)
    from virgi_ns.data.llff import LLFFDataParserConfig

    if (path / "transforms.json").is_file():  # nerfstudio's own format (e.g. tests/virgi_scene.py's capture)
        from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

        return NerfstudioDataParserConfig(data=path, eval_mode="interval", eval_interval=8, load_3D_points=False)
    images = "images_8" if (path / "images_8").is_dir() else "images"
    return LLFFDataParserConfig(data=path, images_dir=images, llffhold=8)


def quiet(cfg, out: Path, name: str) -> None:
    """A trainer config that writes its run to ``out/runs/name/.../run`` and evaluates, saves and shows
    nothing until it ends."""
    cfg.vis = "tensorboard"
    cfg.output_dir = out / "runs"
    cfg.experiment_name = name
    cfg.timestamp = "run"
    cfg.steps_per_eval_image = 10**9
    cfg.steps_per_eval_batch = 10**9
    cfg.steps_per_eval_all_images = 10**9
    cfg.steps_per_save = 10**9
    cfg.viewer.quit_on_train_completion = True


def sync(device=None) -> None:
    """Wait for the GPU's queue (``device``, default the current one; nothing for a CPU device or without a
    GPU), so that wall-clock timings hold the work they time."""
    if torch.cuda.is_available() and (device is None or torch.device(device).type == "cuda"):
        torch.cuda.synchronize(device)


def train(cfg, local_rank: int = 0, world_size: int = 1) -> tuple[object, float, Path, Dict[str, float]]:
    """Train (as process ``local_rank`` of ``world_size``); returns (trainer, seconds, checkpoint
    folder, breakdown). The breakdown sums the wall time of nerfstudio's train iterations by stage
    without extra synchronisation (the CPU runs at most a few steps ahead of the GPU, and every
    10th step logs a loss, which synchronises), and names the time spent outside the iterations
    (checkpoint writing, the trainer's own set-up)."""
    if local_rank == 0:  # config.yml beside the checkpoint, so bench/export.py and bench/edit.py can load the run
        cfg.save_config()
    trainer = cfg.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    steps: List[tuple[int, float]] = []
    inner = trainer.train_iteration

    def timed_iteration(step: int):
        t = time.perf_counter()
        out = inner(step)
        steps.append((step, time.perf_counter() - t))
        return out

    trainer.train_iteration = timed_iteration  # type: ignore[method-assign]
    sync()
    t0 = time.perf_counter()
    trainer.train()
    sync()
    total = time.perf_counter() - t0
    return trainer, total, Path(cfg.get_base_dir()) / "nerfstudio_models", breakdown(trainer, steps, total)


def breakdown(trainer, steps: List[tuple[int, float]], total: float) -> Dict[str, float]:
    """Seconds by stage: geometry steps, the colour stage's first step (warm start included), the
    other colour steps, the last step (the specular gate's measurement), outside the iterations."""
    from virgi_ns.nerfstudio.model import VirgiModel

    model = trainer.pipeline.model
    res: Dict[str, float] = {"iterations_s": sum(s for _, s in steps)}
    res["outside_iterations_s"] = total - res["iterations_s"]
    if isinstance(model, VirgiModel) and steps:
        c0, last = model.colour_start, steps[-1][0]
        geo = [s for i, s in steps if i < c0]
        col = [s for i, s in steps if c0 < i < last]
        res["geometry_steps_s"] = sum(geo)
        settled = geo[WARMUP_STEPS:] or geo  # past the first steps' compilation and allocations
        res["geometry_step_ms"] = 1e3 * sum(settled) / max(len(settled), 1)
        res["first_colour_step_s"] = sum(s for i, s in steps if i == c0)
        res["colour_steps_s"] = sum(col)
        res["colour_step_ms"] = 1e3 * sum(col) / max(len(col), 1)
        res["last_step_s"] = sum(s for i, s in steps if i == last and i != c0)
        res.update({k: float(v) for k, v in model.stage_seconds.items()})
    elif steps:
        res["step_ms"] = 1e3 * res["iterations_s"] / len(steps)
    return res


@torch.no_grad()
def evaluate(pipeline, repeats: int, picture: Optional[Path]) -> Dict[str, float]:
    """Held-out PSNR, SSIM, LPIPS, render FPS (``repeats`` timed renders a view), the error's share on
    near-saturated pixels and, for a VIRGi run, the specular gate's figures; ``picture``: where the first
    view's panels go."""
    from virgi_ns.metrics import image_metrics
    from virgi_ns.nerfstudio.model import VirgiModel

    model = pipeline.model
    model.eval()
    dm = pipeline.datamanager
    n = len(dm.eval_dataset)
    scores: Dict[str, List[float]] = {"psnr": [], "ssim": [], "lpips": []}
    render_s = 0.0
    frames = 0
    is_virgi = isinstance(model, VirgiModel)
    gated_psnr, full_s, gated_s = [], 0.0, 0.0
    se_sum = se_bright = px = px_bright = 0.0
    for i in range(n):
        gt = dm.cached_eval[i]["image"].to(model.device)  # first: caching undistorts and fixes the cameras
        cam = dm.eval_dataset.cameras[i : i + 1].to(model.device)
        gt = (gt.float() / 255.0 if gt.dtype == torch.uint8 else gt)[..., :3]
        out = model.get_outputs_for_camera(cam)
        for k, v in image_metrics(out["rgb"], gt).items():
            scores[k].append(v)
        # where the error sits: near-saturated photo pixels (highlights) against the rest
        se = ((out["rgb"][..., :3].float().clamp(0, 1) - gt) ** 2).sum(-1)
        bright = gt.amax(-1) >= BRIGHT
        se_sum += float(se.sum())
        se_bright += float(se[bright].sum())
        px += se.numel()
        px_bright += float(bright.sum())
        for _ in range(repeats):
            sync()
            t = time.perf_counter()
            model.get_outputs_for_camera(cam)
            sync()
            render_s += time.perf_counter() - t
            frames += 1
        if is_virgi and model.gate_ready():
            sync()
            t = time.perf_counter()
            full = model.render_camera(cam, gated=False)
            sync()
            t2 = time.perf_counter()
            gated = model.render_camera(cam, gated=True)
            sync()
            full_s += t2 - t
            gated_s += time.perf_counter() - t2
            mse = float(((full["rgb"] - gated["rgb"]) ** 2).mean())
            gated_psnr.append(-10 * math.log10(max(mse, 1e-12)))
        if i == 0 and picture is not None:
            save_picture(picture, gt, out)
    res = {k: float(np.nanmean(v)) if v else float("nan") for k, v in scores.items()}
    res["fps"] = frames / max(render_s, 1e-9)
    res["bright_px_share"] = px_bright / max(px, 1.0)
    res["bright_se_share"] = se_bright / max(se_sum, 1e-12)
    res["gaussians"] = int(model.num_points)
    if is_virgi and gated_psnr:
        res["gate_kept"] = float(model.spec_gate.float().mean())
        res["gate_speedup"] = full_s / max(gated_s, 1e-9)
        res["gate_psnr_vs_full"] = float(np.mean(gated_psnr))
    return res


def save_picture(path: Path, gt: torch.Tensor, out: Dict[str, torch.Tensor]) -> None:
    """Ground truth | rgb | diffuse | 2x |specular| side by side, as a PNG."""
    from PIL import Image

    panels = [gt, out["rgb"]]
    if "diffuse" in out:
        panels += [out["diffuse"], (2 * out["specular"].abs()).clamp(0, 1)]
    img = torch.cat([p[..., :3].float().clamp(0, 1).cpu() for p in panels], dim=1)
    with atomic_path(path) as tmp:
        Image.fromarray((img.numpy() * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


def evalset_run(args, scene: EvalScene, folder: Path) -> Path:
    """The config.yml of the trained run of an evaluation-set scene's capture (``folder``): given
    (``args.runs``, where it has them), found under ``args.train_out``, or trained now with ``args.seed``,
    ``args.geometry_steps`` + ``args.colour_steps`` and ``args.train_settings`` where it has them (a synthetic scene imports its
    own Gaussians). ``args``: the calling benchmark's arguments (``bench/edit.py``'s, ``bench/render.py``'s)."""
    runs, settings = getattr(args, "runs", {}), getattr(args, "train_settings", "")
    if scene.capture in runs:
        return runs[scene.capture]
    name = f"{scene.capture.replace('/', '_')}-s{args.seed}" + (f"-{safe_name(settings)}" if settings else "")
    cfg_path = args.train_out / "runs" / name / "virgi" / "run" / "config.yml"
    if any((cfg_path.parent / "nerfstudio_models").glob("step-*.ckpt")):  # a run cut short has no checkpoint
        return cfg_path
    from method_configs.virgi import virgi_trainer_config

    known = folder / "geometry.ply" if scene.synthetic else None  # a synthetic scene's own Gaussians
    c = virgi_trainer_config("virgi", geometry_steps=0 if known else args.geometry_steps, colour_steps=args.colour_steps)
    c.pipeline.datamanager.dataparser = dataparser_config(folder)
    c.pipeline.model.geometry_from = known
    c.machine.seed = args.seed
    if settings:
        apply_settings(c, settings, "--train-settings")
    if not torch.cuda.is_available():  # a CPU (tests): the reference rasterizer trains the geometry too
        c.machine.device_type = "cpu"
    quiet(c, args.train_out, name)
    CONSOLE.log(f"training {scene.capture} (seed {args.seed}, "
                f"{'its known geometry' if known else f'{args.geometry_steps} geometry steps'} + {args.colour_steps} steps)")
    trainer, secs, _, _ = train(c)
    CONSOLE.log(f"trained {scene.capture} in {secs:.0f} s")
    del trainer
    torch.cuda.empty_cache()
    return Path(c.get_base_dir()) / "config.yml"
