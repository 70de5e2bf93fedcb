"""The demo end to end: train on the capture, recolour it from one training view, measure the
held-out views, bake the edited scene, and write ``grid.png``, ``metrics.json``,
``edited_scene.ply`` and the trained run ``run/`` (see :mod:`virgi_ns.demo`)."""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from virgi_ns.data.bundle import bundled_geometry
from virgi_ns.demo.config import DemoConfig, demo_device
from virgi_ns.demo.measure import (DEFINITIONS, as_float, held_out_means, object_mask, psnr, summary_table,
                                   view_metrics)
from virgi_ns.demo.picture import grid_image, grid_row
from virgi_ns.demo.training import colour_steps, train, trainer_config
from virgi_ns.edit.recolor import rule_mask
from virgi_ns.errors import InputError, atomic_path, cli_entry


def _check_full(cfg: DemoConfig, dev: torch.device) -> None:
    if cfg.full and dev.type != "cuda":
        raise InputError("--full trains at 720x1280 and needs a CUDA GPU (none in use); run without --full")


# --------------------------------------------------------------------------------- run
def run(cfg: DemoConfig, console: Optional[Console] = None) -> Dict[str, object]:
    """The whole demo; returns the metrics written to ``metrics.json``."""
    console = console or Console()
    dev = demo_device(cfg.device)
    _check_full(cfg, dev)
    for name in ("edit_steps", "colour_steps", "grid_views", "grid_scale"):
        if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be >= 1")
    rule = cfg.object_rule()
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
                        lambda c, r: model.contributions(c, r),
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

            optimizers = train(pipeline, tc, total, on_step, before_colour,
                               after_init=lambda: marks.__setitem__("init_done", time.perf_counter()))
            end = time.perf_counter()
            times["geometry_s"] = marks.get("geometry_done", end) - marks["start"]
            times["contribution_cache_s"] = marks.get("cache_done", end) - marks.get("geometry_done", end)
            times["colour_init_s"] = marks.get("init_done", end) - marks.get("cache_done", end)
            times["colour_s"] = end - marks.get("init_done", end)
            if use_cache:
                model.contrib_cache = None  # frees the lists

            # ---------------------------------------------------------- evaluation + edit
            from virgi_ns.edit.scene import FrozenScene, render_view
            from virgi_ns.edit.stack import EditSource, EditStack
            from virgi_ns.nerfstudio.cameras import raster_cameras
            from virgi_ns.raster import Request

            pipeline.eval()
            frozen = FrozenScene.from_model(model)
            eval_images = [as_float(c["image"]).to(dev) for c in dm.cached_eval]  # undistorts + fixes cameras
            eval_cams = raster_cameras(dm.eval_dataset.cameras).to(dev)
            n_eval = len(eval_cams)
            t_ev = progress.add_task("render held-out views", total=n_eval, info="")
            t0 = time.perf_counter()
            contribs, base = [], []
            for i in range(n_eval):
                cam = eval_cams.index(i)
                c = frozen.contributions(cam, Request.whole_images(cam))
                contribs.append(c)
                base.append(render_view(frozen, eval_cams, i, None, contrib=c))
                progress.update(t_ev, completed=i + 1)
            times["eval_render_s"] = time.perf_counter() - t0

            # the click: in the training view whose photo shows most of the object's colour, at the
            # pixel of the model's render deepest inside it (unless --edit-view / --pixel say otherwise)
            from virgi_ns.edit.pick import MIN_COVER, PickSession, parse_colour, pick_config

            colour = parse_colour(cfg.colour)
            train_photos = [as_float(im.cpu()) for im in dm.train_images()]
            if cfg.edit_view is None:
                edit_view = int(np.argmax([int(rule_mask(im, rule).sum()) for im in train_photos]))
            else:
                edit_view = cfg.edit_view
                if not 0 <= edit_view < len(train_photos):
                    raise InputError(f"--edit-view {edit_view}: there are {len(train_photos)} training views")
            cam = train_cams.index(edit_view)
            cam_dev = cam.to(dev)
            view_contrib = frozen.contributions(cam_dev, Request.whole_images(cam_dev))
            view_base = render_view(frozen, cam_dev, 0, contrib=view_contrib)
            if cfg.pixel is None:
                click = default_click(view_base["rgb"], train_photos[edit_view],
                                      view_contrib.accumulation()[0] >= MIN_COVER, rule)
                if click is None:
                    raise InputError(f"the object's colour shows nowhere in training view {edit_view}: give --pixel X Y")
                x, y = click
            else:
                x, y = cfg.pixel
            edit_cfg = pick_config(dev)
            edit_cfg.seed = cfg.seed
            if cfg.edit_steps is not None:
                edit_cfg.steps = cfg.edit_steps
            stack = EditStack(frozen.fingerprint())
            src_name = Path(dm.train_dataset.image_filenames[edit_view]).name
            source = EditSource(f"pick({src_name})", cam.Ks[0], cam.viewmats[0], int(cam.widths[0]),
                                int(cam.heights[0]), f"train index {edit_view}, pixel {x} {y}")
            t_ed = progress.add_task("pick", total=1, info=f"view {edit_view}, pixel {x} {y}, {cfg.colour}")
            t0 = time.perf_counter()
            session = PickSession(frozen, cam_dev, x, y, stack, edit_cfg, source)
            edit = session.update(colour, cfg.tolerance, cfg.mode, contiguous=cfg.contiguous)
            pick_s = time.perf_counter() - t0
            stack.add(edit)
            progress.update(t_ed, completed=1)
            # on the selected pixels: elsewhere the edit's target is the unedited render
            edit_fit_psnr = psnr(session.engine.preview()["rgb"].clamp(0, 1), session.edited, session.mask)
            click_view = view_metrics(src_name, view_base["rgb"],
                                      render_view(frozen, cam_dev, 0, stack, contrib=view_contrib)["rgb"],
                                      train_photos[edit_view].to(dev), session.mask, colour)

            rows, per_view = [], []
            for i in range(n_eval):
                ed = render_view(frozen, eval_cams, i, stack, contrib=contribs[i])
                name = Path(dm.eval_dataset.image_filenames[i]).name
                obj = object_mask(base[i]["rgb"], contribs[i].accumulation()[0], rule, MIN_COVER)
                per_view.append(view_metrics(name, base[i]["rgb"], ed["rgb"], eval_images[i], obj, colour))
                if len(rows) < cfg.grid_views:
                    rows.append(grid_row(eval_images[i], base[i], ed))

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
            "click": {"view_index": edit_view, "image": src_name, "pixel": [int(x), int(y)], "colour": cfg.colour,
                      "mode": cfg.mode, "tolerance": cfg.tolerance, "contiguous": cfg.contiguous,
                      "selected_share": session.settings["selected"]},
            "object_rule": rule.to_dict(),
            **held_out_means(per_view),
            "edit_fit_psnr": edit_fit_psnr,
            "click_view": click_view,
            "edit_time_s": {"total": pick_s, "steps_count": edit_cfg.steps},
            "times_s": times,
            "per_view": per_view,
            "definitions": dict(DEFINITIONS),
        }
        cfg.out.mkdir(parents=True, exist_ok=True)
        from PIL import Image

        with atomic_path(cfg.out / "grid.png") as tmp:
            Image.fromarray(grid_image(rows, [v["view"] for v in per_view[: len(rows)]], cfg.grid_scale)).save(
                tmp, format="PNG")
        if exported is not None:
            from virgi_ns.io import save_ply

            save_ply(exported, cfg.out / "edited_scene.ply")
            metrics["exported"] = {"file": "edited_scene.ply", "gaussians": len(exported),
                                   "sh_degree": exported.sh_degree}
        if tmp_dir is None:  # (a --full capture lives in a temporary folder: its run could not reopen)
            from virgi_ns.nerfstudio.pipeline import save_run

            run_dir = cfg.out / "run"
            if (run_dir / "config.yml").is_file():  # an earlier demo's run: its edits belong to it
                shutil.rmtree(run_dir)
            save_run(tc, pipeline, optimizers, total - 1, run_dir)
            metrics["run"] = {"config": str(run_dir / "config.yml"),
                              "pick": {"camera_index": edit_view, "pixel": [int(x), int(y)], "colour": cfg.colour,
                                       "mode": cfg.mode, "contiguous": cfg.contiguous}}
        with atomic_path(cfg.out / "metrics.json") as tmp:
            tmp.write_text(json.dumps(metrics, indent=1) + "\n")
        return metrics
    finally:
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)


def inner_pixel(mask: torch.Tensor) -> tuple[int, int]:
    """(x, y) of the pixel deepest inside ``mask`` [H,W] (farthest from its edge, by repeated 3x3
    erosion; beyond the image counts as outside); among equally deep pixels, the one nearest their
    centroid."""
    inner = mask
    while True:
        padded = torch.nn.functional.pad(inner[None, None].float(), (1, 1, 1, 1))
        eroded = -torch.nn.functional.max_pool2d(-padded, 3, 1, 0)[0, 0] > 0
        if not bool(eroded.any()):
            break
        inner = eroded
    ys, xs = torch.nonzero(inner, as_tuple=True)
    i = int(((ys - ys.float().mean()) ** 2 + (xs - xs.float().mean()) ** 2).argmin())
    return int(xs[i]), int(ys[i])


def default_click(render_rgb: torch.Tensor, photo: torch.Tensor, covered: torch.Tensor,
                  rule) -> Optional[tuple[int, int]]:
    """The demo's click when none is given: the pixel deepest inside the object's colour (``rule``) where
    the render [H,W,3] shows it (what a user sees and the pick reads), else, for a field trained too briefly
    to show it, where the photo does; only where Gaussians cover (``covered`` [H,W]). None where neither
    shows it."""
    for image in (render_rgb.clamp(0, 1).cpu(), photo.cpu()):
        obj = rule_mask(image, rule) & covered.cpu()
        if bool(obj.any()):
            return inner_pixel(obj)
    return None


def next_commands(metrics: Dict[str, object], out: Path) -> list[str]:
    """What to type next on the saved run: open it in the viewer, pick the edited object, export."""
    if "run" not in metrics:
        return []
    config, pick = metrics["run"]["config"], metrics["run"]["pick"]
    x, y = pick["pixel"]
    return [f"ns-viewer --load-config {config}",
            f"virgi-edit pick --load-config {config} --camera-index {pick['camera_index']} --pixel {x} {y} "
            f"--colour '{pick['colour']}' --mode {pick['mode']}"
            + ("" if pick.get("contiguous", True) else " --no-contiguous"),
            f"virgi-export --load-config {config} --out {out / 'recoloured.ply'}"]


def main(cfg: DemoConfig) -> None:
    console = Console()
    metrics = run(cfg, console)
    console.print(summary_table(metrics))
    console.print(f"wrote {cfg.out}/grid.png, metrics.json" + (", edited_scene.ply" if "exported" in metrics else "")
                  + (f" and the run {cfg.out}/run" if "run" in metrics else ""))
    commands = next_commands(metrics, cfg.out)
    if commands:
        console.print("next, on that run:\n  " + "\n  ".join(commands), markup=False)


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(DemoConfig)))


if __name__ == "__main__":
    entrypoint()
