"""Benchmark (GPU): splatfacto against VIRGi on a real capture, same split and geometry steps.

Rows:
  splatfacto                 nerfstudio's recipe, ``--steps`` steps
  virgi                      geometry trained in the same run (``--steps``), then ``--colour-steps``
  virgi (imported geometry)  the splatfacto run's Gaussians imported, then ``--colour-steps``
With ``--ablation`` also decoupled x multi-view on the imported geometry (the paper's Tables 2/3),
per scene in ``--scenes``.

Columns: PSNR, SSIM, LPIPS (NaN offline) on the held-out views (every 8th frame), train time,
Gaussians, render FPS (whole eval images); for virgi also the specular gate's kept fraction, the
gated render's speed-up and the PSNR between gated and full renders; for every row the share of the
squared error on near-saturated photo pixels (``bright_se_share``, a channel >= 0.95). Writes ``results.json`` and,
for one held-out view, ``<scene>_<row>.png`` = ground truth | rgb | diffuse | specular
(|rgb - diffuse|, x2) side by side.

    python bench/train.py --data ../shared/data --out bench_out/train --steps 30000 --colour-steps 10000
"""

from __future__ import annotations

import copy
import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.table import Table

from virgi_ns.bench.settings import split_settings, typed_like
from virgi_ns.errors import InputError, atomic_path, cli_entry
from virgi_ns.metrics import offline_splatfacto_lpips

console = Console()
BRIGHT = 0.95
"""Photo pixels with a channel at or above this count as near-saturated in the error split."""
WARMUP_STEPS = 20
"""Geometry steps left out of ``geometry_step_ms`` (the first ones compile and allocate)."""


@dataclass
class Args:
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    """Folder holding beercan/ (COLMAP) and fern/ (LLFF)."""
    out: Path = Path("bench_out/train")
    scenes: List[str] = field(default_factory=lambda: ["beercan"])
    steps: int = 30000
    """splatfacto steps = virgi geometry steps."""
    colour_steps: int = 10000
    """virgi colour-stage steps."""
    ablation: bool = False
    """Also train decoupled x multi-view variants on the imported geometry (first repeat only)."""
    skip_trained_virgi: bool = False
    """Only the imported-geometry virgi rows (saves one geometry training)."""
    fps_repeats: int = 3
    colour_variants: List[str] = field(default_factory=list)
    """More imported-geometry rows (on the first repeat's splatfacto geometry), each a comma-separated
    list of config settings: 'colour_steps=3000' or dotted TrainerConfig paths such as
    'optimizers.field_grid.optimizer.lr=0.02,pipeline.datamanager.pixel_budget=327680'."""
    repeats: int = 1
    """Train every method this many times (seeds first_seed, first_seed + 1, ...; the imported-geometry
    rows use that repeat's splatfacto run) and print the mean, spread and paired differences: single
    runs of either method vary by a few tenths of a dB on beercan (bench/RESULTS.md, "Training")."""
    first_seed: int = 42
    """Seed of the first repeat (one call can go on where another stopped; see --merge)."""
    merge: List[Path] = field(default_factory=list)
    """Train nothing: read the rows of these results.json files (e.g. seeds split over two calls),
    print the tables and the summary over all of them, and write them to --out/results.json."""


def dataparser_for(scene: str, root: Path):
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
    cfg.vis = "tensorboard"
    cfg.output_dir = out / "runs"
    cfg.experiment_name = name
    cfg.timestamp = "run"
    cfg.steps_per_eval_image = 10**9
    cfg.steps_per_eval_batch = 10**9
    cfg.steps_per_eval_all_images = 10**9
    cfg.steps_per_save = 10**9
    cfg.viewer.quit_on_train_completion = True


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


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
    _sync()
    t0 = time.perf_counter()
    trainer.train()
    _sync()
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
            _sync()
            t = time.perf_counter()
            model.get_outputs_for_camera(cam)
            _sync()
            render_s += time.perf_counter() - t
            frames += 1
        if is_virgi and model.gate_ready():
            _sync()
            t = time.perf_counter()
            full = model.render_camera(cam, gated=False)
            _sync()
            t2 = time.perf_counter()
            gated = model.render_camera(cam, gated=True)
            _sync()
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
    from PIL import Image

    panels = [gt, out["rgb"]]
    if "diffuse" in out:
        panels += [out["diffuse"], (2 * out["specular"].abs()).clamp(0, 1)]
    img = torch.cat([p[..., :3].float().clamp(0, 1).cpu() for p in panels], dim=1)
    with atomic_path(path) as tmp:
        Image.fromarray((img.numpy() * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


def apply_settings(cfg, text: str) -> None:
    """Set 'a.b.c=value,...' on a TrainerConfig (dict keys and attributes alike), typed as the
    value already there; refuses unknown paths."""
    flag = "--colour-variants"
    for path, value in split_settings(text, flag):
        *parents, leaf = path.split(".")
        node = cfg
        for name in parents:
            node = node.get(name) if isinstance(node, dict) else getattr(node, name, None)
            if node is None:
                raise InputError(f"{flag}: no '{path}' in the trainer config")
        if not (leaf in node if isinstance(node, dict) else hasattr(node, leaf)):
            raise InputError(f"{flag}: no '{path}' in the trainer config")
        old = node[leaf] if isinstance(node, dict) else getattr(node, leaf)
        new = typed_like(old, value, path, flag)
        if isinstance(node, dict):
            node[leaf] = new
        else:
            setattr(node, leaf, new)


def colour_variant_config(args: Args, scene: str, text: str):
    """virgi on imported geometry with the settings of one --colour-variants entry ('colour_steps'
    sets the colour stage's length, every other key is a dotted TrainerConfig path)."""
    from method_configs.virgi import virgi_trainer_config

    steps, rest = args.colour_steps, []
    for key, value in split_settings(text, "--colour-variants"):
        if key == "colour_steps":
            steps = typed_like(args.colour_steps, value, key, "--colour-variants")
        else:
            rest.append(f"{key}={value}")
    cfg = virgi_trainer_config("virgi", geometry_steps=0, colour_steps=steps)
    cfg.pipeline.datamanager.dataparser = dataparser_for(scene, args.data)
    apply_settings(cfg, ",".join(rest))
    return cfg


def _seed_suffix(seed: int, sep: str = "-") -> str:
    """Run and picture names: nothing for the first seed (42), '-seed43' etc. after it."""
    return "" if seed == 42 else f"{sep}seed{seed}"


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


def run_scene(args: Args, scene: str, seed: int = 42) -> List[Dict[str, object]]:
    from nerfstudio.configs.method_configs import method_configs

    from method_configs.virgi import virgi_trainer_config

    rows: List[Dict[str, object]] = []
    out = args.out

    def record(name: str, pipeline, seconds: float, parts: Dict[str, float]) -> None:
        res = evaluate(pipeline, args.fps_repeats, out / f"{scene}_{_safe(name)}{_seed_suffix(seed, '_')}.png")
        row = {"scene": scene, "method": name, "seed": seed, "train_s": seconds, **res, "train_breakdown": parts}
        console.log(row)
        rows.append(row)

    # splatfacto
    cfg = copy.deepcopy(method_configs["splatfacto"])
    cfg.pipeline.datamanager.dataparser = dataparser_for(scene, args.data)
    cfg.max_num_iterations = args.steps
    cfg.machine.seed = seed
    for group in cfg.optimizers.values():  # same schedule length as virgi's geometry stage
        sch = group.get("scheduler")
        if sch is not None and hasattr(sch, "max_steps"):
            sch.max_steps = args.steps
    quiet(cfg, out, f"{scene}-splatfacto{_seed_suffix(seed)}")
    trainer, secs, ckpt_dir, parts = train(cfg)
    record("splatfacto", trainer.pipeline, secs, parts)
    ckpt = sorted(ckpt_dir.glob("*.ckpt"))[-1]
    del trainer
    torch.cuda.empty_cache()

    # virgi, geometry trained in the run
    if not args.skip_trained_virgi:
        cfg = virgi_trainer_config("virgi", geometry_steps=args.steps, colour_steps=args.colour_steps)
        cfg.pipeline.datamanager.dataparser = dataparser_for(scene, args.data)
        cfg.machine.seed = seed
        quiet(cfg, out, f"{scene}-virgi{_seed_suffix(seed)}")
        trainer, secs, _, parts = train(cfg)
        record("virgi", trainer.pipeline, secs, parts)
        del trainer
        torch.cuda.empty_cache()

    variants = [("virgi (imported geometry)", True, "multiview")]
    if args.ablation and seed == args.first_seed:
        variants += [("imported, decoupled, single-view", True, "singleview"),
                     ("imported, single MLP, multi-view", False, "multiview"),
                     ("imported, single MLP, single-view", False, "singleview")]
    configs = []
    for name, decoupled, mode in variants:
        cfg = virgi_trainer_config("virgi", decoupled=decoupled, batch_mode=mode, geometry_steps=0,
                                   colour_steps=args.colour_steps)
        cfg.pipeline.datamanager.dataparser = dataparser_for(scene, args.data)
        configs.append((name, cfg))
    if seed == args.first_seed:
        configs += [(f"imported, {v}", colour_variant_config(args, scene, v)) for v in args.colour_variants]
    for name, cfg in configs:
        cfg.pipeline.model.geometry_from = ckpt
        cfg.machine.seed = seed
        quiet(cfg, out, f"{scene}-{_safe(name)}{_seed_suffix(seed)}")
        trainer, secs, _, parts = train(cfg)
        record(name, trainer.pipeline, secs, parts)
        del trainer
        torch.cuda.empty_cache()
    return rows


def print_table(rows: List[Dict[str, object]], device: str) -> None:
    t = Table(title=f"splatfacto vs virgi on {device}")
    cols = ["scene", "method", "psnr", "ssim", "lpips", "train_s", "gaussians", "fps", "gate_kept", "gate_speedup",
            "gate_psnr_vs_full", "bright_se_share"]
    for c in cols:
        t.add_column(c)
    for r in rows:
        t.add_row(*[f"{r[c]:.4g}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols])
    console.print(t)
    b = Table(title="train time by stage (s)")
    keys = ["geometry_steps_s", "warm_start_s", "first_colour_step_s", "colour_steps_s", "colour_step_ms", "gate_s",
            "last_step_s", "outside_iterations_s", "step_ms"]
    b.add_column("method")
    for k in keys:
        b.add_column(k.replace("_s", "").replace("_", " ") if k.endswith("_s") else k)
    for r in rows:
        parts = r.get("train_breakdown", {})
        b.add_row(str(r["method"]), *[f"{parts[k]:.3g}" if k in parts else "" for k in keys])
    console.print(b)


def merged_results(paths: List[Path]) -> Dict[str, object]:
    """The rows of several results.json files as one result; they must share device and step counts,
    and no (scene, method, seed) may appear twice."""
    out: Dict[str, object] = {}
    origin: Dict[str, Path] = {}
    rows: List[Dict[str, object]] = []
    where: Dict[tuple, Path] = {}
    for p in paths:
        try:
            d = json.loads(Path(p).read_text())
            head = {k: d[k] for k in ("device", "steps", "colour_steps")}
            more = list(d["rows"])
            keys = [(str(r["scene"]), str(r["method"]), int(r["seed"])) for r in more]
            for r in more:
                float(r["psnr"]), float(r["ssim"]), float(r["train_s"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(f"--merge: {p} is not a bench/train.py results.json ({e!r})") from None
        for k, v in head.items():
            if out.setdefault(k, v) != v:
                raise InputError(f"--merge: {p} has {k}={v!r}, but {origin[k]} has {out[k]!r}")
            origin.setdefault(k, p)
        for k in keys:
            if k in where:
                raise InputError(f"--merge: {k} is in both {where[k]} and {p}; give each call its own seeds "
                                 "with --first-seed")
            where[k] = p
        rows += more
    out["rows"] = rows
    return out


def main(args: Args) -> None:
    if args.merge:
        res = merged_results(args.merge)
        rows = list(res["rows"])  # type: ignore[arg-type]
        print_table(rows, str(res["device"]))
        summary = repeat_summary(rows)
        print_summary(summary, str(res["device"]))
        args.out.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.out / "results.json") as tmp:
            tmp.write_text(json.dumps({**res, "merged_from": [str(p) for p in args.merge], "summary": summary},
                                      indent=2))
        return
    if not torch.cuda.is_available():
        raise InputError("bench/train.py needs a CUDA GPU (splatfacto trains with gsplat)")
    for scene in args.scenes:  # refuse a bad --colour-variants before any training
        for v in args.colour_variants:
            colour_variant_config(args, scene, v)
    warnings.filterwarnings("ignore", category=FutureWarning)
    offline_splatfacto_lpips()
    # both methods' CUDA extensions are built and loaded before any timing (one-time per machine)
    from gsplat.cuda._backend import _C  # noqa: F401

    from virgi_ns.raster import cuda as virgi_cuda

    ok, why = virgi_cuda.available()
    if not ok:
        raise InputError(why)
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.cuda.get_device_name(0)
    rows: List[Dict[str, object]] = []

    def write(**more) -> None:
        with atomic_path(args.out / "results.json") as tmp:
            tmp.write_text(json.dumps({"device": device, "steps": args.steps, "colour_steps": args.colour_steps,
                                       "rows": rows, **more}, indent=2))

    for scene in args.scenes:
        for r in range(max(1, args.repeats)):
            rows += run_scene(args, scene, args.first_seed + r)
            write()  # after every run: a cut-off call keeps them
    print_table(rows, device)
    if args.repeats > 1:
        summary = repeat_summary(rows)
        print_summary(summary, device)
        write(summary=summary)


def repeat_summary(rows: List[Dict[str, object]]) -> List[Dict[str, object]]:
    """Per (scene, method): mean and sample standard deviation of PSNR, SSIM and train time over the
    seeds, and the mean and range of the PSNR difference to splatfacto's run of the same seed."""
    out = []
    keys = sorted({(str(r["scene"]), str(r["method"])) for r in rows}, key=lambda k: (k[0], k[1] != "splatfacto", k[1]))
    for scene, method in keys:
        mine = [r for r in rows if r["scene"] == scene and r["method"] == method]
        ref = {r["seed"]: r for r in rows if r["scene"] == scene and r["method"] == "splatfacto"}
        row: Dict[str, object] = {"scene": scene, "method": method, "runs": len(mine)}
        for k in ("psnr", "ssim", "train_s"):
            v = np.array([float(r[k]) for r in mine])
            row[k] = float(v.mean())
            row[f"{k}_std"] = float(v.std(ddof=1)) if len(v) > 1 else float("nan")
        d = np.array([float(r["psnr"]) - float(ref[r["seed"]]["psnr"]) for r in mine if r["seed"] in ref])
        if method != "splatfacto" and len(d):
            row["psnr_vs_splatfacto"] = float(d.mean())
            row["psnr_vs_splatfacto_min"], row["psnr_vs_splatfacto_max"] = float(d.min()), float(d.max())
            if "imported" not in method:  # imported rows train the colour stage alone: no time ratio
                t = np.array([float(r["train_s"]) / float(ref[r["seed"]]["train_s"]) for r in mine if r["seed"] in ref])
                row["train_time_vs_splatfacto"] = float(t.mean())
        out.append(row)
    return out


def print_summary(summary: List[Dict[str, object]], device: str) -> None:
    t = Table(title=f"mean over seeds on {device} (+- sample std; differences paired by seed)")
    for c in ("scene", "method", "runs", "PSNR", "SSIM", "train s", "PSNR - splatfacto (min..max)", "time / splatfacto"):
        t.add_column(c)
    for r in summary:
        d = (f"{r['psnr_vs_splatfacto']:+.2f} ({r['psnr_vs_splatfacto_min']:+.2f}..{r['psnr_vs_splatfacto_max']:+.2f})"
             if "psnr_vs_splatfacto" in r else "")
        t.add_row(str(r["scene"]), str(r["method"]), str(r["runs"]), f"{r['psnr']:.2f} +- {r['psnr_std']:.2f}",
                  f"{r['ssim']:.3f} +- {r['ssim_std']:.3f}", f"{r['train_s']:.1f} +- {r['train_s_std']:.1f}", d,
                  f"{r['train_time_vs_splatfacto']:.2f}x" if "train_time_vs_splatfacto" in r else "")
    console.print(t)


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
