"""Benchmark (GPU): fidelity and speed of ``virgi-export`` on a real capture.

For a trained VIRGi run (``--load-config``; without it a run is trained on ``--scene``), three
cases: the base colours, one edit (the benchmark's hue-shift rule on a training view, fitted by
the edit engine), and specular strength 0 with that edit. Each is baked to an INRIA ``.ply`` in
the capture's original frame, read back, and rendered from every held-out camera

- with ``virgi-render``'s path (our rasterizer, SH colours) and
- with gsplat (``rasterization(..., sh_degree=3)``),

the held-out cameras taken from the capture itself (COLMAP ``images.bin``, OpenCV world-to-camera;
for other parsers mapped through the run's frame), and compared with the model's own renders (PSNR).
Then the export time for ``--timing-gaussians`` Gaussians (the run's, resampled with jitter): bake
with the specular gate, bake with every Gaussian fitted, write ``.ply``. Prints a table naming the
device and writes ``export_results.json``.

    python bench/export.py --load-config outputs/.../config.yml --out bench_out/export
    python bench/export.py --scene beercan --geometry-steps 7000 --colour-steps 3000
"""

from __future__ import annotations

import json
import math
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.table import Table

from common.training import dataparser_for, quiet, sync, train
from virgi_ns.errors import InputError, atomic_path, cli_entry
from virgi_ns.metrics import offline_splatfacto_lpips

console = Console()


@dataclass
class Args:
    load_config: Optional[Path] = None
    """A trained virgi run's config.yml (default: train one on --scene)."""
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    scene: str = "beercan"
    geometry_steps: int = 7000
    colour_steps: int = 3000
    out: Path = Path("bench_out/export")
    edit_view: int = -1
    """Training view the benchmark edit is made on (-1: where the rule selects most pixels)."""
    timing_gaussians: int = 1_000_000
    """Gaussians of the timed export (0: no timing)."""
    directions: int = 64
    """Sphere directions of every bake (``virgi-export --directions``)."""
    max_views: int = 0
    """Held-out views measured (0: all)."""
    gsplat: bool = True
    """Also render the exported files with gsplat (needs CUDA)."""


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.clamp(0, 1) - b.clamp(0, 1)) ** 2).mean())
    return -10.0 * math.log10(max(mse, 1e-12))


def train_run(args: Args) -> Path:
    """Train virgi (geometry with gsplat, then colour) on ``args.scene``; returns its config.yml."""
    from method_configs.virgi import virgi_trainer_config

    cfg = virgi_trainer_config("virgi", geometry_steps=args.geometry_steps, colour_steps=args.colour_steps)
    cfg.pipeline.datamanager.dataparser = dataparser_for(args.scene, args.data)
    quiet(cfg, args.out, f"{args.scene}-virgi")
    cfg.save_config()
    offline_splatfacto_lpips()
    trainer, secs, _, _ = train(cfg)
    console.log(f"trained {args.scene} in {secs:.0f} s")
    del trainer
    torch.cuda.empty_cache()
    return Path(cfg.get_base_dir()) / "config.yml"


def capture_viewmats(cfg, pipeline, frame, filenames: List[Path], run_viewmats: torch.Tensor) -> tuple[torch.Tensor, str]:
    """[V,4,4] OpenCV world-to-camera of the held-out images in the capture's frame: read from the
    COLMAP model when the run used one (independent of the frame code), else mapped by ``frame``."""
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

    dp = cfg.pipeline.datamanager.dataparser
    if isinstance(dp, ColmapDataParserConfig):
        from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat, read_images_binary

        root = Path(dp.data)
        images = read_images_binary(root / dp.colmap_path / "images.bin")
        by_name = {im.name: im for im in images.values()}
        out = []
        for f in filenames:
            im = by_name.get(Path(f).name)
            if im is None:
                raise InputError(f"{f} is not in the COLMAP model")
            M = np.eye(4)
            M[:3, :3] = qvec2rotmat(im.qvec)
            M[:3, 3] = im.tvec
            out.append(torch.from_numpy(M))
        return torch.stack(out).float(), "COLMAP images.bin"
    return frame.viewmats_to_capture(run_viewmats.double()).float(), "run cameras mapped by the frame"


def render_gsplat(g, K: torch.Tensor, viewmat: torch.Tensor, w: int, h: int, bg: torch.Tensor) -> torch.Tensor:
    from gsplat import rasterization

    dev = torch.device("cuda")
    g = g.to(dev)
    img, _, _ = rasterization(g.means, g.normalized_quats(), torch.exp(g.scales), torch.sigmoid(g.opacities),
                              g.sh, viewmat[None].to(dev), K[None].to(dev), w, h, sh_degree=g.sh_degree,
                              backgrounds=bg.to(dev)[None])
    return img[0]


class _Scaled:
    """The run's Gaussians resampled to ``n`` (with jitter), for timing: what :func:`bake` reads."""

    def __init__(self, model, n: int, seed: int = 0) -> None:
        gen = torch.Generator(device=model.means.device).manual_seed(seed)
        dev = model.means.device
        idx = torch.randint(model.num_points, (n,), generator=gen, device=dev)
        jitter = torch.randn(n, 3, generator=gen, device=dev) * torch.exp(model.scales.detach()[idx]).mean(-1, True)
        self.means = model.means.detach()[idx] + jitter
        self.scales = model.scales.detach()[idx]
        self.quats = model.quats.detach()[idx]
        self.opacities = model.opacities.detach()[idx]
        self.field = model.field
        self.spec_gate = model.spec_gate[idx] if model.gate_ready() else torch.ones(n, dtype=torch.bool, device=dev)
        self.num_points = n

    def gate_ready(self) -> bool:
        return True


def main(args: Args) -> None:
    warnings.filterwarnings("ignore", category=FutureWarning)
    from virgi_ns.nerfstudio.runs import load_run
    from virgi_ns.cli.render import render_image
    from virgi_ns.edit.engine import EditConfig, EditEngine
    from virgi_ns.edit.recolor import RecolorRule, recolor
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.edit.stack import EditStack
    from virgi_ns.io import load_splat
    from virgi_ns.io.camera_json import CameraSpec
    from virgi_ns.nerfstudio.cameras import raster_cameras
    from virgi_ns.nerfstudio.export import BakeConfig, bake, bake_pipeline, write_splat
    from virgi_ns.nerfstudio.frames import CaptureFrame

    use_gsplat = args.gsplat and torch.cuda.is_available()
    args.out.mkdir(parents=True, exist_ok=True)
    cfg_path = args.load_config or train_run(args)
    cfg, pipeline = load_run(cfg_path)
    model = pipeline.model
    model.eval()
    dev = model.device
    device = torch.cuda.get_device_name(0) if dev.type == "cuda" else "CPU"
    run_dir = cfg_path.parent
    dpj = run_dir / "dataparser_transforms.json"
    frame = CaptureFrame.from_transforms_json(dpj) if dpj.is_file() else CaptureFrame.from_pipeline(pipeline)
    if not model.gate_ready() and model.config.specular_gating:
        model.build_specular_gate(pipeline.datamanager.train_raster_cameras())

    # held-out views: the model's cameras (undistorted) and the capture's own poses
    dm = pipeline.datamanager
    ev = dm.eval_dataset
    _ = dm.cached_eval  # undistorts and fixes the eval cameras' intrinsics
    idx = list(range(len(ev)))
    if args.max_views > 0 and len(idx) > args.max_views:
        idx = [idx[round(i * (len(idx) - 1) / max(args.max_views - 1, 1))] for i in range(args.max_views)]
    run_cams = raster_cameras(ev.cameras[torch.tensor(idx)])
    names = [ev.image_filenames[i] for i in idx]
    cap_vm, cam_source = capture_viewmats(cfg, pipeline, frame, names, run_cams.viewmats)
    mapped = frame.viewmats_to_capture(run_cams.viewmats.double()).float()
    frame_err = float((mapped - cap_vm).abs().max())
    console.log(f"{len(idx)} held-out views; capture cameras from {cam_source}; "
                f"frame-mapped vs capture viewmats max |diff| {frame_err:.2e}")

    # the benchmark edit
    train_cams = dm.train_raster_cameras()
    scene = FrozenScene.from_model(model)
    rule = RecolorRule(190.0, 250.0, 150.0, 0.35, 0.15)
    # the rule applied to a training photo is the edit, as in virgi-bench recolor; the photos are
    # the undistorted ones that match train_raster_cameras
    photos = [im[..., :3].float() / (255.0 if im.dtype == torch.uint8 else 1.0) for im in dm.train_images()]
    edit_view = args.edit_view
    if edit_view < 0:  # the training view where the rule selects most pixels (the can in full view)
        edit_view = int(np.argmax([float(recolor(im, rule)[1].float().mean()) for im in photos]))
    ecam = train_cams.index(edit_view).to(dev)
    edited, mask = recolor(photos[edit_view].to(dev), rule)
    console.log(f"edit on training view {edit_view}: the rule selects {float(mask.float().mean()):.1%} of it")
    stack = EditStack(model.fingerprint())
    edit, timing = EditEngine(scene, ecam, edited, stack, EditConfig()).fit()
    stack.add(edit)
    console.log(f"edit fitted in {timing.total_s:.2f} s")

    bg = torch.as_tensor(model.background_color, dtype=torch.float32).reshape(3)
    rows: List[Dict[str, object]] = []
    cases = [("base", None, 1.0), ("edit", stack, 1.0), ("edit, k=0", stack, 0.0)]
    base_renders: List[torch.Tensor] = []
    for name, st, k in cases:
        if st is not None:
            st.set_specular_strength(k)
        model.set_edit_stack(st)
        sync()
        t0 = time.perf_counter()
        g = bake_pipeline(pipeline, st, k, frame, BakeConfig(directions=args.directions))
        sync()
        bake_s = time.perf_counter() - t0
        path = args.out / f"{args.scene}_{name.replace(', ', '_').replace('=', '')}.ply"
        t0 = time.perf_counter()
        write_splat(g, path)
        write_s = time.perf_counter() - t0
        g = load_splat(path)  # what a user gets
        p_ours, p_gs, changes = [], [], []
        for j in range(len(idx)):
            want = model.render_camera(ev.cameras[idx[j] : idx[j] + 1].to(dev), gated=True)["rgb"].float()
            if name == "base":
                base_renders.append(want)
            else:  # mean |edited render - base render|: shows the edit is not a no-op
                changes.append(float((want - base_renders[j]).abs().mean()))
            K = run_cams.Ks[j]
            spec = CameraSpec(int(run_cams.widths[j]), int(run_cams.heights[j]), float(K[0, 0]), float(K[1, 1]),
                              float(K[0, 2]), float(K[1, 2]), cap_vm[j].double().numpy())
            ours = torch.from_numpy(render_image(g, spec, "auto", tuple(bg.tolist()))).to(want.device)
            p_ours.append(psnr(ours, want))
            if use_gsplat:
                gs = render_gsplat(g, K.float(), cap_vm[j].float(), spec.width, spec.height, bg)
                p_gs.append(psnr(gs.to(want.device), want))
        row = {"case": name, "gaussians": len(g), "bake_s": bake_s, "write_ply_s": write_s,
               "edit_view": edit_view, "render_change_vs_base": float(np.mean(changes)) if changes else 0.0,
               "psnr_virgi_render": float(np.mean(p_ours)), "psnr_virgi_render_min": float(np.min(p_ours)),
               "psnr_gsplat": float(np.mean(p_gs)) if p_gs else float("nan"),
               "psnr_gsplat_min": float(np.min(p_gs)) if p_gs else float("nan"), "file": str(path)}
        console.log(row)
        rows.append(row)
    model.set_edit_stack(None)

    # export time at scale
    timing_rows = []
    modes = (("gated", True), ("all fitted", False)) if args.timing_gaussians > 0 else ()
    big = _Scaled(model, args.timing_gaussians) if modes else None
    for label, use_gate in modes:
        bake_cfg = BakeConfig(use_gate=use_gate, directions=args.directions)
        bake(big, stack, 1.0, frame, train_cams, bake_cfg)  # warm-up (kernels, allocator)
        sync()
        t0 = time.perf_counter()
        g = bake(big, stack, 1.0, frame, train_cams, bake_cfg)
        sync()
        bake_s = time.perf_counter() - t0
        with tempfile.TemporaryDirectory(dir=args.out) as tmp:
            t0 = time.perf_counter()
            write_splat(g, Path(tmp) / "big.ply")
            write_s = time.perf_counter() - t0
        fitted = int(big.spec_gate.sum()) if use_gate else len(g)
        timing_rows.append({"mode": label, "gaussians": len(g), "view_dependent": fitted, "bake_s": bake_s,
                            "write_ply_s": write_s, "total_s": bake_s + write_s})
        console.log(timing_rows[-1])
        del g
        torch.cuda.empty_cache() if torch.cuda.is_available() else None

    t = Table(title=f"virgi-export fidelity on {args.scene}, {len(idx)} held-out views, {device}")
    for c in ("case", "PSNR virgi-render (mean/min)", "PSNR gsplat (mean/min)", "bake s", "write s"):
        t.add_column(c)
    for r in rows:
        t.add_row(str(r["case"]), f"{r['psnr_virgi_render']:.2f} / {r['psnr_virgi_render_min']:.2f}",
                  f"{r['psnr_gsplat']:.2f} / {r['psnr_gsplat_min']:.2f}", f"{r['bake_s']:.2f}", f"{r['write_ply_s']:.2f}")
    console.print(t)
    if timing_rows:
        t2 = Table(title=f"export time, {args.timing_gaussians:,} Gaussians, {device} (target <= 10 s)")
        for c in ("mode", "view-dependent", "bake s", "write .ply s", "total s"):
            t2.add_column(c)
        for r in timing_rows:
            t2.add_row(str(r["mode"]), f"{r['view_dependent']:,}", f"{r['bake_s']:.2f}", f"{r['write_ply_s']:.2f}",
                       f"{r['total_s']:.2f}")
        console.print(t2)
    res = {"device": device, "scene": args.scene, "config": str(cfg_path), "directions": args.directions,
           "held_out_views": len(idx),
           "camera_source": cam_source, "frame_viewmat_max_diff": frame_err, "edit_s": timing.total_s,
           "fidelity": rows, "timing": timing_rows}
    with atomic_path(args.out / "export_results.json") as tmp:
        tmp.write_text(json.dumps(res, indent=2))
    console.log(f"wrote {args.out / 'export_results.json'}")


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
