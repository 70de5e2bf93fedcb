"""Benchmark: what a render costs and what the specular gate buys, per scene, and how long the CLIs
take in a fresh process.

For each real capture of the evaluation set (trained as ``bench/edit.py`` trains it; a run under
``--train-out`` is reused), at the held-out views' own resolution:

  splatfacto SH3 / SH0  nerfstudio's own ``SplatfactoModel`` on the same Gaussians (the run's geometry SH),
                    a viewer frame of it (``get_outputs_for_camera`` on the same camera, reading rgb and
                    depth): what splatfacto's viewer pays per frame, its camera conversion and size reads,
                    Python and background handling included (:func:`splatfacto_model`)
  gsplat SH3 / SH0  gsplat's ``rasterization`` alone as splatfacto calls it (RGB+ED), the camera converted
                    outside the timed region: with degree-3 SH (splatfacto's render cost) and with one
                    colour per Gaussian (a plain SH-0 splat, the cost of a matte scene); a stricter bar
  virgi full        the model's render without the gate (MLP_spec for every visible Gaussian)
  virgi gated       the model's render (what the viewer shows) at each ``--thresholds`` value:
                    kept share, FPS, and PSNR of the gated render against the full one
  matte             the gate keeping no Gaussian (a scene the gate calls matte), against SH0

The JSON's ``ratios`` hold virgi's FPS over each baseline's: gated against splatfacto SH3 and gsplat SH3,
matte against splatfacto SH0 and gsplat SH0.

Rules chosen before measuring, with their reasons: FPS is the median over ``--repeats`` renders of
every held-out view after one warm-up render each (a viewer re-renders the same views); the
threshold sweep is fixed (0, 1/1024, 1/512, 1/255 = the default, 2/255, 4/255, 8/255), and the
default stays where it is unless it misses 45 dB gated vs full on some scene.

A virgi frame is what nerfstudio's viewer does with its default settings: ``get_outputs_for_camera``
(the model's render cache warm after the warm-up render) and reading ``rgb`` and ``depth`` (the
viewer composites depth by default); outputs it does not read are computed on access. Per scene
the JSON also splits the gated (default threshold) and matte frames into stages, each timed alone
with a sync around it (:func:`stage_ms`: the camera conversion, the cache's validity checks, the
colours per Gaussian graphed and eager, the gsplat pass alone and with the outputs around it, the
whole frame and what the stages leave out of it); and it gives the render cache's memory.

``--cli`` also times, on the first scene, ``virgi-edit list / apply / undo``, ``virgi-export`` and
``virgi-render`` as fresh processes (wall time, what a person waits), with the edit's own setup and
step times from its summary line against the same edit fitted warm in the bench's process (the first
edit of a fresh process as a multiple of a warm one), and the bare imports of torch and of torch with
nerfstudio. The run
is loaded from its files (``virgi_run.json`` beside the checkpoint, written here if training did not);
the JSON names any command that loaded it through nerfstudio instead.

    python bench/render.py --data ../shared/data --out bench_out/render --cli
"""

from __future__ import annotations

import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.table import Table

from common.evalset import COLOUR_STEPS, GEOMETRY_STEPS, capture_folder, edit_view, find
from common.results import write_json
from common.training import evalset_run, sync
from virgi_ns.errors import cli_entry

console = Console(width=200)
THRESHOLDS = (0.0, 1 / 1024, 1 / 512, 1 / 255, 2 / 255, 4 / 255, 8 / 255)


@dataclass
class Args:
    scenes: List[str] = field(default_factory=lambda: ["beercan", "fern", "cup"])
    data: Path = Path(__file__).resolve().parents[2] / "shared" / "data"
    out: Path = Path("bench_out/render")
    train_out: Path = Path("bench_out/edit_runs")
    seed: int = 42
    geometry_steps: int = GEOMETRY_STEPS
    colour_steps: int = COLOUR_STEPS
    thresholds: List[float] = field(default_factory=lambda: list(THRESHOLDS))
    repeats: int = 5
    views: int = 4
    """Held-out views measured per scene (the first ones)."""
    cli: bool = False
    """Also time the CLIs in fresh processes on the first scene."""


def _fps(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        sync()
        t = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t)
    return 1.0 / statistics.median(times)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.float() - b.float()) ** 2).mean())
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


def splat_fps(model, cam, sh_degree: Optional[int], repeats: int) -> float:
    """gsplat's rasterization of the model's Gaussians as splatfacto calls it."""
    from gsplat.rendering import rasterization

    from virgi_ns.nerfstudio.cameras import raster_cameras

    rc = raster_cameras(cam).to(model.device)
    means, quats = model.means.detach(), model.quats.detach()
    scales, opac = torch.exp(model.scales.detach()), torch.sigmoid(model.opacities.detach()).reshape(-1)
    n = means.shape[0]
    colours = torch.rand(n, 16, 3, device=means.device) if sh_degree == 3 else torch.rand(n, 3, device=means.device)
    W, H = int(rc.widths[0]), int(rc.heights[0])
    bg = model.background_color.to(model.device)

    def once():
        img, alpha, _ = rasterization(means, quats, scales, opac, colours, rc.viewmats, rc.Ks, W, H,
                                      sh_degree=sh_degree, render_mode="RGB+ED", packed=False,
                                      rasterize_mode="classic", absgrad=False, sparse_grad=False)
        return img[..., :3] + (1 - alpha) * bg

    return _fps(once, repeats)


def splatfacto_model(model, sh_degree: int = 3):
    """nerfstudio's own ``SplatfactoModel`` on the model's Gaussians, in eval mode on its device, for the
    baseline of what a viewer frame of splatfacto costs (:func:`splatfacto_frame`). It shares the
    model's Gaussian tensors (no copy); its colours are the run's own geometry SH (``features_dc`` /
    ``features_rest``, the splat the colour stage started from; zero-padded or cut to ``sh_degree``: a
    frame's cost does not depend on their values), at full degree from the first frame. Built
    offline: splatfacto constructs torchmetrics' LPIPS, which downloads AlexNet's weights where they
    are not cached (:func:`~virgi_ns.metrics.offline_splatfacto_lpips` puts a stand-in there)."""
    from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig

    from virgi_ns.metrics import offline_splatfacto_lpips

    offline_splatfacto_lpips()
    cfg = SplatfactoModelConfig(sh_degree=sh_degree, background_color=model.config.background_color,
                                rasterize_mode="classic", random_init=True, num_random=64)
    sf = SplatfactoModel(config=cfg, scene_box=model.scene_box, num_train_data=1)
    n, rest = model.num_points, (sh_degree + 1) ** 2 - 1
    have = model.features_rest.detach()
    features_rest = have.new_zeros(n, rest, 3)
    features_rest[:, : min(rest, have.shape[1])] = have[:, :rest]
    tensors = {"means": model.means, "scales": model.scales, "quats": model.quats, "opacities": model.opacities,
               "features_dc": model.features_dc, "features_rest": features_rest}
    sf.gauss_params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach(), requires_grad=False)
                                              for k, v in tensors.items()})
    sf.to(model.device).eval()
    if sh_degree > 0:
        sf.step = sh_degree * cfg.sh_degree_interval  # every SH band on, as after training
    sf.background_color = model.background_color.to(model.device)
    return sf


def splatfacto_frame(sf, cam):
    """One viewer frame of nerfstudio's splatfacto: ``get_outputs_for_camera`` (its camera conversion,
    size reads, rasterization, background and depth handling), reading rgb and depth."""
    out = sf.get_outputs_for_camera(cam)
    return out["rgb"], out["depth"]


def viewer_frame(model, cam):
    """One frame as nerfstudio's viewer renders it by default: the outputs, of which it reads rgb
    and depth."""
    out = model.get_outputs_for_camera(cam)
    return out["rgb"], out["depth"]


def _ms(fn, repeats: int) -> float:
    return 1000.0 / _fps(fn, repeats)


STAGES = ("camera", "keys", "colours", "colours_eager", "splat", "raster", "frame", "rest")
"""The stage split of a frame (see :func:`stage_ms`)."""


def frame_keys(model, gated: bool) -> None:
    """The render cache's validity checks of one frame (as :meth:`view_colours` and the gsplat pass make
    them), no colour work."""
    if gated and model.field.decoupled:
        model.render_cache.levels(model)
    model.render_cache.geometry(model)


def stage_ms(model, cams, gated: bool, repeats: int) -> Dict[str, float]:
    """Milliseconds per frame of each stage of a whole-view render, mean over ``cams``, each timed alone
    with a sync around it:

    - camera: nerfstudio's camera to gsplat's (``view_of``; on a GPU one gather, one copy to the host
      and its sync, one copy back);
    - keys: the render cache's validity checks of a frame (:func:`frame_keys`: the field's
      :class:`~virgi_ns.nerfstudio.render_cache.ModuleWatch`, the gate, edit and geometry levels), no
      colour work; ``colours`` and ``raster`` include them;
    - colours: the colours per Gaussian as the frame takes them (a CUDA graph's replay on a GPU once
      the cache state has been seen; for a matte view the checks alone: no tensor operation);
    - colours_eager: the same with ``render_cache_graphs`` off (the kernels launched one by one);
    - splat: the main gsplat pass alone (projection, tile sort, composite of colour + depth);
    - raster: ``render_view`` with reading rgb and depth (the splat and the outputs around it);
    - frame: the whole viewer frame (``get_outputs_for_camera``, reading rgb and depth);
    - rest: frame - camera - colours - raster, what the stages above leave out (Python between them).
    """
    split: Dict[str, List[float]] = {k: [] for k in STAGES}
    cfg = model.config
    for c in cams:
        view = model.view_of(c)
        for _ in range(2):  # a cache state is recorded as a graph on its second frame
            cols = model.view_colours(view, gated, transient=True)
        row = model.render_cache.background_row(model.render_cache.background(model.background_color, model.device))

        def eager():
            cfg.render_cache_graphs = False
            try:
                return model.view_colours(view, gated, transient=True)
            finally:
                cfg.render_cache_graphs = True

        def raster():
            out = model.render_view(view, cols)
            return out["rgb"], out["depth"]

        split["camera"].append(_ms(lambda: model.view_of(c), repeats))
        split["keys"].append(_ms(lambda: frame_keys(model, gated), repeats))
        split["colours"].append(_ms(lambda: model.view_colours(view, gated, transient=True), repeats))
        split["colours_eager"].append(_ms(eager, repeats))
        split["splat"].append(_ms(lambda: model._splat(view, cols.rgb.float(), row, "RGB+ED"), repeats)
                              if model._renders_with_gsplat() else math.nan)
        split["raster"].append(_ms(raster, repeats))
        split["frame"].append(_ms(lambda: viewer_frame(model, c), repeats))
        split["rest"].append(split["frame"][-1] - split["camera"][-1] - split["colours"][-1] - split["raster"][-1])
    return {k: statistics.mean(v) for k, v in split.items()}


def bench_scene(args: Args, scene, cfg_path: Path) -> dict:
    from virgi_ns.nerfstudio.runs import load_run

    _, pipeline = load_run(cfg_path)
    model = pipeline.model
    dm = pipeline.datamanager
    dm.cached_eval  # noqa: B018 - undistorts and fixes the eval cameras' intrinsics
    cams = [dm.eval_dataset.cameras[i : i + 1].to(model.device) for i in range(min(args.views, len(dm.eval_dataset)))]
    if not model.gate_ready():
        model.build_specular_gate(dm.train_raster_cameras())
    default = model.config.gate_threshold
    row: dict = {"scene": scene.name, "gaussians": int(model.num_points),
                 "size": [int(cams[0].width), int(cams[0].height)], "default_threshold": default}

    def mean_fps(fn) -> float:
        return statistics.mean(_fps(lambda c=c: fn(c), args.repeats) for c in cams)

    on_gpu = model.device.type == "cuda"  # gsplat has no CPU path: the splat columns stay empty on a CPU
    row["splat_sh3_fps"] = statistics.mean(splat_fps(model, c, 3, args.repeats) for c in cams) if on_gpu else math.nan
    row["splat_sh0_fps"] = statistics.mean(splat_fps(model, c, None, args.repeats) for c in cams) if on_gpu else math.nan
    for degree in (3, 0):  # splatfacto's own model on the same Gaussians (its get_outputs needs CUDA)
        sf = splatfacto_model(model, degree)
        row[f"splatfacto_sh{degree}_fps"] = mean_fps(lambda c: splatfacto_frame(sf, c)) if on_gpu else math.nan
        del sf
    fulls = [model.render_camera(c, gated=False)["rgb"] for c in cams]

    def full_frame(c):
        out = model.render_camera(c, gated=False)
        return out["rgb"], out["depth"]

    row["full_fps"] = mean_fps(full_frame)
    sweep = []
    for t in list(args.thresholds) + [float("inf")]:
        model.config.gate_threshold = t
        kept = float(model.spec_gate.float().mean())
        psnr = min(_psnr(model.render_camera(c, gated=True)["rgb"], f) for c, f in zip(cams, fulls))
        fps = mean_fps(lambda c: viewer_frame(model, c))
        sweep.append({"threshold": t, "kept": kept, "fps": fps, "psnr_vs_full": psnr})
        if t == default or t == float("inf"):
            name = "matte" if t == float("inf") else "gated"
            row.setdefault("stages_ms", {})[name] = stage_ms(model, cams, True, args.repeats)
            if name == "gated":
                row["cache_mib"] = {k: v / 2**20 for k, v in model.render_cache.nbytes().items()}
                # the frames above took the cached path (a stale or missing gate would take the full one)
                row["cache_served"] = model.render_cache.edit_level is not None and model.gate_ready()
        console.log(f"{scene.name}: threshold {t:.5f} keeps {kept:.1%}: {fps:.1f} FPS, {psnr:.1f} dB vs full")
    model.config.gate_threshold = default
    row["sweep"] = sweep[:-1]
    row["matte"] = sweep[-1]
    at = next(s for s in sweep if s["threshold"] == default) if default in args.thresholds else None
    if at is not None:
        row.update(gated_fps=at["fps"], kept=at["kept"], psnr_gated_vs_full=at["psnr_vs_full"])
    row["ratios"] = ratios(row)
    del pipeline, model
    torch.cuda.empty_cache()
    return row


def ratios(row: dict) -> Dict[str, float]:
    """virgi's FPS over each baseline's: the gated frame against splatfacto's model (SH3) and raw gsplat SH3,
    the matte frame against splatfacto's model with SH0 and raw gsplat SH0 (NaN where one is missing)."""
    def over(a, b):
        return a / b if a is not None and b and not math.isnan(b) else math.nan

    gated, matte = row.get("gated_fps"), row["matte"]["fps"]
    return {"gated_x_splatfacto_sh3": over(gated, row.get("splatfacto_sh3_fps")),
            "gated_x_gsplat_sh3": over(gated, row.get("splat_sh3_fps")),
            "matte_x_splatfacto_sh0": over(matte, row.get("splatfacto_sh0_fps")),
            "matte_x_gsplat_sh0": over(matte, row.get("splat_sh0_fps"))}


# ---------------------------------------------------------------------------- CLIs
def _wall(cmd: List[str], env: dict) -> tuple[float, str, str]:
    """(wall seconds, stdout, stderr) of a command in a fresh process."""
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr[-2000:]}")
    return wall, p.stdout.strip(), p.stderr


def warm_edit(model, camera, edited: torch.Tensor, photo: torch.Tensor, repeats: int = 3) -> dict:
    """The edit ``virgi-edit apply`` fits (``edited`` of ``camera``'s training ``photo``, [H,W,3] in [0,1]),
    in this warm process: a fresh engine per edit after one warm-up, median set-up and steps seconds."""
    from virgi_ns.edit.engine import EditEngine
    from virgi_ns.edit.scene import FrozenScene
    from virgi_ns.nerfstudio.cameras import raster_cameras

    scene = FrozenScene.from_model(model)
    cams = raster_cameras(camera.reshape((1,))).to(model.device)
    edited, photo = edited.to(model.device), photo.to(model.device)
    timings = []
    with torch.no_grad():
        for i in range(1 + max(1, repeats)):
            _, t = EditEngine(scene, cams, edited, original=photo).fit()
            if i > 0:
                timings.append(t)
    return {"setup_s": statistics.median(t.setup_s for t in timings),
            "steps_s": statistics.median(t.steps_s for t in timings)}


def bench_cli(scene, cfg_path: Path, data: Path, out: Path) -> dict:
    """Fresh-process walls of the CLIs on one trained run."""
    from PIL import Image

    from virgi_ns.nerfstudio.runs import load_run
    from virgi_ns.edit.recolor import recolor
    from virgi_ns.io.camera_json import CameraSpec, write_camera_json

    _, pipeline = load_run(cfg_path)
    dm = pipeline.datamanager
    names = [Path(p).name for p in dm.train_dataset.image_filenames]
    photos = [np.asarray(Image.open(p).convert("RGB")) for p in dm.train_dataset.image_filenames[:12]]
    view = edit_view([torch.from_numpy(p).float() / 255 for p in photos], scene.rule)
    edited, _ = recolor(torch.from_numpy(photos[view]).float() / 255, scene.rule)
    image = out / "cli_edited.png"
    Image.fromarray((edited.numpy() * 255 + 0.5).astype(np.uint8)).save(image)
    cam = pipeline.datamanager.train_dataset.cameras[view]
    from virgi_ns.nerfstudio.cameras import raster_cameras

    warm = warm_edit(pipeline.model, cam, edited, torch.from_numpy(photos[view]).float() / 255)
    rc = raster_cameras(cam.reshape((1,)))
    K, vm = rc.Ks[0].double().numpy(), rc.viewmats[0].double().numpy()
    spec = CameraSpec(int(rc.widths[0]), int(rc.heights[0]), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                      float(K[1, 2]), vm)
    write_camera_json(out / "cli_camera.json", spec)
    # the commands load the run from its files (virgi_ns/nerfstudio/saved_run.py) when virgi_run.json lies beside
    # its config.yml, as training writes it (earlier versions: in the checkpoint folder, which the load moves);
    # a run trained before that gets it here, so the new path is measured
    from virgi_ns.nerfstudio.run_info import run_info_of, write_run_info
    from virgi_ns.nerfstudio.saved_run import RUN_INFO, run_settings

    ckpt_dir = run_settings(cfg_path).checkpoint_dir
    written = (cfg_path.parent / RUN_INFO).is_file() or (ckpt_dir / RUN_INFO).is_file()
    run_info = "training" if written else "bench"
    if run_info == "bench":
        write_run_info(run_info_of(dm, pipeline.model), cfg_path)
    del pipeline, dm
    py = [sys.executable, "-m"]
    cfg = str(cfg_path)
    slow: List[str] = []  # commands that loaded the run through nerfstudio (their note on stderr)

    def walls_in(env: dict) -> tuple[Dict[str, float], tuple[float, float]]:
        walls: Dict[str, float] = {}

        def wall(name: str, cmd: List[str]) -> str:
            walls[name], line, err = _wall(py + cmd, env)
            if "through nerfstudio" in err and name not in slow:
                slow.append(name)
            return line

        wall("list", ["virgi_ns.cli.edit", "list", "--load-config", cfg])
        line = wall("apply", ["virgi_ns.cli.edit", "apply", "--load-config", cfg, "--image", str(image),
                              "--image-name", names[view]])
        m = re.search(r"setup ([0-9.]+) s \+ steps ([0-9.]+) s", line)
        edit = (float(m.group(1)), float(m.group(2))) if m else (float("nan"), float("nan"))
        wall("export", ["virgi_ns.cli.export", "--load-config", cfg, "--out", str(out / "cli.ply")])
        wall("render", ["virgi_ns.cli.render", str(out / "cli.ply"), "--camera", str(out / "cli_camera.json"),
                        "--out", str(out / "cli_render.png")])
        wall("undo", ["virgi_ns.cli.edit", "undo", "--load-config", cfg])
        for name, code in (("python_torch_import", "import torch"),
                           ("python_torch_nerfstudio_import", "import torch, nerfstudio.pipelines.base_pipeline")):
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], check=True, env=env)
            walls[name] = time.perf_counter() - t
        return walls, edit

    # as this machine is, and with a bytecode cache: an interpreter that cannot write its packages'
    # __pycache__ (a read-only or --no-compile install) compiles every module it imports in every
    # process; pip's usual install keeps compiled bytecode, which PYTHONPYCACHEPREFIX stands in for
    # here (one unmeasured pass fills it)
    env = dict(os.environ)
    walls, (edit_setup, edit_steps) = walls_in(env)
    cached_env = {k: v for k, v in env.items() if k != "PYTHONDONTWRITEBYTECODE"}
    # (outside --out: thousands of small files that are no result)
    cached_env["PYTHONPYCACHEPREFIX"] = str(Path(tempfile.gettempdir()) / "virgi_bench_pycache")
    walls_in(cached_env)
    cached, (cached_setup, cached_steps) = walls_in(cached_env)
    probe = subprocess.run([sys.executable, "-c", "import sys, os, torch; print(int(sys.flags.dont_write_bytecode), "
                            "int(os.access(os.path.join(os.path.dirname(torch.__file__), '__pycache__'), os.W_OK)))"],
                           capture_output=True, text=True, env=env).stdout.split()
    return {"scene": scene.name, "walls_s": walls, "edit_setup_s": edit_setup, "edit_steps_s": edit_steps,
            "walls_with_bytecode_cache_s": cached, "edit_setup_with_bytecode_cache_s": cached_setup,
            "edit_steps_with_bytecode_cache_s": cached_steps,
            "edit_warm_setup_s": warm["setup_s"], "edit_warm_steps_s": warm["steps_s"],
            "python_writes_bytecode": probe[:1] == ["0"], "torch_pycache_writable": probe[1:2] == ["1"],
            "run_info_written_by": run_info, "loaded_through_nerfstudio": slow}


# --------------------------------------------------------------------------- report
def print_tables(rows: List[dict], cli: Optional[dict], device: str) -> None:
    t = Table(title=f"render at the held-out views' size ({device})")
    for c in ("scene", "Gaussians", "size", "splatfacto SH3 FPS", "gsplat SH3 FPS", "splatfacto SH0 FPS",
              "gsplat SH0 FPS", "virgi full FPS", "virgi gated FPS", "x vs splatfacto SH3", "x vs gsplat SH3", "kept",
              "gated vs full dB", "matte FPS", "matte x vs splatfacto SH0", "matte x vs gsplat SH0", "cache MiB"):
        t.add_column(c)
    nan = float("nan")
    for r in rows:
        x = r.get("ratios") or ratios(r)
        t.add_row(r["scene"], f"{r['gaussians']:,}", "x".join(map(str, r["size"])),
                  f"{r.get('splatfacto_sh3_fps', nan):.0f}", f"{r['splat_sh3_fps']:.0f}",
                  f"{r.get('splatfacto_sh0_fps', nan):.0f}", f"{r['splat_sh0_fps']:.0f}", f"{r['full_fps']:.0f}",
                  f"{r.get('gated_fps', nan):.0f}", f"{x['gated_x_splatfacto_sh3']:.2f}", f"{x['gated_x_gsplat_sh3']:.2f}",
                  f"{r.get('kept', nan):.1%}", f"{r.get('psnr_gated_vs_full', nan):.1f}", f"{r['matte']['fps']:.0f}",
                  f"{x['matte_x_splatfacto_sh0']:.2f}", f"{x['matte_x_gsplat_sh0']:.2f}",
                  f"{sum(r.get('cache_mib', {}).values()):.1f}")
    console.print(t)
    st = Table(title="stages of a frame, ms (each timed alone; rest = frame - camera - colours - raster)")
    st.add_column("scene")
    st.add_column("frame")
    for k in STAGES:
        st.add_column(k)
    for r in rows:
        for name in ("gated", "matte"):
            d = r.get("stages_ms", {}).get(name, {})
            st.add_row(r["scene"], name, *(f"{d.get(k, float('nan')):.3f}" for k in STAGES))
    console.print(st)
    s = Table(title="gate threshold sweep: kept share, FPS, PSNR gated vs full")
    s.add_column("threshold")
    for r in rows:
        s.add_column(r["scene"])
    for i, th in enumerate(rows[0]["sweep"] if rows else []):
        s.add_row(f"{th['threshold']:.5f}", *(f"{r['sweep'][i]['kept']:.0%} {r['sweep'][i]['fps']:.0f} FPS "
                                              f"{r['sweep'][i]['psnr_vs_full']:.1f} dB" for r in rows))
    console.print(s)
    if cli is not None:
        c = Table(title=f"CLIs in a fresh process, wall seconds ({cli['scene']}; python writes bytecode: "
                        f"{cli.get('python_writes_bytecode')}, torch's __pycache__ writable: "
                        f"{cli.get('torch_pycache_writable')})")
        c.add_column("environment")
        for k in cli["walls_s"]:
            c.add_column(k)
        c.add_column("edit setup + steps")
        c.add_column("x warm edit")
        warm = cli.get("edit_warm_setup_s", math.nan) + cli.get("edit_warm_steps_s", math.nan)

        def edit_cells(setup: float, steps: float) -> tuple[str, str]:
            return f"{setup:.2f} + {steps:.2f}", f"{(setup + steps) / warm:.1f}x"

        c.add_row("as is", *(f"{v:.2f}" for v in cli["walls_s"].values()),
                  *edit_cells(cli["edit_setup_s"], cli["edit_steps_s"]))
        if "walls_with_bytecode_cache_s" in cli:
            c.add_row("bytecode cache", *(f"{v:.2f}" for v in cli["walls_with_bytecode_cache_s"].values()),
                      *edit_cells(cli["edit_setup_with_bytecode_cache_s"], cli["edit_steps_with_bytecode_cache_s"]))
        console.print(c)
        console.print(f"the same edit warm, in this process: {warm * 1e3:.0f} ms "
                      f"(set-up {cli.get('edit_warm_setup_s', math.nan) * 1e3:.0f} + steps "
                      f"{cli.get('edit_warm_steps_s', math.nan) * 1e3:.0f})")


def plot(rows: List[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        xs = [s["fps"] for s in r["sweep"]]
        ys = [min(s["psnr_vs_full"], 80.0) for s in r["sweep"]]
        ax.plot(xs, ys, "o-", label=r["scene"])
        d = next((s for s in r["sweep"] if s["threshold"] == r["default_threshold"]), None)
        if d is not None:
            ax.plot([d["fps"]], [min(d["psnr_vs_full"], 80.0)], "k*", ms=12)
        ax.axvline(r["splat_sh3_fps"], ls=":", color=ax.lines[-1].get_color())
    ax.axhline(45.0, color="grey", ls="--", lw=0.8)
    ax.set_xlabel("FPS (dotted: gsplat SH3 on the same Gaussians)")
    ax.set_ylabel("PSNR gated vs full (dB, capped at 80)")
    ax.set_title("specular gate: accuracy against speed (star: default)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(args: Args) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"
    rows, cli = [], None
    for scene in find(args.scenes):
        folder = capture_folder(scene, args.data, args.train_out / "synthetic", "cuda" if torch.cuda.is_available()
                                else "cpu", console)
        cfg_path = evalset_run(args, scene, folder)  # the edit benchmark's runs
        rows.append(bench_scene(args, scene, cfg_path))
        if args.cli and cli is None:
            cli = bench_cli(scene, cfg_path, args.data, args.out)
        write_json(args.out / "results.json", {"device": device, "args": _jsonable(vars(args)), "rows": rows, "cli": cli},
                   console)
    print_tables(rows, cli, device)
    if rows:
        plot(rows, args.out / "gate_sweep.png")


def _jsonable(d: dict) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}


def entrypoint() -> None:
    cli_entry(lambda: main(tyro.cli(Args)))


if __name__ == "__main__":
    entrypoint()
