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
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch
import tyro
from rich.console import Console
from rich.table import Table

from common.results import safe_name
from common.settings import apply_settings, split_settings, typed_like
from common.training import dataparser_for, evaluate, quiet, train
from virgi_ns.errors import InputError, atomic_path, cli_entry
from virgi_ns.metrics import offline_splatfacto_lpips

console = Console()


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
    apply_settings(cfg, ",".join(rest), "--colour-variants")
    return cfg


def _seed_suffix(seed: int, sep: str = "-") -> str:
    """Run and picture names: nothing for the first seed (42), '-seed43' etc. after it."""
    return "" if seed == 42 else f"{sep}seed{seed}"


def run_scene(args: Args, scene: str, seed: int = 42) -> List[Dict[str, object]]:
    from nerfstudio.configs.method_configs import method_configs

    from method_configs.virgi import virgi_trainer_config

    rows: List[Dict[str, object]] = []
    out = args.out

    def record(name: str, pipeline, seconds: float, parts: Dict[str, float]) -> None:
        res = evaluate(pipeline, args.fps_repeats, out / f"{scene}_{safe_name(name, '-_.')}{_seed_suffix(seed, '_')}.png")
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
        quiet(cfg, out, f"{scene}-{safe_name(name, '-_.')}{_seed_suffix(seed)}")
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
