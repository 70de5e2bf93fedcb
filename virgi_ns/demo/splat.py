"""``make demo SPLAT=path`` (``python -m virgi_ns.demo.splat --splat PATH``): recolour any splat, with no photos.

1. **Train** ``ns-train virgi --data PATH splat``'s run in process (:mod:`virgi_ns.data.splat`: views
   rendered from the splat itself, its Gaussians frozen, the colour stage alone), saved to ``OUT/run``.
2. **Click**: ``virgi-edit pick`` on that run, at ``--camera-index``/``--pixel`` or, by default, at the
   most colourful spot of the training views (the largest chroma ``max(rgb) - min(rgb)`` of the views
   blurred over 5x5 pixels), to ``--colour``.
3. **Export** ``virgi-export`` the run unedited (``unedited.ply``) and recoloured (``recoloured.ply`` and
   ``recoloured.spz``).
4. **Measure** at the held-out views, in the file's frame: the original splat, the unedited export and
   the recoloured export, each rendered as a splat (gsplat on a GPU, the reference rasterizer on a
   CPU); the edit's segmentation rendered from the run. ``fidelity``: PSNR of the unedited export
   against the original; ``leak``: PSNR of the recoloured export against the original where the
   segmentation is below 0.01 (pixels holding no more than 1% of recoloured Gaussians; the part's own
   anti-aliased edge lies between); ``recoloured``: the share of the coloured pixels (chroma above
   0.1) where the segmentation is at least 0.5 whose hue lies within 30 degrees of the colour's;
   ``part_share``: the share of the view where the segmentation is at least 0.5 (a leaking
   segmentation shows here, and in the grid's last column).
   ``grid.png``: original | unedited export | recoloured export | segmentation, one row per view.
"""

from __future__ import annotations

import colorsys
import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional

import numpy as np
import torch
import tyro
from rich.console import Console

from virgi_ns.demo.config import demo_device
from virgi_ns.errors import InputError, atomic_path, cli_entry

__all__ = ["SplatDemoConfig", "choose_click", "main", "run"]


@dataclass
class SplatDemoConfig:
    """Recolour a splat file (.ply, .compressed.ply, .spz) from one click: train, pick, export, measure."""

    splat: Path
    """The splat file."""
    out: Path = Path("demo_out/splat")
    """Output folder (grid.png, metrics.json, unedited.ply, recoloured.ply/.spz, the run in run/)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    views: Optional[int] = None
    """Training views; default the dataparser's (64) on a GPU, 16 on a CPU."""
    eval_views: Optional[int] = None
    """Held-out views; default views / 8 on a GPU, 4 on a CPU."""
    max_resolution: Optional[int] = None
    """Largest image side; default the dataparser's (1024) on a GPU, 256 on a CPU."""
    min_resolution: Optional[int] = None
    """Smallest image side; default the dataparser's (256) on a GPU, 128 on a CPU."""
    steps: Optional[int] = None
    """Colour steps; default the dataparser's (1000) on a GPU, 300 on a CPU."""
    camera_index: Optional[int] = None
    """Training view of the click (with --pixel); default: the most colourful spot's."""
    pixel: Optional[tuple[int, int]] = None
    """Clicked pixel X Y of --camera-index."""
    colour: str = "#20c040"
    """The new colour of what the click selects."""
    tolerance: float = 0.2
    """The pick's hue tolerance (0..1, x 90 degrees)."""
    grid_views: int = 4
    """Held-out views shown in grid.png."""
    cache_dir: Optional[Path] = None
    """Where the views are cached (the dataparser's --cache-dir)."""
    colour_init_steps: Optional[int] = None
    """Warm-start steps; default the model's (300) on a GPU, 200 on a CPU."""
    hash_log2: Optional[int] = None
    """log2 of the hash table; default the model's (19) on a GPU, 17 on a CPU."""
    pixel_budget: Optional[int] = None
    """Pixels per colour step; default the recipe's on a GPU, 10240 on a CPU."""
    reuse_run: bool = False
    """Keep ``OUT/run`` when it holds a trained run (another click on the same run); its edits are reset first."""
    seed: int = 0


# ----------------------------------------------------------------------------- training
def trainer_config(cfg: SplatDemoConfig, dev: torch.device):
    """``ns-train virgi --data SPLAT splat``'s config with the demo's sizes, made a splat run."""
    from method_configs.virgi import virgi_trainer_config
    from virgi_ns.colour.field import ColourFieldConfig
    from virgi_ns.data.splat import SplatDataParserConfig, prepare_splat_run

    cpu = dev.type != "cuda"
    tc = virgi_trainer_config("virgi")
    parser = SplatDataParserConfig(data=cfg.splat, cache_dir=cfg.cache_dir)
    for name, cpu_default in (("views", 16), ("eval_views", 4), ("max_resolution", 256), ("min_resolution", 128),
                              ("steps", 300)):
        value = getattr(cfg, name)
        if value is None and cpu:
            value = cpu_default
        if value is not None:
            setattr(parser, name, int(value))
    dm = tc.pipeline.datamanager
    dm.dataparser = parser
    dm.data = cfg.splat
    dm.cache_images = "gpu"  # keeps the images on the manager's device, whichever it is
    if cfg.pixel_budget is not None or cpu:
        dm.pixel_budget = cfg.pixel_budget if cfg.pixel_budget is not None else 2 * 5 * 32 * 32
    m = tc.pipeline.model
    if cfg.colour_init_steps is not None or cpu:
        m.colour_init_steps = cfg.colour_init_steps if cfg.colour_init_steps is not None else 200
        if cpu:
            m.colour_init_batch = 4096
    if cfg.hash_log2 is not None or cpu:
        m.color_field = ColourFieldConfig(log2_hashmap_size=cfg.hash_log2 if cfg.hash_log2 is not None else 17)
    prepare_splat_run(tc)
    return tc


def train_run(cfg: SplatDemoConfig, dev: torch.device, console: Console) -> tuple[Path, Dict[str, float]]:
    """Train the splat's run in process and save it to ``OUT/run``; (its config.yml, times)."""
    from virgi_ns.demo.training import _cached_model_class, train
    from virgi_ns.nerfstudio.pipeline import save_run

    times: Dict[str, float] = {}
    t0 = time.perf_counter()
    tc = trainer_config(cfg, dev)
    use_cache = dev.type != "cuda"
    if use_cache:  # a CPU slices its tiles from whole-view contribution lists (as make demo does)
        tc.pipeline.model._target = _cached_model_class()
    pipeline = tc.pipeline.setup(device=dev, test_mode="val")
    model, dm = pipeline.model, pipeline.datamanager
    cams = dm.train_raster_cameras()
    times["views_and_setup_s"] = time.perf_counter() - t0
    console.log(f"{cfg.splat.name}: {model.num_points:,} Gaussians, {len(dm.train_dataset)} training + "
                f"{len(dm.eval_dataset)} held-out views at {int(cams.widths[0])}x{int(cams.heights[0])}, device {dev}")
    steps = int(tc.max_num_iterations)

    def before_colour() -> None:
        if use_cache:
            from virgi_ns.nerfstudio.contrib_cache import ContributionCache

            model.contrib_cache = ContributionCache(cams, model.num_points, lambda c, r: model.contributions(c, r))

    def on_step(step: int, m: Dict[str, float]) -> None:
        if (step + 1) % max(1, steps // 5) == 0 or step + 1 == steps:
            console.log(f"colour step {step + 1}/{steps}" + (f" psnr {m['psnr']:.2f}" if "psnr" in m else ""))

    t0 = time.perf_counter()
    optimizers = train(pipeline, tc, steps, on_step, before_colour)
    if use_cache:
        model.contrib_cache = None
    times["train_s"] = time.perf_counter() - t0
    run_dir = cfg.out / "run"
    if (run_dir / "config.yml").is_file():  # an earlier demo's run: its edits belong to it
        shutil.rmtree(run_dir)
    config = save_run(tc, pipeline, optimizers, steps - 1, run_dir)
    return config, times


# -------------------------------------------------------------------------------- click
def choose_click(images: List[torch.Tensor]) -> tuple[int, tuple[int, int]]:
    """(view, (x, y)): the most colourful spot of ``images`` ([H,W,3] in [0,1]): the largest chroma
    ``max - min`` over the channels after a 5x5 box blur (a spot, not a stray pixel)."""
    best = (-1.0, 0, (0, 0))
    for v, im in enumerate(images):
        x = im.float().permute(2, 0, 1)[None]
        blur = torch.nn.functional.avg_pool2d(x, 5, 1, 2, count_include_pad=False)[0]
        chroma = blur.amax(0) - blur.amin(0)
        i = int(chroma.argmax())
        c = float(chroma.reshape(-1)[i])
        if c > best[0]:
            best = (c, v, (i % chroma.shape[1], i // chroma.shape[1]))
    return best[1], best[2]


# ------------------------------------------------------------------------------ measure
def render_splat(g, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, background,
                 dev: torch.device) -> torch.Tensor:
    """[H,W,3] of a splat file's Gaussians ``g`` (its SH colours) from one camera (OpenCV world-to-camera
    ``viewmat`` [4,4], ``K`` [3,3]): gsplat on a GPU, the reference rasterizer on a CPU."""
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev)
    if dev.type == "cuda":
        import gsplat

        g = g.to(dev, torch.float32)
        img, _, _ = gsplat.rasterization(g.means, g.normalized_quats(), torch.exp(g.scales),
                                         torch.sigmoid(g.opacities), g.sh, viewmat[None].to(dev).float(),
                                         K[None].to(dev).float(), width, height, sh_degree=g.sh_degree,
                                         backgrounds=bg[None])
        return img[0].float().cpu()
    from virgi_ns.colour.sh import view_colours
    from virgi_ns.raster import Cameras, Request, composite, rasterize

    g = g.to(dev, torch.float32)
    cams = Cameras(K[None].float(), viewmat[None].float(), [width], [height])
    contrib = rasterize(g.means, g.normalized_quats(), torch.exp(g.scales), torch.sigmoid(g.opacities), cams,
                        Request.whole_images(cams), backend="reference")
    colours = view_colours(g.sh, g.means, cams.camera_centers()[0])
    return composite(colours[contrib.pair_gaussian], contrib, bg)[0].float().cpu()


def psnr(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR of ``a`` against ``b`` (both clamped to [0, 1]) over ``mask`` [H,W] (all pixels when None)."""
    d = (a.clamp(0, 1) - b.clamp(0, 1)) ** 2
    if mask is not None:
        if not bool(mask.any()):
            return float("nan")
        d = d[mask]
    mse = float(d.mean())
    return float("inf") if mse == 0.0 else -10.0 * float(np.log10(mse))


def hue_of(rgb: torch.Tensor) -> torch.Tensor:
    """Hue in degrees [0, 360) of [...,3] colours."""
    mx, arg = rgb.max(-1)
    mn = rgb.min(-1).values
    c = (mx - mn).clamp_min(1e-8)
    r, g, b = rgb.unbind(-1)
    h = torch.where(arg == 0, ((g - b) / c) % 6, torch.where(arg == 1, (b - r) / c + 2, (r - g) / c + 4))
    return (h * 60.0) % 360.0


def measure(cfg: SplatDemoConfig, config: Path, dev: torch.device) -> tuple[List[dict], List[dict]]:
    """Per held-out view: the numbers of the module doc, and the grid's images."""
    from virgi_ns.nerfstudio.runs import open_run
    from virgi_ns.edit.scene import FrozenScene, render_view
    from virgi_ns.edit.stack import EditStack
    from virgi_ns.io import load_splat

    run = open_run(config)
    model = run.model
    stack = EditStack.open(config.parent, model.fingerprint()).to(model.device)
    scene = FrozenScene.from_model(model)
    views = run.eval if run.eval is not None and len(run.eval) else run.train
    cams = views.cameras()
    vm_cap = run.frame.viewmats_to_capture(cams.viewmats.double()).float()
    original = load_splat(cfg.splat)
    unedited = load_splat(cfg.out / "unedited.ply")
    recoloured = load_splat(cfg.out / "recoloured.ply")
    bg = model.background_color.float().cpu()
    target_hue = float(colorsys.rgb_to_hsv(*parse_colour(cfg.colour))[0] * 360.0)
    rows, images = [], []
    for i in range(len(cams)):
        W, H = int(cams.widths[i]), int(cams.heights[i])
        K = cams.Ks[i]
        a = render_splat(original, vm_cap[i], K, W, H, bg, dev)
        b = render_splat(unedited, vm_cap[i], K, W, H, bg, dev)
        c = render_splat(recoloured, vm_cap[i], K, W, H, bg, dev)
        seg = render_view(scene, cams, i, stack)["segmentation"][..., 0].float().cpu()
        part = seg >= 0.5
        coloured = part & ((c.amax(-1) - c.amin(-1)) > 0.1)
        dh = (hue_of(c) - target_hue).abs()
        near = torch.minimum(dh, 360.0 - dh) <= 30.0
        rows.append({"view": Path(views.filenames[i]).name, "fidelity_psnr": psnr(b, a),
                     "leak_psnr": psnr(c, a, seg < 0.01), "part_pixels": int(part.sum()),
                     "part_share": float(part.float().mean()),
                     "recoloured_share": float((near & coloured).sum()) / max(1, int(coloured.sum())),
                     "changed_pixels": int(((c - a).abs().amax(-1) > 0.1).sum())})
        images.append({"original": a, "unedited": b, "recoloured": c, "segmentation": seg[..., None]})
    return rows, images


def parse_colour(text: str) -> tuple[float, float, float]:
    t = text.strip().lstrip("#")
    if len(t) != 6 or any(ch not in "0123456789abcdefABCDEF" for ch in t):
        raise InputError(f"--colour {text!r}: expected #RRGGBB")
    return tuple(int(t[k : k + 2], 16) / 255.0 for k in (0, 2, 4))  # type: ignore[return-value]


def grid(images: List[dict], labels: List[str]) -> np.ndarray:
    from PIL import Image, ImageDraw

    cols = ("original", "unedited", "recoloured", "segmentation")
    h, w = images[0]["original"].shape[:2]
    pad, title = 4, 18
    canvas = Image.new("RGB", (len(cols) * (w + pad) + pad, title + len(images) * (h + pad)), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for c, name in enumerate(cols):
        draw.text((pad + c * (w + pad) + 2, 3), name, fill=(0, 0, 0))
    for r, row in enumerate(images):
        for c, name in enumerate(cols):
            img = row[name].clamp(0, 1)
            if img.shape[-1] == 1:
                img = img.expand(*img.shape[:-1], 3)
            canvas.paste(Image.fromarray((img.numpy() * 255 + 0.5).astype(np.uint8)),
                         (pad + c * (w + pad), title + r * (h + pad)))
        draw.text((pad + 2, title + r * (h + pad) + 2), labels[r], fill=(255, 255, 0))
    return np.asarray(canvas)


# ---------------------------------------------------------------------------------- run
def run(cfg: SplatDemoConfig, console: Optional[Console] = None) -> Dict[str, object]:
    """The whole demo; returns the metrics written to ``metrics.json``."""
    from virgi_ns.cli.edit import Pick
    from virgi_ns.cli.edit import run as edit_run
    from virgi_ns.cli.export import Export
    from virgi_ns.cli.export import run as export_run

    console = console or Console()
    dev = demo_device(cfg.device)
    if (cfg.pixel is None) != (cfg.camera_index is None):
        raise InputError("give --camera-index and --pixel together (or neither: the most colourful spot)")
    parse_colour(cfg.colour)
    if not cfg.splat.is_file():
        raise InputError(f"no such splat file: {cfg.splat}")
    torch.manual_seed(cfg.seed)
    t_all = time.perf_counter()
    config = cfg.out / "run" / "config.yml"
    if cfg.reuse_run and config.is_file():
        from virgi_ns.cli.edit import Reset

        edit_run(Reset(config))  # the demo's click is the run's only edit
        times: Dict[str, float] = {"reused_run": 1.0}
    else:
        config, times = train_run(cfg, dev, console)

    t0 = time.perf_counter()
    if cfg.pixel is None:
        from PIL import Image

        from virgi_ns.nerfstudio.saved_run import RunInfo

        info = RunInfo.read(config.parent)
        ims = [torch.from_numpy(np.asarray(Image.open(f).convert("RGB"), dtype=np.float32) / 255.0)
               for f in info.train.filenames]
        view, pixel = choose_click(ims)
    else:
        view, pixel = int(cfg.camera_index), (int(cfg.pixel[0]), int(cfg.pixel[1]))
    quiet = Console(quiet=True)
    pick_line = edit_run(Pick(config, pixel, cfg.colour, camera_index=view, tolerance=cfg.tolerance), quiet)
    times["pick_s"] = time.perf_counter() - t0
    console.log(str(pick_line))
    t0 = time.perf_counter()
    export_run(Export(config, cfg.out / "unedited.ply", no_edits=True))
    export_run(Export(config, cfg.out / "recoloured.ply"))
    export_run(Export(config, cfg.out / "recoloured.spz"))
    times["export_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    rows, images = measure(cfg, config, dev)
    times["measure_s"] = time.perf_counter() - t0
    times["total_s"] = time.perf_counter() - t_all
    finite = lambda xs: [x for x in xs if np.isfinite(x)]  # noqa: E731
    seen = [r for r in rows if r["part_pixels"] > 0]
    metrics: Dict[str, object] = {
        "splat": str(cfg.splat), "device": str(dev), "run": str(config),
        "click": {"camera_index": view, "pixel": list(pixel), "colour": cfg.colour, "tolerance": cfg.tolerance},
        "fidelity_psnr_mean": float(np.mean(finite([r["fidelity_psnr"] for r in rows]) or [float("inf")])),
        "fidelity_psnr_min": float(min([r["fidelity_psnr"] for r in rows])),
        "leak_psnr_min": float(min(finite([r["leak_psnr"] for r in rows]) or [float("nan")])),
        "views_with_part": len(seen), "held_out_views": len(rows),
        "recoloured_share_min": float(min([r["recoloured_share"] for r in seen] or [float("nan")])),
        "times_s": times, "per_view": rows,
        "definitions": {"fidelity_psnr": "unedited export vs the original splat, rendered at a held-out view",
                        "leak_psnr": "recoloured export vs the original where the edit's segmentation < 0.01",
                        "part_share": "share of the view where the edit's segmentation >= 0.5",
                        "recoloured_share": "share of the coloured pixels (chroma > 0.1) with segmentation >= 0.5 "
                                            "whose hue is within 30 degrees of the colour's"},
    }
    labels = [r["view"] for r in rows]
    with atomic_path(cfg.out / "grid.png") as tmp:
        from PIL import Image

        Image.fromarray(grid(images[: cfg.grid_views], labels[: cfg.grid_views])).save(tmp, format="PNG")
    with atomic_path(cfg.out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(metrics, indent=1) + "\n")
    return metrics


def main(cfg: SplatDemoConfig) -> None:
    console = Console()
    m = run(cfg, console)
    console.print(f"fidelity (unedited export vs the splat, held-out views): mean {m['fidelity_psnr_mean']:.2f} dB, "
                  f"min {m['fidelity_psnr_min']:.2f} dB; leak min {m['leak_psnr_min']:.2f} dB; recoloured share min "
                  f"{m['recoloured_share_min']:.2f} over {m['views_with_part']}/{m['held_out_views']} views showing "
                  "the part")
    console.print(f"wrote {cfg.out}/grid.png, metrics.json, unedited.ply, recoloured.ply, recoloured.spz and the "
                  f"run {m['run']}")
    click = m["click"]
    console.print("next, on that run:\n  " + "\n  ".join([
        f"ns-viewer --load-config {m['run']}",
        f"virgi-edit pick --load-config {m['run']} --camera-index {click['camera_index']} --pixel "
        f"{click['pixel'][0]} {click['pixel'][1]} --colour '#d02020'"]), markup=False)


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(SplatDemoConfig)))


if __name__ == "__main__":
    entrypoint()
