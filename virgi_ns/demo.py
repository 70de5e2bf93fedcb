"""``make demo``: VIRGi end to end on the bundled beercan capture, written to ``demo_out/``.

1. **Geometry**: the bundle's pre-trained ``geometry.ply`` (capture frame) when present, else a
   short geometry stage on this machine (the reference rasterizer on a CPU: coarse, but it runs).
2. **Colour**: the colour stage of ``ns-train virgi``: the field is warm-started from the
   geometry's own colours (the model's ``colour_init``), then trained on multi-view tile batches.
   On a CPU every training view is rasterized once
   (:class:`~virgi_ns.nerfstudio.contrib_cache.ContributionCache`) and the tiles are sliced from those lists.
3. **Edit**: the recolour rule (:mod:`virgi_ns.edit.recolor`, the can's blue to red) applied to the
   photo of one training view (the one where the rule selects most pixels) is the edited image;
   :class:`~virgi_ns.edit.engine.EditEngine` fits the edit.
4. **Outputs**: ``grid.png`` (held-out views: photo, render, recoloured render, segmentation,
   diffuse, specular), ``metrics.json`` (reconstruction, recolour and propagation PSNR, edit
   time, stage times) and ``edited_scene.ply`` (the edited scene baked to SH, capture frame).

``python -m virgi_ns.demo --help`` lists the knobs; ``--full`` rebuilds the capture at full
resolution from the shared COLMAP data and is meant for a GPU.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from torch import Tensor

from virgi_ns.data.bundle import BUNDLED_SCENE, BundleDataParserConfig, bundled_geometry
from virgi_ns.errors import InputError, atomic_path, cli_entry
from virgi_ns.edit.recolor import RecolorRule, recolor, rule_mask

REPO = Path(__file__).resolve().parents[1]
SHARED_BEERCAN = REPO.parent / "shared" / "data" / "beercan"
COLUMNS = ("photo", "render", "recoloured", "segmentation", "diffuse", "specular")
TITLES = {"specular": "|specular| x4"}


@dataclass
class DemoConfig:
    """VIRGi on the bundled capture: train, recolour from one view, write pictures and numbers."""

    out: Path = Path("demo_out")
    """Output folder (grid.png, metrics.json, edited_scene.ply)."""
    scene: Path = BUNDLED_SCENE
    """A nerfstudio-format capture (transforms.json); the bundled beercan by default."""
    geometry: Optional[Path] = None
    """Pre-trained geometry (.ply/.spz/.compressed.ply in the capture's frame); default: the
    scene's geometry.ply if it has one, otherwise geometry is trained here."""
    full: bool = False
    """Rebuild the capture at full resolution from --source first (use a GPU)."""
    source: Path = SHARED_BEERCAN
    """COLMAP beercan used by --full."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    geometry_steps: Optional[int] = None
    """Geometry steps when no pre-trained geometry is found; default 15000 on a GPU, 400 on a CPU
    (half at 1/4, half at 1/2 resolution, no densification: a coarse stand-in seeded from the
    sparse points)."""
    colour_steps: Optional[int] = None
    """Colour-stage steps; default 5000 on a GPU, 1000 on a CPU."""
    colour_init: Literal["geometry", "geometry_sh", "none"] = "geometry"
    """Warm-start the colour field from the geometry's own colours before the colour steps
    (the model's ``colour_init``), or start from a random field. The bundled geometry stores
    degree-0 colours only, for which 'geometry_sh' (the model's default) is the same as 'geometry'."""
    colour_init_steps: Optional[int] = None
    """Warm-start steps; default 200 on a CPU, the model's (300) on a GPU."""
    colour_init_batch: Optional[int] = None
    """Gaussians per warm-start step; default 4096 on a CPU, the model's (16384) on a GPU."""
    tile_size: int = 32
    views_per_anchor: int = 5
    pixel_budget: Optional[int] = None
    """Pixels per colour step (whole multi-view mini-batches); default 10240 on a CPU, 163840 on a GPU."""
    hash_log2: int = 17
    """log2 of the hash table size (the paper's 19 is for GPUs and large scenes)."""
    edit_steps: Optional[int] = None
    """Edit steps; default: the edit engine's (its measured knee; longer fits leak the recolour)."""
    edit_source: Literal["photo", "render"] = "photo"
    """The image the rule recolours for the edit: the view's photo (as the benchmark does) or the
    model's own render of it (no reconstruction error in the edit's target)."""
    edit_view: Optional[int] = None
    """Training view to edit (index among training views); default: where the rule selects most."""
    hue_from: float = 190.0
    """Rule: hue range start (degrees)."""
    hue_to: float = 260.0
    """Rule: hue range end (degrees)."""
    hue_shift: float = 130.0
    """Rule: hue shift (degrees); blue + 130 is red."""
    sat_min: float = 0.25
    val_min: float = 0.1
    grid_views: int = 4
    """Held-out views shown in grid.png."""
    export: bool = True
    """Bake the edited scene to edited_scene.ply."""
    export_directions: int = 64
    """Sphere directions per Gaussian when baking SH."""
    seed: int = 0

    def rule(self) -> RecolorRule:
        return RecolorRule(self.hue_from, self.hue_to, self.hue_shift, self.sat_min, self.val_min)


# ------------------------------------------------------------------------------- model
def _cached_model_class():
    """VirgiModel whose colour-stage rasterization can come from a contribution cache."""
    from virgi_ns.nerfstudio.model import VirgiModel

    class CachedVirgiModel(VirgiModel):
        contrib_cache = None

        def _raster(self, cams, request, geometry_grad: bool = False):
            cache = self.contrib_cache
            if cache is not None and self.geometry_frozen and cache.matches(cams):
                return cache.contributions(request, self.means.detach())
            return super()._raster(cams, request, geometry_grad)

    return CachedVirgiModel


def trainer_config(cfg: DemoConfig, scene: Path, geometry: Optional[Path], use_cache: bool):
    """``ns-train virgi``'s recipe on ``scene``, with the demo's step counts and sizes."""
    from method_configs.virgi import virgi_trainer_config
    from virgi_ns.colour.field import ColorFieldConfig

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
    m.color_field = ColorFieldConfig(log2_hashmap_size=cfg.hash_log2)
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
          before_colour: Callable[[], None], after_init: Callable[[], None] = lambda: None) -> None:
    """nerfstudio's training loop (callbacks, optimizers, schedulers), without checkpoints or viewer."""
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


# ------------------------------------------------------------------------------ helpers
def psnr(a: Tensor, b: Tensor, mask: Optional[Tensor] = None) -> float:
    """PSNR (data range 1) over all pixels, or over ``mask`` [H,W] (NaN when it is empty)."""
    err = (a.float() - b.float()) ** 2
    if mask is not None:
        if not bool(mask.any()):
            return float("nan")
        err = err[mask]
    return -10.0 * math.log10(max(float(err.mean()), 1e-10))


def _mean(xs: List[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return float(sum(xs) / len(xs)) if xs else float("nan")


def _as_float(img: Tensor) -> Tensor:
    img = img[..., :3]
    return img.float() / 255.0 if img.dtype == torch.uint8 else img.float()


def grid_image(rows: List[Dict[str, Tensor]], labels: List[str]) -> np.ndarray:
    """uint8 grid: one row per held-out view, the :data:`COLUMNS` left to right, a title strip."""
    from PIL import Image, ImageDraw

    h, w = rows[0]["photo"].shape[:2]
    pad, title = 4, 18
    H = title + len(rows) * (h + pad)
    W = len(COLUMNS) * (w + pad) + pad
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for c, name in enumerate(COLUMNS):
        draw.text((pad + c * (w + pad) + 2, 3), TITLES.get(name, name), fill=(0, 0, 0))
    for r, row in enumerate(rows):
        for c, name in enumerate(COLUMNS):
            img = row[name].detach().float().cpu().clamp(0, 1)
            if img.shape[-1] == 1:
                img = img.expand(*img.shape[:-1], 3)
            arr = (img.numpy() * 255 + 0.5).astype(np.uint8)
            canvas.paste(Image.fromarray(arr), (pad + c * (w + pad), title + r * (h + pad)))
        draw.text((pad + 2, title + r * (h + pad) + 2), labels[r], fill=(255, 255, 0))
    return np.asarray(canvas)


def _check_full(cfg: DemoConfig, dev: torch.device) -> None:
    if cfg.full and dev.type != "cuda":
        raise InputError("--full trains at 720x1280 and needs a CUDA GPU (none in use); run without --full")


# --------------------------------------------------------------------------------- run
def run(cfg: DemoConfig, console: Optional[Console] = None) -> Dict[str, object]:
    """The whole demo; returns the metrics written to ``metrics.json``."""
    console = console or Console()
    dev = torch.device("cuda" if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available())
                       else "cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA GPU is available")
    _check_full(cfg, dev)
    for name in ("edit_steps", "colour_steps", "grid_views"):
        if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be >= 1")
    rule = cfg.rule()
    tmp_dir: Optional[Path] = None
    scene = cfg.scene
    if not (scene / "transforms.json").is_file():
        raise InputError(f"{scene}: not a capture (no transforms.json)")
    geometry = cfg.geometry if cfg.geometry is not None else bundled_geometry(scene)
    if cfg.full:  # the same views at full resolution, in the same (COLMAP) frame: the geometry still fits
        from virgi_ns.data.make_bundle import Args as BundleArgs
        from virgi_ns.data.make_bundle import make_bundle

        if not (cfg.source / "sparse" / "0").is_dir():
            raise InputError(f"--full needs the COLMAP beercan at {cfg.source} (--source)")
        n_views = len(json.loads((scene / "transforms.json").read_text())["frames"])
        tmp_dir = Path(tempfile.mkdtemp(prefix="virgi_demo_full_"))
        make_bundle(BundleArgs(source=cfg.source, out=tmp_dir, views=n_views, downscale=1))
        scene = tmp_dir
    if geometry is not None and not Path(geometry).exists():
        raise InputError(f"no such geometry file: {geometry}")
    torch.manual_seed(cfg.seed)
    use_cache = dev.type == "cpu"
    times: Dict[str, float] = {}
    t_all = time.perf_counter()
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console, transient=False)
    try:
        with progress:
            # ---------------------------------------------------------- set-up
            t0 = time.perf_counter()
            tc = trainer_config(cfg, scene, geometry, use_cache)
            pipeline = tc.pipeline.setup(device=dev, test_mode="val")
            model, dm = pipeline.model, pipeline.datamanager
            train_cams = dm.train_raster_cameras()
            times["setup_s"] = time.perf_counter() - t0
            g_steps = model.colour_start
            n_colour = colour_steps(cfg, geometry)
            total = g_steps + n_colour
            console.log(f"scene {scene.name}: {len(dm.train_dataset)} training + {len(dm.eval_dataset)} held-out views "
                        f"at {int(train_cams.widths[0])}x{int(train_cams.heights[0])}, {model.num_points:,} Gaussians "
                        f"({'imported from ' + str(geometry) if geometry else 'geometry trained here'}), device {dev}")

            # ---------------------------------------------------------- training
            t_geo = progress.add_task("geometry", total=max(g_steps, 1), info="", visible=g_steps > 0)
            t_cache = progress.add_task("rasterize training views", total=len(train_cams), info="", visible=use_cache)
            t_col = progress.add_task("colour field", total=n_colour, info="")
            marks: Dict[str, float] = {"start": time.perf_counter()}

            def before_colour() -> None:
                marks["geometry_done"] = time.perf_counter()
                if use_cache:
                    from virgi_ns.nerfstudio.contrib_cache import ContributionCache

                    model.contrib_cache = ContributionCache(
                        train_cams, model.num_points,
                        lambda c, r: model._raster(c, r),
                        progress=lambda d, n: (progress.update(t_cache, completed=d),
                                               None if console.is_terminal or d % 7 else
                                               console.log(f"rasterized training view {d}/{n}")))
                marks["cache_done"] = time.perf_counter()

            def on_step(step: int, m: Dict[str, float]) -> None:
                info = f"psnr {m['psnr']:.2f}" if "psnr" in m else ""
                stage, done, n = ("geometry", step + 1, g_steps) if step < g_steps else \
                    ("colour", step + 1 - g_steps, n_colour)
                progress.update(t_geo if stage == "geometry" else t_col, completed=done, info=info)
                if not console.is_terminal and (done % max(1, n // 10) == 0 or done == n):
                    console.log(f"{stage} step {done}/{n} {info}")  # a log file gets lines, not a bar

            train(pipeline, tc, total, on_step, before_colour,
                  after_init=lambda: marks.__setitem__("init_done", time.perf_counter()))
            end = time.perf_counter()
            times["geometry_s"] = marks.get("geometry_done", end) - marks["start"]
            times["contribution_cache_s"] = marks.get("cache_done", end) - marks.get("geometry_done", end)
            times["colour_init_s"] = marks.get("init_done", end) - marks.get("cache_done", end)
            times["colour_s"] = end - marks.get("init_done", end)
            if use_cache:
                model.contrib_cache = None  # frees the lists

            # ---------------------------------------------------------- evaluation + edit
            from virgi_ns.edit.engine import EditConfig, EditEngine
            from virgi_ns.edit.scene import FrozenScene, render_view
            from virgi_ns.edit.stack import EditSource, EditStack
            from virgi_ns.nerfstudio.cameras import raster_cameras

            pipeline.eval()
            frozen = FrozenScene.from_model(model)
            eval_images = [_as_float(c["image"]).to(dev) for c in dm.cached_eval]  # undistorts + fixes cameras
            eval_cams = raster_cameras(dm.eval_dataset.cameras).to(dev)
            n_eval = len(eval_cams)
            t_ev = progress.add_task("render held-out views", total=n_eval, info="")
            t0 = time.perf_counter()
            contribs, base = [], []
            for i in range(n_eval):
                cam = eval_cams.index(i)
                from virgi_ns.raster import Request

                c = frozen.contributions(cam, Request.whole_images(cam))
                contribs.append(c)
                base.append(render_view(frozen, eval_cams, i, None, contrib=c))
                progress.update(t_ev, completed=i + 1)
            times["eval_render_s"] = time.perf_counter() - t0

            train_images = [_as_float(im).to(dev) for im in dm.train_images()]
            if cfg.edit_view is None:
                counts = [int(rule_mask(im, rule).sum()) for im in train_images]
                edit_view = int(np.argmax(counts))
            else:
                edit_view = cfg.edit_view
                if not 0 <= edit_view < len(train_images):
                    raise InputError(f"--edit-view {edit_view}: there are {len(train_images)} training views")
            if cfg.edit_source == "render":
                source_image = render_view(frozen, train_cams.to(dev), edit_view)["rgb"].clamp(0, 1)
            else:
                source_image = train_images[edit_view]
            edited_photo, edit_mask = recolor(source_image, rule)
            if not bool(edit_mask.any()):
                raise InputError(f"the recolour rule selects no pixel of training view {edit_view}")
            edit_cfg = EditConfig(seed=cfg.seed)
            if cfg.edit_steps is not None:
                edit_cfg.steps = cfg.edit_steps
            t_ed = progress.add_task("edit", total=edit_cfg.steps, info=f"view {edit_view}")
            stack = EditStack(frozen.fingerprint())
            src_name = Path(dm.train_dataset.image_filenames[edit_view]).name
            cam = train_cams.index(edit_view)
            engine = EditEngine(frozen, cam, edited_photo, stack,
                                edit_cfg,
                                EditSource(f"rule({src_name})", cam.Ks[0], cam.viewmats[0],
                                           int(cam.widths[0]), int(cam.heights[0]), f"train index {edit_view}"),
                                original=source_image)
            edit, timing = engine.fit(progress=lambda d, n: progress.update(t_ed, completed=d))
            stack.add(edit)
            # on the pixels the rule changed: elsewhere the edit's target is the unedited render
            edit_fit_psnr = psnr(engine.preview()["rgb"].clamp(0, 1), edited_photo, edit_mask)

            rows, per_view = [], []
            for i in range(n_eval):
                ed = render_view(frozen, eval_cams, i, stack, contrib=contribs[i])
                b = base[i]
                photo = eval_images[i]
                truth, truth_mask = recolor(photo, rule)
                prop_truth, prop_mask = recolor(b["rgb"].clamp(0, 1), rule)
                e_rgb = ed["rgb"].clamp(0, 1)
                per_view.append({
                    "view": Path(dm.eval_dataset.image_filenames[i]).name,
                    "reconstruction_psnr": psnr(b["rgb"].clamp(0, 1), photo),
                    "recolour_psnr": psnr(e_rgb, truth),
                    "recolour_psnr_inside_mask": psnr(e_rgb, truth, truth_mask),
                    "unedited_psnr_inside_mask": psnr(b["rgb"].clamp(0, 1), truth, truth_mask),
                    "propagation_psnr": psnr(e_rgb, prop_truth),
                    "propagation_psnr_inside_mask": psnr(e_rgb, prop_truth, prop_mask),
                    "propagation_psnr_outside_mask": psnr(e_rgb, prop_truth, ~prop_mask),
                    "mask_fraction": float(prop_mask.float().mean()),
                    "rule_pixels_render": int(prop_mask.sum()),
                    "rule_pixels_photo": int(truth_mask.sum()),
                })
                if len(rows) < cfg.grid_views:
                    rows.append({"photo": photo, "render": b["rgb"], "recoloured": e_rgb,
                                 "segmentation": ed["segmentation"], "diffuse": ed["diffuse"],
                                 "specular": (ed["specular"].abs() * 4.0)})

            # ---------------------------------------------------------- export
            exported = None
            times_export = 0.0
            if cfg.export:
                from virgi_ns.nerfstudio.export import BakeConfig, bake_pipeline

                t_ex = progress.add_task("bake edited scene", total=1, info="")
                t0 = time.perf_counter()
                g = bake_pipeline(pipeline, stack, cfg=BakeConfig(directions=cfg.export_directions),
                                 progress=lambda d, n: progress.update(t_ex, total=n, completed=d))
                times_export = time.perf_counter() - t0
                exported = g
        times["export_s"] = times_export
        times["total_s"] = time.perf_counter() - t_all

        # ------------------------------------------------------------------ write
        metrics: Dict[str, object] = {
            "scene": str(scene), "device": str(dev),
            "geometry": str(geometry) if geometry else f"trained here ({g_steps} steps)",
            "gaussians": int(model.num_points),
            "train_views": len(dm.train_dataset), "held_out_views": n_eval,
            "resolution": [int(train_cams.widths[0]), int(train_cams.heights[0])],
            "geometry_steps": g_steps, "colour_steps": n_colour,
            "colour_init": {"mode": cfg.colour_init, "steps": int(model.config.colour_init_steps),
                            "batch": int(model.config.colour_init_batch)},
            "rule": rule.to_dict(),
            "edit_view": {"index": edit_view, "image": src_name, "source": cfg.edit_source,
                          "rule_pixels": int(edit_mask.sum())},
            "reconstruction_psnr": _mean([v["reconstruction_psnr"] for v in per_view]),
            "recolour_psnr": _mean([v["recolour_psnr"] for v in per_view]),
            "recolour_psnr_inside_mask": _mean([v["recolour_psnr_inside_mask"] for v in per_view]),
            "unedited_psnr_inside_mask": _mean([v["unedited_psnr_inside_mask"] for v in per_view]),
            "propagation_psnr": _mean([v["propagation_psnr"] for v in per_view]),
            "propagation_psnr_inside_mask": _mean([v["propagation_psnr_inside_mask"] for v in per_view]),
            "propagation_psnr_outside_mask": _mean([v["propagation_psnr_outside_mask"] for v in per_view]),
            "edit_fit_psnr": edit_fit_psnr,
            "rule_pixels": {"unedited_renders": sum(v["rule_pixels_render"] for v in per_view),
                            "photos": sum(v["rule_pixels_photo"] for v in per_view)},
            "edit_time_s": {"setup": timing.setup_s, "steps": timing.steps_s, "total": timing.total_s,
                            "steps_count": timing.steps},
            "times_s": times,
            "per_view": per_view,
            "definitions": {
                "reconstruction_psnr": "unedited render vs held-out photo",
                "recolour_psnr": "edited render vs the rule applied to the held-out photo",
                "recolour_psnr_inside_mask": "the same on the pixels the rule recolours in the photo (the can);"
                                             " unedited_psnr_inside_mask: the unedited render there (no edit)",
                "propagation_psnr": "edited render vs the rule applied to the unedited render (isolates the edit);"
                                    " inside_mask: pixels the rule recolours (misses), outside: the rest (leaks)",
                "edit_fit_psnr": "edited view's render vs the edited image (the rule applied to its photo or render), "
                                 "on the pixels the rule changed",
                "rule_pixels": "held-out pixels the rule recolours, summed over the held-out views: in the unedited"
                               " renders (what the edit can visibly change) and in the photos",
                "mask_fraction": "per view: share of pixels the rule recolours in the unedited render",
            },
        }
        cfg.out.mkdir(parents=True, exist_ok=True)
        from PIL import Image

        with atomic_path(cfg.out / "grid.png") as tmp:
            Image.fromarray(grid_image(rows, [v["view"] for v in per_view[: len(rows)]])).save(tmp, format="PNG")
        if exported is not None:
            from virgi_ns.io import save_ply

            save_ply(exported, cfg.out / "edited_scene.ply")
            metrics["exported"] = {"file": "edited_scene.ply", "gaussians": len(exported),
                                   "sh_degree": exported.sh_degree}
        with atomic_path(cfg.out / "metrics.json") as tmp:
            tmp.write_text(json.dumps(metrics, indent=1) + "\n")
        return metrics
    finally:
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)


def summary_table(metrics: Dict[str, object]):
    from rich.table import Table

    t = Table(title="virgi demo")
    t.add_column("figure")
    t.add_column("value", justify="right")
    for key in ("reconstruction_psnr", "recolour_psnr", "recolour_psnr_inside_mask", "unedited_psnr_inside_mask",
                "propagation_psnr", "propagation_psnr_inside_mask",
                "propagation_psnr_outside_mask", "edit_fit_psnr"):
        t.add_row(key.replace("_", " "), f"{metrics[key]:.2f} dB")
    et = metrics["edit_time_s"]
    t.add_row("edit time", f"{et['total']:.2f} s (setup {et['setup']:.2f}, {et['steps_count']} steps {et['steps']:.2f})")
    t.add_row("total time", f"{metrics['times_s']['total_s']:.0f} s")
    return t


def main(cfg: DemoConfig) -> None:
    console = Console()
    metrics = run(cfg, console)
    console.print(summary_table(metrics))
    console.print(f"wrote {cfg.out}/grid.png, metrics.json" + (", edited_scene.ply" if "exported" in metrics else ""))


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(DemoConfig)))


if __name__ == "__main__":
    entrypoint()
